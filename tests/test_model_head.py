"""The Gaussian head (`tokengs_jax.model.head`): activation constants and the z-offset bias."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from scenes import FULL, MICRO, full_init, micro_params

from tokengs_jax.model.head import activate


def test_head_activation_constants():
  act = jax.jit(functools.partial(activate, config=MICRO))
  raw = jnp.zeros((14,))
  out = np.asarray(act(raw))
  np.testing.assert_allclose(out[:3], [0, 0, 1.0])  # z-offset 1
  np.testing.assert_allclose(out[3], 1 / (1 + np.exp(2.0)), rtol=1e-6)  # sigmoid(x - 2)
  np.testing.assert_allclose(out[4:7], 0.075 / np.e, rtol=1e-6)  # exp(x - (1 - ln 0.075))
  np.testing.assert_allclose(out[11:], 0.5)  # 0.5 tanh + 0.5
  # raw order [xyz, rgb, scale, quat, opacity]; huge scale is capped with a finite gradient
  raw = jnp.array([1.0, -2.0, 0.5, 3, 3, 3, 200.0, 0.0, 0.0, 3.0, 0, 4.0, 0, 0.0])
  out = np.asarray(act(raw))
  np.testing.assert_allclose(out[:3], [np.e - 1, -(np.e**2 - 1), np.expm1(0.5) + 1], rtol=1e-6)
  np.testing.assert_allclose(out[4], 0.075)
  np.testing.assert_allclose(out[7:11], [0.6, 0, 0.8, 0], atol=1e-7)
  np.testing.assert_allclose(out[11:], 0.5 * np.tanh(3.0) + 0.5, rtol=1e-6)
  grad = jax.jit(jax.grad(lambda r: act(r).sum()))(raw)
  assert np.all(np.isfinite(grad)) and grad[6] == 0
  assert np.asarray(grad)[0] == np.e  # d/dx expm1(x) at x = 1
  assert jax.grad(lambda x: act(jnp.zeros(14).at[0].set(x))[0])(0.0) == 1.0


def test_head_z_init_bias():
  bias = full_init()["activation_head"]["deconv"]["bias"]
  per_gaussian = np.asarray(bias).reshape(FULL.gaussians_per_token, 14)
  np.testing.assert_allclose(per_gaussian[:, 2], np.log(1.1), rtol=1e-6)
  assert not np.any(np.delete(per_gaussian, 2, axis=1))
  assert not np.any(micro_params()["activation_head"]["deconv"]["bias"])
