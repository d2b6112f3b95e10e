"""Safe numerical primitives shared by every module.

Nothing here knows about cameras, Gaussians or networks. Each op keeps its value *and* its
gradient finite for every finite input (zero vectors, huge arguments), which is what lets the
renderer and the losses survive degenerate Gaussians without NaN poisoning a training run.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

TINY = 1e-12  # floor used by torch.nn.functional.normalize, kept for parity with the references


def safe_norm(x: jax.Array, axis: int = -1, keepdims: bool = False, eps: float = TINY) -> jax.Array:
  """Euclidean norm whose gradient is 0 (not NaN) at x = 0.

  x: [..., D] -> [...] (or [..., 1] with keepdims).
  """
  sq = jnp.sum(x * x, axis=axis, keepdims=keepdims)
  nonzero = sq > eps * eps
  # Double-where: the sqrt branch never sees 0, so its derivative is never inf * 0.
  return jnp.where(nonzero, jnp.sqrt(jnp.where(nonzero, sq, 1.0)), 0.0)


def safe_normalize(x: jax.Array, axis: int = -1, eps: float = TINY) -> jax.Array:
  """x / max(|x|, eps) like torch's F.normalize, with finite gradients at x = 0.

  x: [..., D] -> [..., D]; the zero vector maps to the zero vector.
  """
  return x / jnp.maximum(safe_norm(x, axis=axis, keepdims=True), eps)


def safe_exp(x: jax.Array, limit: float = 80.0) -> jax.Array:
  """exp clipped so that neither the value nor the gradient overflows float32.

  Above `limit` the value is exp(limit) and the gradient is 0 (the clamp's): an argument that
  large is already a bug upstream, and a zero gradient keeps it from spreading.
  """
  return jnp.exp(jnp.minimum(x, limit))


def safe_div(num: jax.Array, den: jax.Array, eps: float = TINY) -> jax.Array:
  """num / den with |den| floored at eps (sign kept; den = 0 counts as positive); gradients stay
  finite: d/dnum = 1 / den', and d/dden is 0 where the floor holds (|den| < eps)."""
  den = jnp.where(jnp.abs(den) < eps, jnp.where(den < 0, -eps, eps), den)
  return num / den


def quat_to_rotmat(quats: jax.Array) -> jax.Array:
  """Rotation matrices from (possibly unnormalised) wxyz quaternions.

  quats: [..., 4] (w, x, y, z) -> [..., 3, 3]. The quaternion is normalised first (as gsplat
  does); the zero quaternion gives the identity, with finite gradients.
  """
  w, x, y, z = jnp.moveaxis(safe_normalize(quats), -1, 0)
  rows = [
    [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
  ]
  return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)
