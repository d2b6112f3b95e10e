"""`render`: project, cull, bin into tiles, composite; batched over scenes and cameras."""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from tokengs_jax.gaussians import Gaussians
from tokengs_jax.splatting import binning, checks, projection, rasterize
from tokengs_jax.splatting.config import RenderConfig, RenderResult, RenderStats

_DEPTH_ALPHA_FLOOR = 1e-10  # gsplat's clamp in D / alpha for "ED" depth
# Sub-tile lists pay when Gaussians are small against a tile; with many (Gaussian, tile) pairs per
# Gaussian they reach nearly every sub-tile and the split is pure cost (65k at 256², loaded: -40%
# CPU fwd+bwd at 2.8 pairs per Gaussian, +25% at 11.3; docs/benchmarks.md, "Renderer"). Counted
# per drawn Gaussian: culled ones (and a compaction's padding) do not dilute it (issue 27).
_SPLIT_MAX_PAIRS_PER_GAUSSIAN = 6
# Or where lists are short: the split costs every listed pair but saves only on what is composited
# before pixels saturate, most of a short list (65k fine at 1024²: 11.1 pairs per Gaussian, 178 a
# tile, -34% fwd+bwd; TokenGS-like, >= 1,200 a tile: no gain; "Pixel scaling at 1024²").
_SPLIT_MAX_PAIRS_PER_TILE = 512


def _split_pays(pairs, drawn, tiles) -> jax.Array:
  """Whether to split the lists into sub-tiles: [] bool from the radius boxes' (Gaussian, tile)
  pairs, the drawn Gaussians and the tiles ([] each, summed over the cameras binned together)."""
  per_gaussian = pairs <= _SPLIT_MAX_PAIRS_PER_GAUSSIAN * drawn
  return per_gaussian | (pairs <= _SPLIT_MAX_PAIRS_PER_TILE * tiles)


def _split_pays_for(cameras: _Camera, tiles_per_camera: int) -> jax.Array:
  """`_split_pays` of C cameras [C, ...] binned together."""
  drawn = jnp.sum(cameras.proj.cull_code == projection.VISIBLE)
  tiles = cameras.box_pairs.shape[0] * tiles_per_camera
  return _split_pays(jnp.sum(cameras.box_pairs), drawn, tiles)


def compute_dtype(dtype) -> jnp.dtype:
  """float32 for half types (bf16 / f16 inputs are upcast), float64 kept when x64 is on."""
  return jnp.promote_types(dtype, jnp.float32)


def tiles_to_image(values: jax.Array, tiling: rasterize.Tiling) -> jax.Array:
  """[T, P, C] per-tile pixels -> [H, W, C] image (padding pixels of edge tiles dropped)."""
  ts = tiling.tile_size
  grid = values.reshape(tiling.tiles_y, tiling.tiles_x, ts, ts, values.shape[-1])
  image = grid.transpose(0, 2, 1, 3, 4).reshape(tiling.tiles_y * ts, tiling.tiles_x * ts, -1)
  return image[: tiling.height, : tiling.width]


class _Camera(NamedTuple):
  """What one camera's projection and binning hand to the shared compositor."""

  proj: projection.Projected
  attrs: jax.Array  # [N, 6 + 4] compositor attributes (geometry, rgb, depth)
  box_pairs: jax.Array  # [] int32 (Gaussian, tile) pairs of the radius boxes
  bins: binning.TileBins | None  # None until binned, and for an empty scene


def _finite_or_absent(gaussians: Gaussians) -> tuple[Gaussians, jax.Array]:
  """Replaces Gaussians with a NaN / inf in any field by a transparent stand-in.

  The double-where keeps a bad Gaussian local: every later op sees finite numbers, so the
  backward has no 0 * NaN to spread into its neighbours' gradients, and its own gradient is 0.
  gaussians: one scene [N] -> (sanitised Gaussians [N], finite [N] bool).
  """
  finite = jnp.all(jnp.isfinite(gaussians.means), axis=-1) & jnp.isfinite(gaussians.opacities)
  for field in (gaussians.scales, gaussians.quats, gaussians.colors):
    finite &= jnp.all(jnp.isfinite(field), axis=-1)
  stand_in = Gaussians(
    means=jnp.zeros_like(gaussians.means),
    opacities=jnp.zeros_like(gaussians.opacities),
    scales=jnp.ones_like(gaussians.scales),
    quats=jnp.zeros_like(gaussians.quats).at[:, 0].set(1.0),
    colors=jnp.zeros_like(gaussians.colors),
  )
  pick = lambda good, bad: jnp.where(
    finite.reshape(finite.shape + (1,) * (good.ndim - 1)), good, bad
  )
  return jax.tree.map(pick, gaussians, stand_in), finite


