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


def test_safe_exp_is_exp_below_its_limit_and_flat_above():
  x = jnp.array([-20.0, -1.0, 0.0, 0.5, 10.0, 79.0])
  np.testing.assert_allclose(tmath.safe_exp(x), np.exp(np.asarray(x, np.float64)), rtol=1e-6)
  np.testing.assert_allclose(jax.vmap(jax.grad(tmath.safe_exp))(x), np.exp(x), rtol=1e-6)
  above = jnp.array([80.0, 81.0, 1e30])
  np.testing.assert_allclose(tmath.safe_exp(above), np.exp(np.float32(80.0)), rtol=1e-6)
  np.testing.assert_array_equal(jax.vmap(jax.grad(tmath.safe_exp))(above[1:]), 0.0)
  grid = jnp.linspace(-30.0, 100.0, 301)
  assert bool(jnp.all(jnp.diff(tmath.safe_exp(grid)) >= 0))  # monotone


def test_safe_div_divides_and_floors_tiny_denominators_keeping_their_sign():
  num = jnp.array([3.0, -2.0, 1.0, 1.0, 1.0])
  den = jnp.array([4.0, 0.5, 1e-20, -1e-20, 0.0])
  eps = tmath.TINY
  np.testing.assert_allclose(
    tmath.safe_div(num, den), [0.75, -4.0, 1 / eps, -1 / eps, 1 / eps], rtol=1e-6
  )
  d_num = jax.vmap(jax.grad(tmath.safe_div, 0))(num, den)
  np.testing.assert_allclose(d_num, [0.25, 2.0, 1 / eps, -1 / eps, 1 / eps], rtol=1e-6)
  d_den = jax.vmap(jax.grad(tmath.safe_div, 1))(num, den)
  np.testing.assert_allclose(d_den[:2], [-3.0 / 16.0, 8.0], rtol=1e-6)
  np.testing.assert_array_equal(d_den[2:], 0.0)  # the floor's gradient


def test_safe_norm_values_and_gradient_are_the_norms():
  x = jnp.array([[3.0, 4.0, 0.0], [1.0, -2.0, 2.0], [0.0, 0.0, 0.0]])
  np.testing.assert_allclose(tmath.safe_norm(x), [5.0, 3.0, 0.0], rtol=1e-6)
  grads = jax.vmap(jax.grad(tmath.safe_norm))(x)
  np.testing.assert_allclose(grads[:2], x[:2] / np.array([[5.0], [3.0]]), rtol=1e-6)
  np.testing.assert_array_equal(grads[2], 0.0)
  np.testing.assert_allclose(tmath.safe_normalize(x)[1], [1 / 3, -2 / 3, 2 / 3], rtol=1e-6)
  np.testing.assert_array_equal(tmath.safe_normalize(x)[2], 0.0)
