"""Exact compaction: the Gaussians that can affect no pixel of the given cameras, moved out.

A Gaussian draws nothing in a camera when the renderer culls it there (`projection`: non-finite,
centre depth outside [near, far], degenerate, opacity < 1/255, radius box off the image). Those
culled in every camera of a render cost projection and binning (whose buffer grows with N) but
change no pixel. `drawable` finds the others, conservatively: it applies the renderer's own rule
with a widened image (`MARGIN` pixels plus a 1e-3 relative share), relaxed near / far planes
and the degenerate ones kept, so that rounding in another compilation of the same maths can never
make it drop a Gaussian the renderer draws. `compact` gathers the kept Gaussians in their order
(the renderer ranks by (depth, index), so the tile lists, the compositing order and every sum are
unchanged) into a bucket of `bucket_size` (a power of two: scenes share compilations), padded
with transparent stand-ins, which the renderer culls by their opacity.

    keep = drawable(gaussians, w2c, intrinsics, height=H, width=W)          # [..., N] bool
    small = compact_for_cameras(gaussians, w2c, intrinsics, height=H, width=W)  # host-level
    out = render_exact(small, w2c, intrinsics, height=H, width=W)  # = the uncompacted images

Images, alpha and depth are those of the uncompacted render, and so are the gradients with
respect to the kept Gaussians (a dropped one's is 0 in both). Inside jit the bucket must be
static: `compact` returns whether every kept Gaussian fitted, and a caller that cannot choose
the bucket on the host renders the full set where it did not (never a silent drop).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from tokengs_jax.gaussians import Gaussians
from tokengs_jax.splatting import checks, pipeline, projection
from tokengs_jax.splatting.config import RenderConfig

MARGIN = 2.0  # pixels the image is widened by: radii are ceil()ed, so rounding can move one by 1
DEPTH_SLACK = 1e-4  # relative slack of the near / far test (float32 rounding of z is ~1e-7)
MIN_BUCKET = 256


@functools.partial(jax.jit, static_argnames=("height", "width", "config"))
def drawable(
  gaussians: Gaussians,
  world_to_camera: jax.Array,
  intrinsics: jax.Array,
  *,
  height: int,
  width: int,
  near: float = 0.025,
  far: float = 125.0,
  config: RenderConfig = RenderConfig(),
) -> jax.Array:
  """Which Gaussians some camera may draw: False only where every camera culls it for sure.

  Arguments as `render` (no background). Returns [..., N] bool over the Gaussians' own batch
  shape [...] (a set seen by several cameras, or broadcast over scenes, is kept where any of
  them may draw it). False exactly for: non-finite, opacity < `config.alpha_threshold` (both as
  the renderer tests them), or in every camera a centre clearly outside [near, far] or a radius
  box clearly off the image.
  """
  batch = checks.check_shapes(gaussians, world_to_camera, intrinsics, None, height, width)
  dtype = pipeline.compute_dtype(gaussians.means.dtype)
  cast = jax.tree.map(lambda x: jnp.asarray(x, dtype), gaussians)
  scenes = pipeline._flat_scenes(cast, batch)
  views = pipeline._flat(jnp.asarray(world_to_camera, dtype), 3, batch)
  rows = pipeline._flat(jnp.asarray(intrinsics, dtype), 2, batch)

  def one(scene, w2c, intrinsics_row):
    clean, finite = pipeline._finite_or_absent(scene)
    scale = jnp.sum(jnp.abs(clean.means), -1) * jnp.max(jnp.abs(w2c[:3, :3]))
    slack = DEPTH_SLACK * (scale + jnp.sum(jnp.abs(w2c[:3, 3])) + abs(near) + abs(far) + 1.0)
    proj = projection.project_gaussians(
      clean.means,
      clean.quats,
      clean.scales,
      clean.opacities,
      w2c,
      intrinsics_row,
      height=height,
      width=width,
      near=near - slack,
      far=far + slack,
      eps2d=config.eps2d,
      radius_sigmas=config.radius_sigmas,
      alpha_threshold=config.alpha_threshold,
      margin=MARGIN,
    )
    code = proj.cull_code
    may_draw = (code == projection.VISIBLE) | (code == projection.CULLED_DEGENERATE)
    return may_draw & finite & (clean.opacities >= config.alpha_threshold)

  per_view = jax.vmap(one, in_axes=(None, 0, 0))
  keep = jnp.any(jax.vmap(per_view)(scenes, views, rows), axis=1)  # [S, N]
  return _to_batch(keep.reshape(batch + keep.shape[-1:]), gaussians.batch_shape)


def _to_batch(keep: jax.Array, batch_shape: tuple[int, ...]) -> jax.Array:
  """[*broadcast batch, N] -> [*batch_shape, N]: any over the axes the Gaussians broadcast on."""
  extra = keep.ndim - 1 - len(batch_shape)
  keep = jnp.any(keep, axis=tuple(range(extra)))
  axes = tuple(i for i, size in enumerate(batch_shape) if size == 1 and keep.shape[i] != 1)
  return jnp.any(keep, axis=axes, keepdims=True) if axes else keep


def bucket_size(count: int, num: int, minimum: int = MIN_BUCKET) -> int:
  """The compacted size for `count` kept of `num` Gaussians: the next power of two, at least
  `minimum`; `num` where that is not smaller (compaction would not pay)."""
  size = max(minimum, 1 << max(int(count) - 1, 0).bit_length())
  return num if size >= num else size


@functools.partial(jax.jit, static_argnames=("size",))
def compact(gaussians: Gaussians, keep: jax.Array, size: int) -> tuple[Gaussians, jax.Array]:
  """The kept Gaussians of each set, in their order, padded with transparent stand-ins.

  gaussians: [..., N]; keep: [..., N] bool (`drawable`); size: static bucket.
  Returns (Gaussians [..., size], fits [] bool: every set's kept Gaussians fitted). Where `fits`
  is False some were cut: render the full set instead (`compact_for_cameras` sizes the bucket on
  the host, so it always fits). Differentiable: the gradient flows back to the kept Gaussians.
  """
  batch, num = gaussians.batch_shape, gaussians.num_gaussians
  flat = jax.tree.map(lambda x: x.reshape((-1, num) + x.shape[len(batch) + 1 :]), gaussians)
  rows = jnp.broadcast_to(keep, batch + (num,)).reshape(-1, num)
  counts = jnp.sum(rows, axis=-1)
  index = jax.vmap(lambda row: jnp.nonzero(row, size=size, fill_value=0)[0])(rows)  # [S, size]
  valid = jnp.arange(size) < counts[:, None]
  stand_in = {"opacities": 0.0, "scales": 1.0, "means": 0.0, "colors": 0.0}

  def gather(name, field):
    taken = jnp.take_along_axis(field, index.reshape(index.shape + (1,) * (field.ndim - 2)), 1)
    mask = valid.reshape(valid.shape + (1,) * (field.ndim - 2))
    if name == "quats":
      pad = jnp.zeros_like(taken).at[..., 0].set(1.0)
    else:
      pad = jnp.full_like(taken, stand_in[name])
    return jnp.where(mask, taken, pad)

  out = Gaussians(**{name: gather(name, getattr(flat, name)) for name in _FIELDS})
  out = jax.tree.map(lambda x: x.reshape(batch + x.shape[1:]), out)
  return out, jnp.all(counts <= size)


_FIELDS = ("means", "opacities", "scales", "quats", "colors")


def compact_for_cameras(
  gaussians: Gaussians,
  world_to_camera,
  intrinsics,
  *,
  height: int,
  width: int,
  near: float = 0.025,
  far: float = 125.0,
  config: RenderConfig = RenderConfig(),
  minimum: int = MIN_BUCKET,
) -> Gaussians:
  """Host-level: the Gaussians the cameras may draw, compacted to a bucket sized on the host.

  Arguments as `drawable`. Returns Gaussians [..., size] with `size = bucket_size(most kept in
  one set, N, minimum)`, or `gaussians` itself where that is not smaller than N. Renders of the
  result at these cameras equal those of `gaussians` (call outside jit: it reads the count).
  """
  keep = drawable(
    gaussians, world_to_camera, intrinsics, height=height, width=width, near=near, far=far,
    config=config,
  )  # fmt: skip
  num = gaussians.num_gaussians
  count = int(np.max(np.sum(np.asarray(keep), axis=-1), initial=0))
  size = bucket_size(count, num, minimum)
  if size >= num:
    return gaussians
  compacted, fits = compact(gaussians, keep, size)
  assert bool(fits)  # the bucket holds the largest count by construction
  return compacted
