"""`render`: project, cull, bin into tiles, composite; batched over scenes and cameras."""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp

from tokengs_jax.gaussians import Gaussians
from tokengs_jax.splatting import binning, projection, rasterize
from tokengs_jax.splatting.config import RenderConfig, RenderResult, RenderStats

_DEPTH_ALPHA_FLOOR = 1e-10  # gsplat's clamp in D / alpha for "ED" depth


def compute_dtype(dtype) -> jnp.dtype:
  """float32 for half types (bf16 / f16 inputs are upcast), float64 kept when x64 is on."""
  return jnp.promote_types(dtype, jnp.float32)


def tiles_to_image(values: jax.Array, tiling: rasterize.Tiling) -> jax.Array:
  """[T, P, C] per-tile pixels -> [H, W, C] image (padding pixels of edge tiles dropped)."""
  ts = tiling.tile_size
  grid = values.reshape(tiling.tiles_y, tiling.tiles_x, ts, ts, values.shape[-1])
  image = grid.transpose(0, 2, 1, 3, 4).reshape(tiling.tiles_y * ts, tiling.tiles_x * ts, -1)
  return image[:tiling.height, :tiling.width]


def _render_camera(gaussians: Gaussians, world_to_camera, intrinsics, background, near, far, *,
                   height: int, width: int, config: RenderConfig) -> RenderResult:
  """One scene [N] seen by one camera: w2c [4, 4], intrinsics [4], background [3]."""
  num = gaussians.num_gaussians
  dtype = gaussians.means.dtype
  proj = projection.project_gaussians(
      gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities, world_to_camera,
      intrinsics, height=height, width=width, near=near, far=far, eps2d=config.eps2d,
      radius_sigmas=config.radius_sigmas, alpha_threshold=config.alpha_threshold)
  tiles_x, tiles_y = -(-width // config.tile_size), -(-height // config.tile_size)
  tiling = rasterize.Tiling(height, width, config.tile_size, tiles_x, tiles_y, config.chunk_size,
                            min(config.tiles_per_step, tiles_x * tiles_y), config.max_alpha,
                            config.alpha_threshold, config.transmittance_stop)
  budget = config.intersection_budget(num)
  visible = proj.cull_code == projection.VISIBLE

  if num:
    bins = binning.bin_gaussians(proj.means2d, proj.radii, proj.depths, visible,
                                 tile_size=config.tile_size, tiles_x=tiles_x, tiles_y=tiles_y,
                                 budget=budget)
    attrs = jnp.concatenate([proj.means2d, proj.conics, gaussians.opacities[:, None],
                             gaussians.colors, proj.depths[:, None]], axis=-1)
    accum, transmittance, chunks = rasterize.rasterize_tiles(
        attrs, bins.gaussian_ids, bins.tile_starts, bins.tile_ends, tiling)
    accum = tiles_to_image(accum, tiling)
    transmittance = tiles_to_image(transmittance[..., None], tiling)
    num_intersections = bins.num_intersections
    tile_chunks = jnp.sum(chunks).astype(jnp.int32)
  else:  # an empty scene: nothing to bin, the image is the background
    accum = jnp.zeros((height, width, 4), dtype)
    transmittance = jnp.ones((height, width, 1), dtype)
    tile_chunks = num_intersections = jnp.zeros((), jnp.int32)

  alpha = 1.0 - transmittance
  rgb = accum[..., :3] + transmittance * background
  depth = accum[..., 3:] / jnp.maximum(alpha, _DEPTH_ALPHA_FLOOR)

  def count(code):
    return jnp.sum(proj.cull_code == code).astype(jnp.int32)

  stats = RenderStats(
      num_culled_depth=count(projection.CULLED_DEPTH),
      num_culled_degenerate=count(projection.CULLED_DEGENERATE),
      num_culled_opacity=count(projection.CULLED_OPACITY),
      num_culled_frustum=count(projection.CULLED_FRUSTUM),
      num_visible=count(projection.VISIBLE),
      num_intersections=num_intersections,
      budget=jnp.asarray(budget, jnp.int32),
      overflow=num_intersections > budget,
      tile_chunks=tile_chunks,
  )
  return RenderResult(rgb=rgb, alpha=alpha, depth=depth, means2d=proj.means2d,
                      radii=proj.radii.astype(jnp.int32), depths=proj.depths, stats=stats)


@functools.partial(jax.jit, static_argnames=("height", "width", "config"))
def render(gaussians: Gaussians, world_to_camera: jax.Array, intrinsics: jax.Array, *, height: int,
           width: int, background: jax.Array | None = None, near: float = 0.025, far: float = 125.0,
           config: RenderConfig = RenderConfig()) -> RenderResult:
  """Renders Gaussians with gsplat 1.5.3 semantics (`rasterization(render_mode="RGB+ED")`).

  Differentiable w.r.t. every Gaussian field (and the cameras); jit-compiled (height, width and
  config are static). Inputs in bf16/f16 are computed in float32, float64 stays float64 (x64), and
  the outputs come in that compute dtype.

  Args:
    gaussians: batch shape [...], N Gaussians.
    world_to_camera: [..., V, 4, 4] OpenCV world-to-camera poses.
    intrinsics: [..., V, 4] (fx, fy, cx, cy) in pixels.
    height, width: image size in pixels.
    background: None (black), [3] or [..., V, 3] colour composited behind the Gaussians.
    near, far: a Gaussian whose centre depth is outside [near, far] is culled.
    config: RenderConfig.

  Returns:
    RenderResult with rgb [..., V, H, W, 3], alpha and depth [..., V, H, W, 1], means2d
    [..., V, N, 2], radii [..., V, N, 2], depths [..., V, N] and per-camera stats [..., V].
  """
  dtype = compute_dtype(gaussians.means.dtype)
  gaussians = jax.tree.map(lambda x: jnp.asarray(x, dtype), gaussians)
  world_to_camera = jnp.asarray(world_to_camera, dtype)
  intrinsics = jnp.asarray(intrinsics, dtype)
  num_views = world_to_camera.shape[-3]
  batch = jnp.broadcast_shapes(gaussians.batch_shape, world_to_camera.shape[:-3],
                               intrinsics.shape[:-2])
  if background is None:
    background = jnp.zeros((3,), dtype)
  background = jnp.broadcast_to(jnp.asarray(background, dtype), batch + (num_views, 3))

  def flat(x, tail):
    tail_shape = x.shape[x.ndim - tail:]
    return jnp.broadcast_to(x, batch + tail_shape).reshape((math.prod(batch),) + tail_shape)

  scenes = Gaussians(means=flat(gaussians.means, 2), opacities=flat(gaussians.opacities, 1),
                     scales=flat(gaussians.scales, 2), quats=flat(gaussians.quats, 2),
                     colors=flat(gaussians.colors, 2))
  one = functools.partial(_render_camera, height=height, width=width, config=config)
  per_view = jax.vmap(one, in_axes=(None, 0, 0, 0, None, None))
  per_scene = jax.vmap(per_view, in_axes=(0, 0, 0, 0, None, None))
  out = per_scene(scenes, flat(world_to_camera, 3), flat(intrinsics, 2), flat(background, 2),
                  near, far)
  return jax.tree.map(lambda x: x.reshape(batch + x.shape[1:]), out)


def scene_budget_hint(num_intersections: int, config: RenderConfig = RenderConfig()) -> int:
  """An explicit `max_intersections` that fits a measured `stats.num_intersections` with 25% room."""
  return config.chunk_size * math.ceil(1.25 * num_intersections / config.chunk_size)
