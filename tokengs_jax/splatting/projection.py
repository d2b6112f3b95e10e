"""EWA projection of 3D Gaussians into one pinhole camera (gsplat 1.5.3 semantics, matrix form)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from tokengs_jax import math as tmath
from tokengs_jax.splatting.config import PRECISION

# Culling codes, in the order gsplat tests them (the first rule that fires is recorded); `render`
# marks Gaussians with non-finite fields CULLED_NONFINITE before any of these.
VISIBLE, CULLED_DEPTH, CULLED_DEGENERATE, CULLED_OPACITY, CULLED_FRUSTUM, CULLED_NONFINITE = range(
  6
)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Projected:
  """Per-Gaussian screen-space quantities for one camera.

  Attributes:
    means2d: [N, 2] pixel coordinates of the centres.
    conics: [N, 3] (a, b, c) of the inverse blurred 2D covariance; sigma = a dx²/2 + b dx dy + c dy²/2.
    depths: [N] camera z of the centres.
    radii: [N, 2] float pixel radii (integers as floats), 0 where culled.
    cull_code: [N] int32, VISIBLE or the first culling rule that fired.
  """

  means2d: jax.Array
  conics: jax.Array
  depths: jax.Array
  radii: jax.Array
  cull_code: jax.Array


def covariances_3d(quats: jax.Array, scales: jax.Array) -> jax.Array:
  """World covariance R S S^T R^T.  quats: [..., 4] wxyz, scales: [..., 3] -> [..., 3, 3]."""
  basis = tmath.quat_to_rotmat(quats) * scales[..., None, :]  # R @ diag(s)
  return _matmul(basis, jnp.swapaxes(basis, -1, -2))


def _matmul(a, b):
  return jnp.matmul(a, b, precision=PRECISION)


def project_gaussians(
  means,
  quats,
  scales,
  opacities,
  world_to_camera,
  intrinsics,
  *,
  height,
  width,
  near,
  far,
  eps2d,
  radius_sigmas,
  alpha_threshold,
  margin=0.0,
) -> Projected:
  """Projects N Gaussians into one camera.

  Args:
    means: [N, 3]; quats: [N, 4]; scales: [N, 3]; opacities: [N].
    world_to_camera: [4, 4] (OpenCV); intrinsics: [4] (fx, fy, cx, cy) pixels.
    height, width: image size; near, far: centre-depth culling planes; eps2d, radius_sigmas,
    alpha_threshold: see RenderConfig.
    margin: pixels the image is widened by on each side for the frustum rule (plus a 1e-3
      relative share of the centre's coordinates and the radius); 0 (the renderer) is gsplat's
      rule exactly. `compaction.drawable` widens it to judge conservatively.

  Returns:
    Projected. Every value and gradient is finite for finite inputs, culled or not: the maths of a
    culled Gaussian runs on a safe stand-in and its outputs are masked.
  """
  rot, trans = world_to_camera[:3, :3], world_to_camera[:3, 3]
  means_cam = _matmul(means, rot.T) + trans
  cov_cam = _matmul(_matmul(rot, covariances_3d(quats, scales)), rot.T)
  x, y, z = means_cam[:, 0], means_cam[:, 1], means_cam[:, 2]
  fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]

  in_depth = (z >= near) & (z <= far)
  # Means2d are wanted (visibility loss) even for culled centres: safe_div keeps them finite.
  means2d = jnp.stack([fx * tmath.safe_div(x, z) + cx, fy * tmath.safe_div(y, z) + cy], axis=-1)

  z_safe = jnp.where(in_depth, z, 1.0)
  cov2d = _blurred_cov2d(x, y, z_safe, cov_cam, (fx, fy, cx, cy), height, width, eps2d, means.dtype)
  a, b, c = cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]
  det = a * c - b * b
  good_det = in_depth & (det > 0)
  det_safe = jnp.where(good_det, det, 1.0)
  conics = jnp.stack([c / det_safe, -b / det_safe, a / det_safe], axis=-1)

  radii, opaque_enough = _pixel_radii(
    a, c, good_det, opacities, radius_sigmas=radius_sigmas, alpha_threshold=alpha_threshold
  )
  cull_code = _cull_codes(in_depth, good_det, opaque_enough, radii, means2d, height, width, margin)
  visible = cull_code == VISIBLE
  return Projected(
    means2d=means2d,
    conics=conics,
    depths=z,
    radii=jnp.where(visible[:, None], radii, 0.0),
    cull_code=cull_code,
  )


def _blurred_cov2d(x, y, z_safe, cov_cam, focal_centre, height, width, eps2d, dtype):
  """EWA screen covariance J cov J^T + eps2d I ([N, 2, 2]) of camera-space Gaussians.

  x, y: [N] camera coordinates of the centres; z_safe: [N] their depths (a stand-in where culled);
  cov_cam: [N, 3, 3] camera-space covariances; focal_centre: [] (fx, fy, cx, cy) in pixels;
  dtype: of the eps2d blur.
  J is the Jacobian of the perspective map, with the centre clamped to 1.3x the field of view
  (gsplat), so that Gaussians far outside the image do not blow up to huge footprints.
  """
  fx, fy, cx, cy = focal_centre
  inv_z = 1.0 / z_safe
  lim_x = 0.3 * 0.5 * width / fx
  lim_y = 0.3 * 0.5 * height / fy
  tx = z_safe * jnp.clip(x * inv_z, -(cx / fx + lim_x), (width - cx) / fx + lim_x)
  ty = z_safe * jnp.clip(y * inv_z, -(cy / fy + lim_y), (height - cy) / fy + lim_y)
  zeros = jnp.zeros_like(z_safe)
  jac = jnp.stack(
    [
      jnp.stack([fx * inv_z, zeros, -fx * tx * inv_z * inv_z], axis=-1),
      jnp.stack([zeros, fy * inv_z, -fy * ty * inv_z * inv_z], axis=-1),
    ],
    axis=-2,
  )  # [N, 2, 3]
  return _matmul(_matmul(jac, cov_cam), jnp.swapaxes(jac, -1, -2)) + eps2d * jnp.eye(2, dtype=dtype)


def _pixel_radii(a, c, good_det, opacities, *, radius_sigmas, alpha_threshold):
  """Integer-valued pixel radii [N, 2] (x, y) of the opacity-aware extent, without gradient.

  a, c: [N] screen variances along x and y; good_det: [N] bool, the 2D covariance is usable;
  opacities: [N]. Returns `(radii, opaque_enough [N] bool)`: beyond sqrt(2 ln(o / threshold))
  sigmas alpha is below the threshold, and a Gaussian below the threshold draws nothing.
  """
  opaque_enough = opacities >= alpha_threshold
  log_ratio = jnp.log(jnp.where(opaque_enough, opacities / alpha_threshold, 1.0))
  extent = jnp.minimum(radius_sigmas, jnp.sqrt(2.0 * log_ratio))
  var_x = jnp.where(good_det, a, 1.0)
  var_y = jnp.where(good_det, c, 1.0)
  radii = jax.lax.stop_gradient(jnp.ceil(extent[:, None] * jnp.sqrt(jnp.stack([var_x, var_y], -1))))
  return radii, opaque_enough


def _cull_codes(in_depth, good_det, opaque_enough, radii, means2d, height, width, margin=0.0):
  """[N] int32: VISIBLE, or the first culling rule that fired, in gsplat's order.

  in_depth, good_det, opaque_enough: [N] bool; radii: [N, 2] pixel radii; means2d: [N, 2] (the
  radius box must overlap the image, widened by `margin` (`project_gaussians`); 0: exactly).
  """
  nonzero_radius = (radii[:, 0] > 0) | (radii[:, 1] > 0)
  mx, my = jax.lax.stop_gradient(means2d[:, 0]), jax.lax.stop_gradient(means2d[:, 1])
  rx, ry = radii[:, 0], radii[:, 1]
  if margin:  # a static float: the renderer's (margin 0) comparisons are untouched
    rx = rx + margin * (1.0 + 1e-3 * (jnp.abs(mx) + rx))
    ry = ry + margin * (1.0 + 1e-3 * (jnp.abs(my) + ry))
  in_image = (mx + rx > 0) & (mx - rx < width) & (my + ry > 0) & (my - ry < height)
  return jnp.select(
    [~in_depth, ~good_det, ~opaque_enough, ~nonzero_radius, ~in_image],
    [CULLED_DEPTH, CULLED_DEGENERATE, CULLED_OPACITY, CULLED_DEGENERATE, CULLED_FRUSTUM],
    VISIBLE,
  ).astype(jnp.int32)
