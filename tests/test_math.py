import functools

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


# ----- against the plain ops inside the safe range, in the manner of multinerf's math_test.py


def _directions(count, seed):
  """Random unit vectors [count, 3] scaled to norms from 1e-10 to 1e18 (inside the safe range:
  above TINY, and squares that float32 still holds)."""
  x = jax.random.normal(jax.random.key(seed), (count, 3))
  return x / jnp.linalg.norm(x, axis=-1, keepdims=True) * jnp.logspace(-10, 18, count)[:, None]


def test_safe_norm_is_the_plain_norm_and_its_gradient_above_tiny_and_zero_below():
  x = _directions(57, seed=0)
  np.testing.assert_allclose(tmath.safe_norm(x), jnp.linalg.norm(x, axis=-1), rtol=1e-6)
  grads = jax.vmap(jax.grad(tmath.safe_norm))(x)
  np.testing.assert_allclose(grads, jax.vmap(jax.grad(jnp.linalg.norm))(x), rtol=1e-5, atol=1e-7)
  # below TINY the norm is clamped to 0, and so is its gradient (the clamp's, not a NaN)
  tiny = jnp.array([[1e-13, 0.0, 0.0], [0.0, -5e-13, 5e-13]])
  np.testing.assert_array_equal(tmath.safe_norm(tiny), 0.0)
  np.testing.assert_array_equal(jax.vmap(jax.grad(tmath.safe_norm))(tiny), 0.0)
  # monotone along a ray: |t x| never decreases with t >= 0, through the clamp and beyond it
  t = jnp.concatenate([jnp.zeros(1), jnp.logspace(-14, 14, 300)])
  assert bool(jnp.all(jnp.diff(tmath.safe_norm(t[:, None] * x[20])) >= 0))


def test_safe_normalize_is_the_plain_normalize_and_its_jacobian_above_tiny():
  x = _directions(57, seed=1)
  plain = lambda v: v / jnp.linalg.norm(v)
  np.testing.assert_allclose(tmath.safe_normalize(x), jax.vmap(plain)(x), rtol=1e-6, atol=1e-7)
  np.testing.assert_allclose(jnp.linalg.norm(tmath.safe_normalize(x), axis=-1), 1.0, rtol=1e-6)
  got = jax.vmap(jax.jacobian(tmath.safe_normalize))(x)
  want = jax.vmap(jax.jacobian(plain))(x)
  scale = jnp.linalg.norm(x, axis=-1)[:, None, None]  # the Jacobian falls as 1 / |x|
  np.testing.assert_allclose(got * scale, want * scale, rtol=0, atol=1e-5)
  # below TINY the norm is clamped at TINY: x / TINY (not a unit vector), Jacobian I / TINY
  tiny = jnp.array([1e-13, 0.0, 0.0])
  np.testing.assert_allclose(tmath.safe_normalize(tiny), tiny / tmath.TINY, rtol=1e-6)
  np.testing.assert_allclose(
    jax.jacobian(tmath.safe_normalize)(tiny) * tmath.TINY, np.eye(3), rtol=1e-6
  )


def test_safe_div_is_the_plain_division_and_its_gradients_above_tiny_and_monotone():
  keys = jax.random.split(jax.random.key(2), 2)
  num = jax.random.normal(keys[0], (64,)) * jnp.logspace(-6, 6, 64)
  magnitude = jnp.logspace(-11, 11, 64)
  den = jnp.where(jax.random.bernoulli(keys[1], 0.5, (64,)), magnitude, -magnitude)
  np.testing.assert_allclose(tmath.safe_div(num, den), num / den, rtol=1e-6)
  for argnum in (0, 1):
    got = jax.vmap(jax.grad(tmath.safe_div, argnum))(num, den)
    want = jax.vmap(jax.grad(jnp.divide, argnum))(num, den)
    np.testing.assert_allclose(got, want, rtol=1e-5)
  # monotone: increasing in the numerator; in the denominator decreasing on each side of 0 for
  # a positive numerator (den = 0 counts as positive), and flat (zero gradient: the floor)
  # inside (-TINY, TINY)
  line = jnp.linspace(-5.0, 5.0, 101)
  assert bool(jnp.all(jnp.diff(tmath.safe_div(line, 0.5)) > 0))
  magnitudes = jnp.logspace(-14, 4, 200)
  positive = tmath.safe_div(1.0, jnp.concatenate([jnp.zeros(1), magnitudes]))
  assert bool(jnp.all(jnp.diff(positive) <= 0)) and positive[0] == 1 / np.float32(tmath.TINY)
  assert bool(jnp.all(jnp.diff(tmath.safe_div(1.0, -magnitudes)) >= 0))
  inside = jnp.array([-9e-13, -1e-20, 1e-20, 9e-13])
  np.testing.assert_array_equal(jax.vmap(jax.grad(tmath.safe_div, 1))(jnp.ones(4), inside), 0.0)


def test_safe_norm_neither_overflows_nor_underflows_the_squares():
  # float32 squares overflow above ~1.8e19 and fall below the smallest normal under ~1e-19
  large = jnp.array([[3e19, 4e19, 0.0], [3e37, -4e37, 0.0], [1e38, 1e38, 1e38]])
  np.testing.assert_allclose(tmath.safe_norm(large), [5e19, 5e37, np.sqrt(3) * 1e38], rtol=1e-6)
  grads = jax.vmap(jax.grad(tmath.safe_norm))(large)
  np.testing.assert_allclose(grads[:2], [[0.6, 0.8, 0.0], [0.6, -0.8, 0.0]], rtol=1e-6)
  np.testing.assert_allclose(tmath.safe_normalize(large)[0], [0.6, 0.8, 0.0], rtol=1e-6)
  np.testing.assert_allclose(tmath.safe_norm(large, keepdims=True)[:1], [[5e19]], rtol=1e-6)
  long = jnp.arange(8.0) * 1e19  # an axis too long to be written out: a jnp reduction
  np.testing.assert_allclose(
    tmath.safe_norm(long), np.linalg.norm(np.arange(8.0)) * 1e19, rtol=1e-6
  )
  # tiny: with a smaller eps, components whose squares float32 cannot hold (below 1e-45)
  tiny = jnp.array([3e-25, -4e-25, 0.0])
  np.testing.assert_allclose(tmath.safe_norm(tiny, eps=1e-30), 5e-25, rtol=1e-6)
  tiny_grad = jax.grad(functools.partial(tmath.safe_norm, eps=1e-30))(tiny)
  np.testing.assert_allclose(tiny_grad, [0.6, -0.8, 0.0], rtol=1e-6)
  assert float(tmath.safe_norm(jnp.array([jnp.inf, 1.0]))) == np.inf
  # zero: 0 with gradient 0, first and second order
  zero = jnp.zeros(3)
  assert float(tmath.safe_norm(zero)) == 0.0
  np.testing.assert_array_equal(jax.grad(tmath.safe_norm)(zero), 0.0)
  np.testing.assert_array_equal(jax.hessian(tmath.safe_norm)(zero), 0.0)
