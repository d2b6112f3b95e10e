"""Camera conventions in one place.

- Axes: OpenCV (+x right, +y down, +z forward).
- Poses: `c2w [..., 4, 4]` camera-to-world for data and Plücker rays; `w2c [..., 4, 4]`
  world-to-camera for rendering and projection.
- Intrinsics: `[..., 4]` = (fx, fy, cx, cy) in pixels, never a K matrix (convert one with
  `intrinsics_from_matrix`). RE10K/DL3DV files store them divided by width/height
  ("normalised"); convert at the file boundary with `intrinsics_to_pixels`.
- Pixel (row i, column j) has its centre at (j + 0.5, i + 0.5).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from tokengs_jax import math as tmath


def invert_rigid(pose: jax.Array) -> jax.Array:
  """Inverse of a rigid 4x4 transform (c2w <-> w2c) without a general matrix inverse.

  pose: [..., 4, 4] -> [..., 4, 4].
  """
  rot = pose[..., :3, :3]
  trans = pose[..., :3, 3:]
  rot_t = jnp.swapaxes(rot, -1, -2)
  top = jnp.concatenate([rot_t, -rot_t @ trans], axis=-1)
  bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0], pose.dtype), top.shape[:-2] + (1, 4))
  return jnp.concatenate([top, bottom], axis=-2)


def intrinsics_matrix(intrinsics: jax.Array) -> jax.Array:
  """(fx, fy, cx, cy) -> K.  intrinsics: [..., 4] -> [..., 3, 3]."""
  fx, fy, cx, cy = jnp.moveaxis(intrinsics, -1, 0)
  zero, one = jnp.zeros_like(fx), jnp.ones_like(fx)
  return jnp.stack(
    [
      jnp.stack([fx, zero, cx], -1),
      jnp.stack([zero, fy, cy], -1),
      jnp.stack([zero, zero, one], -1),
    ],
    axis=-2,
  )


def intrinsics_from_matrix(matrix: jax.Array) -> jax.Array:
  """K -> (fx, fy, cx, cy).  matrix: [..., 3, 3] or [..., 4, 4] (K padded to 4x4) -> [..., 4]."""
  if np.shape(matrix)[-2:] not in ((3, 3), (4, 4)):
    raise ValueError(f"a K matrix is [..., 3, 3] or [..., 4, 4], got shape {np.shape(matrix)}")
  matrix = jnp.asarray(matrix)
  return jnp.stack(
    [matrix[..., 0, 0], matrix[..., 1, 1], matrix[..., 0, 2], matrix[..., 1, 2]], axis=-1
  )


def check_camera_values(
  poses, intrinsics, *, pose_name: str, camera: str, layout: str, prefix: str = ""
) -> None:
  """Raises ValueError for a camera with a non-finite pose or intrinsics, or fx, fy <= 0.

  poses: [..., 4, 4]; intrinsics: [..., 4] (fx, fy, cx, cy), with the same cameras [...] (or
  broadcasting to them). The message names the array (`pose_name` or "intrinsics") and the first
  bad camera as "{camera} [i, j] (index into {layout})", after `prefix`.
  Only concrete arrays are read: a traced one (under jit, vmap, grad) has no values yet, and
  reading it would cost a device-to-host copy on every step.
  """
  checks = ((pose_name, poses, 2), ("intrinsics", intrinsics, 1))
  for name, values, matrix_axes in checks:
    if isinstance(values, jax.core.Tracer):
      continue
    values = np.asarray(values)
    bad = ~np.all(np.isfinite(values), axis=tuple(range(-matrix_axes, 0)))
    if np.any(bad):
      index = np.argwhere(bad)[0].tolist()
      raise ValueError(
        f"{prefix}{name} of {camera} {index} (index into {layout}) is not finite (NaN or inf)"
      )
    non_positive = np.any(values[..., :2] <= 0, axis=-1) if name == "intrinsics" else False
    if np.any(non_positive):
      index = np.argwhere(non_positive)[0].tolist()
      hint = (
        "; a 4x4 K matrix? intrinsics are one (fx, fy, cx, cy) row per camera: convert K with "
        "camera.intrinsics_from_matrix"
        if values.shape[-2:] == (4, 4)
        else ""
      )
      raise ValueError(
        f"{prefix}intrinsics of {camera} {index} (index into {layout}): fx, fy must be > 0, "
        f"got (fx, fy, cx, cy) = {values[tuple(index)].tolist()}{hint}"
      )


def intrinsics_to_pixels(normalised: jax.Array, height: int, width: int) -> jax.Array:
  """(fx/W, fy/H, cx/W, cy/H) -> pixels.  normalised: [..., 4] -> [..., 4]."""
  scale = jnp.array([width, height, width, height], dtype=normalised.dtype)
  return normalised * scale


def pixel_centers(height: int, width: int, dtype=jnp.float32) -> jax.Array:
  """Pixel-centre coordinates (u, v) = (j + 0.5, i + 0.5).  -> [H, W, 2]."""
  u = jnp.arange(width, dtype=dtype) + 0.5
  v = jnp.arange(height, dtype=dtype) + 0.5
  uu, vv = jnp.meshgrid(u, v, indexing="xy")
  return jnp.stack([uu, vv], axis=-1)


def ray_directions(c2w: jax.Array, intrinsics: jax.Array, height: int, width: int) -> jax.Array:
  """Unit world-space ray directions through every pixel centre.

  c2w: [..., 4, 4], intrinsics: [..., 4] -> [..., H, W, 3].
  """
  uv = pixel_centers(height, width, dtype=c2w.dtype)  # [H, W, 2]
  fx, fy, cx, cy = (intrinsics[..., k, None, None] for k in range(4))
  x = (uv[..., 0] - cx) / fx
  y = (uv[..., 1] - cy) / fy
  inv_norm = jax.lax.rsqrt(x * x + y * y + 1.0)
  rot = c2w[..., None, None, :3, :3]
  # R @ (x, y, 1) / |(x, y, 1)| written out column by column: one elementwise fusion. As a batched
  # dot it cost 3-6 ms of the default train step; as a multiply-reduce over the size-3 axis, XLA:CPU
  # hands the reduction to a library call that the patch embedding's transpose cannot fuse with.
  x, y, inv_norm = x[..., None], y[..., None], inv_norm[..., None]
  return (rot[..., 0] * x + rot[..., 1] * y + rot[..., 2]) * inv_norm


def plucker_rays(c2w: jax.Array, intrinsics: jax.Array, height: int, width: int) -> jax.Array:
  """Plücker ray embedding (moment o x d first, then direction d), as the official `ray_condition`.

  c2w: [..., 4, 4], intrinsics: [..., 4] (pixels) -> [..., H, W, 6].
  """
  dirs = ray_directions(c2w, intrinsics, height, width)
  origins = jnp.broadcast_to(c2w[..., None, None, :3, 3], dirs.shape)
  return jnp.concatenate([jnp.cross(origins, dirs), dirs], axis=-1)


def project_points(points: jax.Array, w2c: jax.Array, intrinsics: jax.Array):
  """Pinhole projection of world points into cameras.

  points: [..., N, 3], w2c: [..., V, 4, 4], intrinsics: [..., V, 4]
  -> (uv [..., V, N, 2] in pixels, depth [..., V, N] camera z). Points with depth near 0 get a
  finite (floored) uv; callers decide visibility from `depth`.
  """
  rot = w2c[..., :3, :3]  # [..., V, 3, 3]
  trans = w2c[..., :3, 3]  # [..., V, 3]
  cam = jnp.einsum("...vij,...nj->...vni", rot, points) + trans[..., None, :]
  depth = cam[..., 2]
  fx, fy, cx, cy = (intrinsics[..., k, None] for k in range(4))
  u = fx * tmath.safe_div(cam[..., 0], depth) + cx
  v = fy * tmath.safe_div(cam[..., 1], depth) + cy
  return jnp.stack([u, v], axis=-1), depth
