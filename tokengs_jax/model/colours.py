"""Gaussian colours read from the input views (`ModelConfig.gaussian_colours="inputs"`).

Not in the paper or the official code. The official head regresses each Gaussian's RGB from its
token; a small model trained for minutes renders those colours smooth (half the targets' contrast
on the synthetic sets, docs/generalisation.md). Here each Gaussian instead takes the mean of the
input pixels its centre projects to, bilinearly sampled, so the render is sharp from the first
step and the colour is a function of the mean: where the views disagree (wrong depth) the sample
averages two different colours, and the photometric loss moves the mean to where they agree, a
multi-view-stereo signal the head's colours never give. Gaussians no input view sees keep the
head's colour.

Dynamic Gaussians move, and each input view was taken at its own time: a Gaussian decoded at the
target time would read, in a view taken earlier, whatever was at its present place then (the
background, where the object has moved on). With the input views' times, the model decodes the
dynamic Gaussians again at each view's time and reads view v where the Gaussian was at t_v
(`with_input_colours(dynamic_means=...)`), so one that follows an object finds it in every view,
and the colour's agreement across views supervises the trajectory.
"""

from __future__ import annotations

import flax.struct
import jax
import jax.numpy as jnp

from tokengs_jax.camera import project_points

# Camera-z below which a view does not see a Gaussian (the renderer's near plane).
NEAR = 0.025


@flax.struct.dataclass
class InputViews:
  """The input views the colours are read from.

  Attributes:
    images: [B, V, H, W, 3] RGB in [0, 1].
    world_to_camera: [B, V, 4, 4] (OpenCV).
    intrinsics: [B, V, 4] fx, fy, cx, cy in pixels.
    times: [B, V] normalised times the views were taken at (dynamic models), else None.
  """

  images: jax.Array
  world_to_camera: jax.Array
  intrinsics: jax.Array
  times: jax.Array | None = None


def bilinear_sample(images: jax.Array, uv: jax.Array) -> jax.Array:
  """Bilinear lookup with edge clamping; pixel centres at +0.5.

  Args:
    images: [B, V, H, W, C].
    uv: [B, V, N, 2] pixel coordinates (x right, y down).

  Returns:
    [B, V, N, C], differentiable in `uv` (and in `images`).
  """
  b, v, h, w, c = images.shape
  x = jnp.clip(uv[..., 0] - 0.5, 0.0, w - 1.0)
  y = jnp.clip(uv[..., 1] - 0.5, 0.0, h - 1.0)
  x0 = jnp.minimum(jnp.floor(x), w - 2.0) if w > 1 else jnp.zeros_like(x)
  y0 = jnp.minimum(jnp.floor(y), h - 2.0) if h > 1 else jnp.zeros_like(y)
  fx, fy = (x - x0)[..., None], (y - y0)[..., None]
  x0, y0 = x0.astype(jnp.int32), y0.astype(jnp.int32)
  x1, y1 = jnp.minimum(x0 + 1, w - 1), jnp.minimum(y0 + 1, h - 1)
  flat = images.reshape(b, v, h * w, c)

  def at(yi, xi):
    return jnp.take_along_axis(flat, (yi * w + xi)[..., None], axis=2)

  top = at(y0, x0) * (1.0 - fx) + at(y0, x1) * fx
  bottom = at(y1, x0) * (1.0 - fx) + at(y1, x1) * fx
  return top * (1.0 - fy) + bottom * fy


def input_colours(means: jax.Array, views: InputViews) -> tuple[jax.Array, jax.Array]:
  """Mean colour of the input pixels each Gaussian centre projects to.

  Args:
    means: [B, N, 3] world positions, or [B, V, N, 3]: each view's own positions of the N
      Gaussians (where they were when that view was taken).
    views: the input views.

  Returns:
    (colours [B, N, 3] float32: the average over the views whose image contains the projection,
    seen [B, N] bool: at least one view does). A non-finite centre is seen by no view and gets
    a zero gradient here, as the renderer culls it (design.md §8), instead of a NaN one.
  """
  h, w = views.images.shape[-3:-1]
  finite = jnp.all(jnp.isfinite(means), axis=-1)  # [B, N] or [B, V, N]
  means = jnp.where(finite[..., None], means, 0.0)
  if means.ndim == 3:
    uv, depth = project_points(means, views.world_to_camera, views.intrinsics)  # [B,V,N,(2)]
    finite = finite[:, None]
  else:  # one camera per set of positions: a view axis of 1 inside project_points
    uv, depth = project_points(
      means, views.world_to_camera[:, :, None], views.intrinsics[:, :, None]
    )
    uv, depth = uv[:, :, 0], depth[:, :, 0]
  inside = (
    finite
    & (depth > NEAR)
    & (uv[..., 0] >= 0.0)
    & (uv[..., 0] <= w)
    & (uv[..., 1] >= 0.0)
    & (uv[..., 1] <= h)
  )
  weights = inside.astype(jnp.float32)[..., None]  # [B, V, N, 1]
  samples = bilinear_sample(views.images.astype(jnp.float32), uv)
  count = jnp.sum(weights, axis=1)  # [B, N, 1]
  colours = jnp.sum(weights * samples, axis=1) / jnp.maximum(count, 1.0)
  return colours, count[..., 0] > 0


def with_input_colours(
  flat: jax.Array, views: InputViews, dynamic_means: jax.Array | None = None
) -> jax.Array:
  """flat Gaussians [B, N, 14] -> the same with RGB read from the views where any sees them.

  dynamic_means: [B, V, Nd, 3], the last Nd Gaussians' centres at each view's time (module
  docstring): each view is read where they were when it was taken. None: where they are now.
  """
  if dynamic_means is None:
    colours, seen = input_colours(flat[..., :3], views)
  else:
    first = flat.shape[1] - dynamic_means.shape[2]
    still, still_seen = input_colours(flat[:, :first, :3], views)
    moving, moving_seen = input_colours(dynamic_means, views)
    colours = jnp.concatenate([still, moving], axis=1)
    seen = jnp.concatenate([still_seen, moving_seen], axis=1)
  rgb = jnp.where(seen[..., None], colours, flat[..., 11:14])
  return jnp.concatenate([flat[..., :11], rgb], axis=-1)
