import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tokengs_jax import math as tmath


def test_safe_norm_and_normalize_have_finite_gradients_at_zero():
  zero = jnp.zeros(3)
  assert float(tmath.safe_norm(zero)) == 0.0
  g = jax.grad(lambda x: tmath.safe_norm(x))(zero)
  assert np.all(np.isfinite(g))
  j = jax.jacobian(tmath.safe_normalize)(zero)
  assert np.all(np.isfinite(j))
  np.testing.assert_allclose(tmath.safe_normalize(jnp.array([3.0, 4.0])), [0.6, 0.8], rtol=1e-6)


def test_quat_to_rotmat_is_rotation_and_ignores_scale():
  q = jax.random.normal(jax.random.PRNGKey(0), (16, 4))
  r = tmath.quat_to_rotmat(q)
  np.testing.assert_allclose(
    r @ jnp.swapaxes(r, -1, -2), np.broadcast_to(np.eye(3), r.shape), atol=1e-5
  )
  np.testing.assert_allclose(jnp.linalg.det(r), 1.0, atol=1e-5)
  np.testing.assert_allclose(tmath.quat_to_rotmat(7.5 * q), r, atol=1e-6)
  # 90 degrees about z (wxyz): x -> y
  c = np.cos(np.pi / 4)
  rz = tmath.quat_to_rotmat(jnp.array([c, 0.0, 0.0, c]))
  np.testing.assert_allclose(rz @ jnp.array([1.0, 0, 0]), [0, 1, 0], atol=1e-6)


def test_zero_quaternion_gives_identity_with_finite_gradient():
  np.testing.assert_allclose(tmath.quat_to_rotmat(jnp.zeros(4)), np.eye(3))
  g = jax.grad(lambda q: jnp.sum(tmath.quat_to_rotmat(q) ** 2))(jnp.zeros(4))
  assert np.all(np.isfinite(g))


@pytest.mark.parametrize("x", [-1e30, -1.0, 0.0, 1e-30, 50.0, 1e30])
def test_safe_exp_and_div_finite(x):
  x = jnp.float32(x)
  assert np.isfinite(tmath.safe_exp(x)) and np.isfinite(jax.grad(tmath.safe_exp)(x))
  assert np.isfinite(tmath.safe_div(1.0, x)) and np.isfinite(jax.grad(tmath.safe_div, 1)(1.0, x))
