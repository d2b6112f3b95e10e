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

Hidden views (`ModelConfig.input_occlusion_tolerance`, not in the paper either): a Gaussian's
projection into a view is that view's pixel whatever lies in front of the Gaussian, so a surface
hidden from the view that the weights prefer takes the occluder's colour. In a dynamic scene
that is the background an object stood on at the view's time: the copy of that view, ghost
included, is all such colours can render where the object has gone. With a tolerance, each view
renders the decoded scene (where it was at the view's time) and a view whose render is opaque at
the projection with an expected depth nearer than the Gaussian's by more than the tolerance gives
it no colour; a Gaussian hidden in every view that contains it keeps the views' colours as if
none hid it. The test is a mask without gradient, as the projection's `inside` is.
"""

from __future__ import annotations

import flax.struct
import jax
import jax.numpy as jnp

from tokengs_jax.camera import invert_rigid, project_points
from tokengs_jax.gaussians import Gaussians
from tokengs_jax.math import safe_normalize
from tokengs_jax.splatting import render

# Camera-z below which a view does not see a Gaussian (the renderer's near plane).
NEAR = 0.025
# Render alpha above which a view's expected depth is a surface that can hide what is behind it.
OPAQUE = 0.5
# Relative distance under which a viewer's centre is an input view's (`own_view=False`).
COINCIDENT = 1e-6


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


@flax.struct.dataclass
class Occluders:
  """What each input view sees, to find the Gaussians it hides (module docstring).

  Attributes:
    scenes: [B, N, 14] the decoded Gaussians, or [B, V, N, 14]: each view's own scene, where
      the Gaussians were when that view was taken.
    tolerance: a view hides a Gaussian whose camera z exceeds the view's expected depth at its
      projection by more than this fraction of that depth.
  """

  scenes: jax.Array
  tolerance: float = flax.struct.field(pytree_node=False)


def _hidden(occluders: Occluders, views: InputViews, uv: jax.Array, depth: jax.Array) -> jax.Array:
  """[B, V, N] bool: view v's render of its scene is opaque at the Gaussian's projection `uv`
  [B, V, N, 2], with an expected depth nearer than its camera z `depth` [B, V, N] by more than the
  tolerance. A view whose render overflowed its tile budget hides nothing (the rule without the
  test), rather than a wrong surface."""
  scenes = jax.lax.stop_gradient(occluders.scenes)
  if scenes.ndim == 3:
    scenes = jnp.broadcast_to(scenes[:, None], depth.shape[:2] + scenes.shape[1:])
  h, w = views.images.shape[-3:-1]
  seen = render(
    Gaussians.from_flat(scenes.astype(jnp.float32)),
    jax.lax.stop_gradient(views.world_to_camera)[:, :, None],
    jax.lax.stop_gradient(views.intrinsics)[:, :, None],
    height=h,
    width=w,
  )
  maps = jnp.concatenate([seen.depth, seen.alpha], axis=-1)[:, :, 0]  # [B, V, H, W, 2]
  surface = bilinear_sample(maps, jax.lax.stop_gradient(uv))
  behind = depth > surface[..., 0] * (1.0 + occluders.tolerance)
  exact = ~seen.stats.overflow  # [B, V, 1]
  return exact & (surface[..., 1] > OPAQUE) & jax.lax.stop_gradient(behind)


def _sampled(
  means: jax.Array, views: InputViews, occluders: Occluders | None = None
) -> tuple[jax.Array, jax.Array, jax.Array]:
  """Every view's sample at each Gaussian's projection.

  Args:
    means: [B, N, 3] world positions, or [B, V, N, 3]: each view's own positions of the N
      Gaussians (where they were when that view was taken).
    occluders: with them, a view that hides a Gaussian does not contain it (module docstring).

  Returns:
    (samples [B, V, N, 3] float32, inside [B, V, N] bool: the view's image contains the
    projection (and, with occluders, does not hide it), positions [B, V, N, 3]: where view v saw
    the Gaussian, non-finite ones at 0). A non-finite centre is inside no view and gets a zero
    gradient here, as the renderer culls it (design.md §8), instead of a NaN one.
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
  if occluders is not None:
    unhidden = inside & ~_hidden(occluders, views, uv, depth)
    inside = jnp.where(jnp.any(unhidden, axis=1, keepdims=True), unhidden, inside)
  return bilinear_sample(views.images.astype(jnp.float32), uv), inside, positions


def input_colours(
  means: jax.Array, views: InputViews, occluders: Occluders | None = None
) -> tuple[jax.Array, jax.Array]:
  """Mean colour of the input pixels each Gaussian centre projects to.

  Args:
    means: [B, N, 3] world positions, or [B, V, N, 3]: each view's own positions of the N
      Gaussians (where they were when that view was taken).
    views: the input views.
    occluders: with them, views that hide a Gaussian are left out (module docstring).

  Returns:
    (colours [B, N, 3] float32: the average over the views whose image contains the projection,
    seen [B, N] bool: at least one view does).
  """
  samples, inside, _ = _sampled(means, views, occluders)
  weights = inside.astype(jnp.float32)[..., None]  # [B, V, N, 1]
  count = jnp.sum(weights, axis=1)  # [B, N, 1]
  colours = jnp.sum(weights * samples, axis=1) / jnp.maximum(count, 1.0)
  return colours, count[..., 0] > 0


def viewer_colours(
  means: jax.Array,
  views: InputViews,
  present: jax.Array,
  viewers: jax.Array,
  sharpness: float,
  occluders: Occluders | None = None,
  own_view: bool | jax.Array = True,
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
    sharpness: the softmax's inverse temperature (large: the nearest ray's view alone); a
      scalar, or [N] one per Gaussian.
    occluders: with them, views that hide a Gaussian get no weight (module docstring).
    own_view: False: a view whose centre is the viewer's (an input view rendered again) gets no
      weight for that viewer, so its render shows the other views' colours at the Gaussians'
      places and tests the geometry instead of returning the view's own pixels. A [T] bool
      array decides per viewer (the same decode then serves both kinds of render).

  Returns:
    (colours [B, T, N, 3] float32, seen [B, T, N] bool: a view that weighs in contains the
    projection).
  """
  samples, inside, positions = _sampled(means, views, occluders)
  centres = invert_rigid(views.world_to_camera)[..., :3, 3]  # [B, V, 3]
  from_views = safe_normalize(positions - centres[:, :, None])  # [B, V, N, 3]
  from_viewers = safe_normalize(present[:, None] - viewers[:, :, None])  # [B, T, N, 3]
  cosines = jnp.einsum("bvnk,btnk->btvn", from_views, from_viewers)
  usable = jnp.broadcast_to(inside[:, None], cosines.shape)  # [B, T, V, N]
  if own_view is not True:
    offset = jnp.linalg.norm(viewers[:, :, None] - centres[:, None], axis=-1)  # [B, T, V]
    scale = 1.0 + jnp.linalg.norm(centres, axis=-1)[:, None]
    reads_own = jnp.broadcast_to(jnp.asarray(own_view, bool), viewers.shape[1:2])  # [T]
    usable = usable & ((offset > COINCIDENT * scale) | reads_own[:, None])[..., None]
  # views that do not contain the projection get no weight (uniform where none does: unseen)
  weights = jax.nn.softmax(jnp.where(usable, sharpness * cosines, -1e9), axis=2)
  colours = jnp.einsum("btvn,bvnc->btnc", weights, samples)
  return colours, jnp.any(usable, axis=2)


def own_view_reading(configured: bool, per_viewer: jax.Array | None) -> bool | jax.Array:
  """`viewer_colours`'s `own_view` for a model configured with `own_view_colours=configured`
  and rendered for viewers that ask `per_viewer` ([T] bool, or None: as configured): a model
  that never reads a viewer's own view does not for any."""
  return configured if per_viewer is None or not configured else per_viewer


def with_input_colours(
  flat: jax.Array,
  views: InputViews,
  dynamic_at_view_times: jax.Array | None = None,
  viewers: jax.Array | None = None,
  sharpness: float = 0.0,
  occlusion_tolerance: float | None = None,
  dynamic_sharpness: float | None = None,
  own_view: bool | jax.Array = True,
) -> jax.Array:
  """flat Gaussians [B, N, 14] -> the same with RGB read from the views where any sees them.

  dynamic_at_view_times: [B, V, Nd, 14], the last Nd Gaussians decoded at each view's time
  (module docstring): each view is read where they were when it was taken. None: where they
  are now.
  viewers: [B, T, 3] centres of the cameras the Gaussians will be rendered from: returns one
  set per viewer, [B, T, N, 14], coloured by `viewer_colours` at `sharpness`. None: the views'
  mean (`input_colours`), [B, N, 14].
  occlusion_tolerance: None reads every view the projection falls in; a fraction: views that
  hide the Gaussian behind their render of the scene are left out (`Occluders`).
  dynamic_sharpness: the viewer weights' sharpness for the dynamic Gaussians (None: `sharpness`).
  own_view: False: a viewer at an input view's centre does not read that view; a [T] bool
  array: per viewer (`viewer_colours`).
  """
  scenes = flat
  if dynamic_at_view_times is not None:
    num_views, num_dynamic = dynamic_at_view_times.shape[1:3]
    first = flat.shape[1] - num_dynamic
    still = jnp.broadcast_to(flat[:, None, :first], (flat.shape[0], num_views, first, 14))
    scenes = jnp.concatenate([still, dynamic_at_view_times], axis=2)  # [B, V, N, 14]
  means = scenes[..., :3]
  occluders = None if occlusion_tolerance is None else Occluders(scenes, occlusion_tolerance)
  if viewers is None:
    colours, seen = input_colours(means, views, occluders)
  else:
    if dynamic_at_view_times is not None and dynamic_sharpness is not None:
      sharpness = jnp.concatenate(
        [jnp.full((first,), sharpness), jnp.full((num_dynamic,), dynamic_sharpness)]
      )  # [N]: per Gaussian
    colours, seen = viewer_colours(
      means, views, flat[..., :3], viewers, sharpness, occluders, own_view
    )
    flat = jnp.broadcast_to(flat[:, None], colours.shape[:-1] + flat.shape[-1:])
  rgb = jnp.where(seen[..., None], colours, flat[..., 11:14])
  return jnp.concatenate([flat[..., :11], rgb], axis=-1)
