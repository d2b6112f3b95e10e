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

Seen from a camera (`ModelConfig.input_colour_weights="viewer"`, not in the paper either), the
views are not averaged but weighted by how close each view's ray through the Gaussian is to the
viewer's ray (the unstructured-lumigraph rule of image-based rendering: a softmax of the rays'
cosine at `ModelConfig.viewer_colour_sharpness`). A view averaged in from far away brings the
colour of another side of the surface, of an occluder, or of an object that moved away; the
view whose ray nearly coincides with the viewer's shows what the viewer sees. Colours become
view-dependent, as spherical harmonics are, and the Gaussians of one scene come as one set per
viewing camera.
"""

from __future__ import annotations

import flax.struct
import jax
import jax.numpy as jnp

from tokengs_jax.camera import invert_rigid, project_points
from tokengs_jax.math import safe_normalize

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


def _sampled(means: jax.Array, views: InputViews) -> tuple[jax.Array, jax.Array, jax.Array]:
  """Every view's sample at each Gaussian's projection.

  Args:
    means: [B, N, 3] world positions, or [B, V, N, 3]: each view's own positions of the N
      Gaussians (where they were when that view was taken).

  Returns:
    (samples [B, V, N, 3] float32, inside [B, V, N] bool: the view's image contains the
    projection, positions [B, V, N, 3]: where view v saw the Gaussian, non-finite ones at 0).
    A non-finite centre is inside no view and gets a zero gradient here, as the renderer culls
    it (design.md §8), instead of a NaN one.
  """
  h, w = views.images.shape[-3:-1]
  finite = jnp.all(jnp.isfinite(means), axis=-1)  # [B, N] or [B, V, N]
  means = jnp.where(finite[..., None], means, 0.0)
  if means.ndim == 3:
    uv, depth = project_points(means, views.world_to_camera, views.intrinsics)  # [B,V,N,(2)]
    finite = finite[:, None]
    positions = jnp.broadcast_to(means[:, None], uv.shape[:-1] + (3,))
  else:  # one camera per set of positions: a view axis of 1 inside project_points
    uv, depth = project_points(
      means, views.world_to_camera[:, :, None], views.intrinsics[:, :, None]
    )
    uv, depth, positions = uv[:, :, 0], depth[:, :, 0], means
  inside = (
    finite
    & (depth > NEAR)
    & (uv[..., 0] >= 0.0)
    & (uv[..., 0] <= w)
    & (uv[..., 1] >= 0.0)
    & (uv[..., 1] <= h)
  )
  return bilinear_sample(views.images.astype(jnp.float32), uv), inside, positions


def input_colours(means: jax.Array, views: InputViews) -> tuple[jax.Array, jax.Array]:
  """Mean colour of the input pixels each Gaussian centre projects to.

  Args:
    means: [B, N, 3] world positions, or [B, V, N, 3]: each view's own positions of the N
      Gaussians (where they were when that view was taken).
    views: the input views.

  Returns:
    (colours [B, N, 3] float32: the average over the views whose image contains the projection,
    seen [B, N] bool: at least one view does).
  """
  samples, inside, _ = _sampled(means, views)
  weights = inside.astype(jnp.float32)[..., None]  # [B, V, N, 1]
  count = jnp.sum(weights, axis=1)  # [B, N, 1]
  colours = jnp.sum(weights * samples, axis=1) / jnp.maximum(count, 1.0)
  return colours, count[..., 0] > 0


def viewer_colours(
  means: jax.Array, views: InputViews, present: jax.Array, viewers: jax.Array, sharpness: float
) -> tuple[jax.Array, jax.Array]:
  """Colours as seen from `viewers`: each view's sample weighted by how close its ray through the
  Gaussian is to the viewer's (the unstructured-lumigraph rule; module docstring).

  Weight of view v for a Gaussian seen from viewer c: softmax over the views that contain its
  projection of `sharpness * cos(angle between x_v - o_v and x - c)`, with o_v the view's
  centre, x_v where view v saw the Gaussian and x where it is now.

  Args:
    means: as `input_colours`.
    views: the input views.
    present: [B, N, 3] where the Gaussians are at the time they are rendered.
    viewers: [B, T, 3] centres of the cameras the Gaussians are rendered from.
    sharpness: the softmax's inverse temperature (large: the nearest ray's view alone).

  Returns:
    (colours [B, T, N, 3] float32, seen [B, N] bool).
  """
  samples, inside, positions = _sampled(means, views)
  centres = invert_rigid(views.world_to_camera)[..., :3, 3]  # [B, V, 3]
  from_views = safe_normalize(positions - centres[:, :, None])  # [B, V, N, 3]
  from_viewers = safe_normalize(present[:, None] - viewers[:, :, None])  # [B, T, N, 3]
  cosines = jnp.einsum("bvnk,btnk->btvn", from_views, from_viewers)
  # views that do not contain the projection get no weight (uniform where none does: unseen)
  weights = jax.nn.softmax(jnp.where(inside[:, None], sharpness * cosines, -1e9), axis=2)
  colours = jnp.einsum("btvn,bvnc->btnc", weights, samples)
  return colours, jnp.any(inside, axis=1)


def with_input_colours(
  flat: jax.Array,
  views: InputViews,
  dynamic_means: jax.Array | None = None,
  viewers: jax.Array | None = None,
  sharpness: float = 0.0,
) -> jax.Array:
  """flat Gaussians [B, N, 14] -> the same with RGB read from the views where any sees them.

  dynamic_means: [B, V, Nd, 3], the last Nd Gaussians' centres at each view's time (module
  docstring): each view is read where they were when it was taken. None: where they are now.
  viewers: [B, T, 3] centres of the cameras the Gaussians will be rendered from: returns one
  set per viewer, [B, T, N, 14], coloured by `viewer_colours` at `sharpness`. None: the views'
  mean (`input_colours`), [B, N, 14].
  """
  means = flat[..., :3]
  if dynamic_means is not None:
    num_views, first = dynamic_means.shape[1], flat.shape[1] - dynamic_means.shape[2]
    still = jnp.broadcast_to(means[:, None, :first], (means.shape[0], num_views, first, 3))
    means = jnp.concatenate([still, dynamic_means], axis=2)  # [B, V, N, 3]
  if viewers is None:
    colours, seen = input_colours(means, views)
  else:
    colours, seen = viewer_colours(means, views, flat[..., :3], viewers, sharpness)
    flat, seen = flat[:, None], seen[:, None]
    flat = jnp.broadcast_to(flat, colours.shape[:-1] + flat.shape[-1:])
  rgb = jnp.where(seen[..., None], colours, flat[..., 11:14])
  return jnp.concatenate([flat[..., :11], rgb], axis=-1)