def _project(
  gaussians: Gaussians,
  world_to_camera,
  intrinsics,
  near,
  far,
  *,
  height: int,
  width: int,
  config: RenderConfig,
) -> _Camera:
  """One scene [N] seen by one camera (w2c [4, 4], intrinsics [4]): projection and culling."""
  gaussians, finite = _finite_or_absent(gaussians)
  proj = projection.project_gaussians(
    gaussians.means,
    gaussians.quats,
    gaussians.scales,
    gaussians.opacities,
    world_to_camera,
    intrinsics,
    height=height,
    width=width,
    near=near,
    far=far,
    eps2d=config.eps2d,
    radius_sigmas=config.radius_sigmas,
    alpha_threshold=config.alpha_threshold,
  )
  proj = dataclasses.replace(
    proj,
    cull_code=jnp.where(finite, proj.cull_code, projection.CULLED_NONFINITE),
    radii=jnp.where(finite[:, None], proj.radii, 0.0),
  )
  attrs = jnp.concatenate(
    [
      proj.means2d,
      proj.conics,
      gaussians.opacities[:, None],
      gaussians.colors,
      proj.depths[:, None],
    ],
    axis=-1,
  )
  counts, _ = binning.box_counts(
    proj.means2d,
    proj.radii,
    proj.cull_code == projection.VISIBLE,
    tile_size=config.tile_size,
    tiles_x=-(-width // config.tile_size),
    tiles_y=-(-height // config.tile_size),
  )
  return _Camera(proj, attrs, jnp.sum(counts), None)


def _bin(
  cameras: _Camera, *, height: int, width: int, config: RenderConfig, ladder: tuple[int, ...]
) -> binning.TileBins:
  """Tile lists of C cameras [C, ...], sorted at the smallest ladder size that holds them all.

  Sorting dominates binning and grows with the buffer, so a scene needing few pairs sorts a small
  buffer; the lists are split into sub-tiles (`config.subtile_size`) where that pays
  (`_split_pays`), else each sub-tile reads its tile's list, and padded to the full budget
  (times the sub-tiles per tile; the compositor never reads the padding).
  Under `jax.vmap(render)` the switch turns into running every size (correct, slower).
  """
  budget = ladder[-1]
  tiling = dict(
    tiles_x=-(-width // config.tile_size),
    tiles_y=-(-height // config.tile_size),
    height=height,
    width=width,
    alpha_threshold=config.alpha_threshold,
  )

  parts = (config.tile_size // config.subtile_size) ** 2

  def split_one(camera, bins):
    proj = camera.proj
    opacities = camera.attrs[:, rasterize.OPACITY]
    return binning.split_tiles(
      bins,
      proj.means2d,
      proj.conics,
      opacities,
      tile_size=config.tile_size,
      subtile_size=config.subtile_size,
      **tiling,
    )

  def share_one(camera, bins):
    del camera
    shared = binning.share_tiles(
      bins,
      tile_size=config.tile_size,
      subtile_size=config.subtile_size,
      tiles_x=tiling["tiles_x"],
      height=height,
      width=width,
    )
    ids = jnp.pad(shared.gaussian_ids, (0, (parts - 1) * shared.gaussian_ids.shape[0]))
    return dataclasses.replace(shared, gaussian_ids=ids)

  def bin_at(size):
    def bin_one(camera):
      proj = camera.proj
      return binning.bin_gaussians(
        proj.means2d,
        proj.radii,
        proj.depths,
        proj.cull_code == projection.VISIBLE,
        proj.conics,
        camera.attrs[:, rasterize.OPACITY],
        tile_size=config.tile_size,
        budget=size,
        **tiling,
      )

    def run(cameras):
      bins = jax.vmap(bin_one)(cameras)
      if parts > 1:
        small = _split_pays_for(cameras, tiling["tiles_x"] * tiling["tiles_y"])
        bins = jax.lax.cond(small, jax.vmap(split_one), jax.vmap(share_one), cameras, bins)
      pad = parts * budget - bins.gaussian_ids.shape[-1]
      return dataclasses.replace(bins, gaussian_ids=jnp.pad(bins.gaussian_ids, ((0, 0), (0, pad))))

    return run

  branches = [bin_at(size) for size in ladder]
  if len(branches) == 1:
    return branches[0](cameras)
  needed = jnp.max(cameras.box_pairs)
  step = jnp.sum(needed > jnp.asarray(ladder[:-1], needed.dtype))
  return jax.lax.switch(step, branches, cameras)


def _bin_and_composite_rebinning(
  cameras: _Camera, *, height: int, width: int, config: RenderConfig, ladder: tuple[int, ...]
):
  """`RenderConfig.rebin_on_overflow`: bin at the smallest ladder size even when the pairs exceed
  it, composite, and only where that cut could change a pixel (some camera's `overflow`) bin
  again at the size that holds them all and composite that (`lax.cond`).

  -> (cameras with the first binning's lists, `_composite`'s result of the render used).
  """
  first = cameras._replace(
    bins=_bin(cameras, height=height, width=width, config=config, ladder=ladder[:1])
  )
  composited = _composite(first, height=height, width=width, config=config)

  def rebin(_):
    full = cameras._replace(
      bins=_bin(cameras, height=height, width=width, config=config, ladder=ladder)
    )
    return _composite(full, height=height, width=width, config=config)

  return first, jax.lax.cond(jnp.any(composited[3]), rebin, lambda _: composited, None)


def _composite(cameras: _Camera, *, height: int, width: int, config: RenderConfig):
  """Composites C cameras at once: their tile lists are concatenated into one flat tile axis.

  One compositor call (rather than a vmap over cameras) keeps the while loops unbatched: a
  batched while loop selects over its whole carried state every step, which costs more than the
  compositing itself. It also shares one compacted work list across all cameras' tiles.

  Returns (accumulated features [C, H, W, 4], transmittance [C, H, W, 1], tile chunks [C], lossy
  [C]: some tile lost pairs to the budget and did not saturate before its list ran out).
  """
  num_cameras, num = cameras.attrs.shape[:2]
  tiles_x, tiles_y = -(-width // config.subtile_size), -(-height // config.subtile_size)
  num_tiles = tiles_x * tiles_y
  tiling = rasterize.Tiling(
    height,
    width,
    config.subtile_size,
    tiles_x,
    tiles_y,
    num_cameras,
    config.chunk_size,
    min(config.tiles_per_step, num_cameras * num_tiles),
    config.max_alpha,
    config.alpha_threshold,
    config.transmittance_stop,
    pixel_major=config.pixel_major,
  )
  if cameras.bins is None:  # an empty scene: nothing to bin, the image is the background
    dtype = cameras.attrs.dtype
    return (
      jnp.zeros((num_cameras, height, width, 4), dtype),
      jnp.ones((num_cameras, height, width, 1), dtype),
      jnp.zeros((num_cameras,), jnp.int32),
      jnp.zeros((num_cameras,), bool),
    )
  camera = jnp.arange(num_cameras, dtype=jnp.int32)[:, None]
  bins = cameras.bins
  length = bins.gaussian_ids.shape[-1]
  accum, transmittance, chunks, saturated = rasterize.rasterize_tiles(
    cameras.attrs.reshape(num_cameras * num, -1),
    (bins.gaussian_ids + camera * num).reshape(-1),
    (bins.tile_starts + camera * length).reshape(-1),
    (bins.tile_ends + camera * length).reshape(-1),
    tiling,
    jnp.any(bins.shared_lists),
  )
  split = lambda x: x.reshape((num_cameras, num_tiles) + x.shape[1:])
  to_images = jax.vmap(functools.partial(tiles_to_image, tiling=tiling))
  return (
    to_images(split(accum)),
    to_images(split(transmittance)[..., None]),
    jnp.sum(split(chunks), axis=-1).astype(jnp.int32),
    jnp.any(bins.tile_truncated & ~split(saturated), axis=-1),
  )


def _finish(
  cameras: _Camera, accum, transmittance, tile_chunks, lossy, background, budget
) -> RenderResult:
  """Per-camera images and stats from the compositor's sums (each array with a leading [C])."""
  proj = cameras.proj
  alpha = 1.0 - transmittance
  rgb = accum[..., :3] + transmittance * background[:, None, None, :]
  depth = accum[..., 3:] / jnp.maximum(alpha, _DEPTH_ALPHA_FLOOR)

  def count(code):
    return jnp.sum(proj.cull_code == code, axis=-1).astype(jnp.int32)

  if cameras.bins is None:
    num_intersections = jnp.zeros(tile_chunks.shape, jnp.int32)
  else:
    num_intersections = cameras.bins.num_intersections
  stats = RenderStats(
    num_culled_nonfinite=count(projection.CULLED_NONFINITE),
    num_culled_depth=count(projection.CULLED_DEPTH),
    num_culled_degenerate=count(projection.CULLED_DEGENERATE),
    num_culled_opacity=count(projection.CULLED_OPACITY),
    num_culled_frustum=count(projection.CULLED_FRUSTUM),
    num_visible=count(projection.VISIBLE),
    num_intersections=num_intersections,
    budget=jnp.full(tile_chunks.shape, budget, jnp.int32),
    truncated=num_intersections > budget,
    overflow=lossy,
    tile_chunks=tile_chunks,
  )
  return RenderResult(
    rgb=rgb,
    alpha=alpha,
    depth=depth,
    means2d=proj.means2d,
    radii=proj.radii.astype(jnp.int32),
    depths=proj.depths,
    stats=stats,
  )


def render(
  gaussians: Gaussians,
  world_to_camera: jax.Array,
  intrinsics: jax.Array,
  *,
  height: int,
  width: int,
  background: jax.Array | None = None,
  near: float = 0.025,
  far: float = 125.0,
  config: RenderConfig = RenderConfig(),
) -> RenderResult:
  """Renders Gaussians with gsplat 1.5.3 semantics (`rasterization(render_mode="RGB+ED")`).

  Differentiable w.r.t. every Gaussian field (and the cameras); jit-compiled (height, width and
  config are static). Batch through the leading dimensions rather than `jax.vmap(render)`: all
  cameras then share one unbatched compositor loop, while a vmap turns its while loops into
  batched ones that copy their whole state every step (measured 2x slower forward+backward) and
  its per-step choice of block size into running every size.
  Inputs in bf16/f16 are computed in float32, float64 stays float64 (x64), and
  the outputs come in that compute dtype. Matmuls run at full float32 precision (`PRECISION`).

  The (Gaussian, tile) buffer has a static size (`config`); a scene that needs more is reported in
  `stats.overflow`. Inside jit read that flag (training logs it); outside jit an overflowed
  result also warns (`RenderBudgetWarning`, which waits for the render to read the flag). For a
  result that must be exact (evaluation, export) call `render_exact`, which re-renders with a
  larger buffer.

  Bad values: a Gaussian with a NaN / inf in any field is rendered as absent (counted in
  `stats.num_culled_nonfinite`) and its gradient is 0; the others render as without it.
  Shapes, dtypes and sizes are checked at trace time (ValueError naming the argument). Camera
  values are checked where they are concrete (outside jit, vmap, grad): a NaN / inf in
  world_to_camera or intrinsics, or fx, fy <= 0, is a ValueError naming the field and camera.
  Traced cameras are not checked (their values do not exist yet): such a camera renders what its
  values give (a NaN one: the background, every Gaussian culled).

  Args:
    gaussians: batch shape [...], N Gaussians.
    world_to_camera: [..., V, 4, 4] OpenCV world-to-camera poses (the view axis is required).
    intrinsics: [..., V, 4] (fx, fy, cx, cy) in pixels, one row per view; never a K matrix
      (convert with `camera.intrinsics_from_matrix`). A [..., 3, 3] K is refused by its shape;
      a 4x4 K has the shape of four views' rows, and is refused (where concrete) by its zero
      focal lengths.
    height, width: image size in pixels (positive ints).
    background: None (black), [3] or [..., V, 3] colour composited behind the Gaussians.
    near, far: a Gaussian whose centre depth is outside [near, far] is culled.
    config: RenderConfig.

  Returns:
    RenderResult with rgb [..., V, H, W, 3], alpha and depth [..., V, H, W, 1], means2d
    [..., V, N, 2], radii [..., V, N, 2], depths [..., V, N] and per-camera stats [..., V].
  """
  out = jitted_render(
    gaussians,
    world_to_camera,
    intrinsics,
    height=height,
    width=width,
    background=background,
    near=near,
    far=far,
    config=config,
  )
  checks.check_cameras(world_to_camera, intrinsics)  # after the trace has checked their shapes
  checks.warn_if_overflowed(out.stats)
  return out


@functools.partial(jax.jit, static_argnames=("height", "width", "config"))
def jitted_render(
  gaussians: Gaussians,
  world_to_camera: jax.Array,
  intrinsics: jax.Array,
  *,
  height: int,
  width: int,
  background: jax.Array | None = None,
  near: float = 0.025,
  far: float = 125.0,
  config: RenderConfig = RenderConfig(),
) -> RenderResult:
  """`render` without its host-side checks (the camera values, the overflow warning): the
  compiled program, whose arguments and result are `render`'s (`render_exact` re-renders with it).
  """
  batch = checks.check_shapes(gaussians, world_to_camera, intrinsics, background, height, width)
  dtype = compute_dtype(gaussians.means.dtype)
  gaussians = jax.tree.map(lambda x: jnp.asarray(x, dtype), gaussians)
  world_to_camera = jnp.asarray(world_to_camera, dtype)
  intrinsics = jnp.asarray(intrinsics, dtype)
  num_views = world_to_camera.shape[-3]
  if background is None:
    background = jnp.zeros((3,), dtype)
  background = jnp.broadcast_to(jnp.asarray(background, dtype), batch + (num_views, 3))

  scenes = _flat_scenes(gaussians, batch)
  cameras = _project_cameras(
    scenes,
    _flat(world_to_camera, 3, batch),
    _flat(intrinsics, 2, batch),
    near,
    far,
    height=height,
    width=width,
    config=config,
  )
  tiles = -(-height // config.tile_size) * -(-width // config.tile_size)
  ladder = config.budget_ladder(scenes.num_gaussians, tiles)
  if scenes.num_gaussians and config.rebin_on_overflow and len(ladder) > 1:
    cameras, composited = _bin_and_composite_rebinning(
      cameras, height=height, width=width, config=config, ladder=ladder
    )
  else:
    if scenes.num_gaussians:
      cameras = cameras._replace(
        bins=_bin(cameras, height=height, width=width, config=config, ladder=ladder)
      )
    composited = _composite(cameras, height=height, width=width, config=config)
  out = _finish(
    cameras, *composited, background=_flat(background, 2, batch).reshape(-1, 3), budget=ladder[-1]
  )
  out = jax.tree.map(lambda x: x.reshape((math.prod(batch), num_views) + x.shape[1:]), out)
  return jax.tree.map(lambda x: x.reshape(batch + x.shape[1:]), out)


def _flat(x: jax.Array, tail: int, batch: tuple[int, ...]) -> jax.Array:
  """[..., *tail] broadcast to `batch` [...] -> [S, *tail], the batch as one scene axis S."""
  tail_shape = x.shape[x.ndim - tail :]
  return jnp.broadcast_to(x, batch + tail_shape).reshape((math.prod(batch),) + tail_shape)


def _flat_scenes(gaussians: Gaussians, batch: tuple[int, ...]) -> Gaussians:
  """Gaussians broadcast to `batch` [...] -> S scenes [S, N]."""
  return Gaussians(
    means=_flat(gaussians.means, 2, batch),
    opacities=_flat(gaussians.opacities, 1, batch),
    scales=_flat(gaussians.scales, 2, batch),
    quats=_flat(gaussians.quats, 2, batch),
    colors=_flat(gaussians.colors, 2, batch),
  )


def _project_cameras(
  scenes: Gaussians,
  world_to_camera,
  intrinsics,
  near,
  far,
  *,
  height: int,
  width: int,
  config: RenderConfig,
) -> _Camera:
  """S scenes [S, N] seen by their V views (w2c [S, V, 4, 4], intrinsics [S, V, 4]): `_project`
  of every (scene, view), on one camera axis C = S * V for binning and the compositor."""
  one = functools.partial(_project, height=height, width=width, config=config)
  per_view = jax.vmap(one, in_axes=(None, 0, 0, None, None))
  per_scene = jax.vmap(per_view, in_axes=(0, 0, 0, None, None))
  cameras = per_scene(scenes, world_to_camera, intrinsics, near, far)
  return jax.tree.map(lambda x: x.reshape((x.shape[0] * x.shape[1],) + x.shape[2:]), cameras)
