"""Growing a pretrained model (`train.tokens`): token expansion, dynamic tokens from static ones,
parameter transplant, Gaussian splitting."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from toy_training import toy_params

from tokengs_jax.train import (
  dynamic_tokens_from_static,
  expand_tokens,
  split_gaussians,
  transplant_params,
)


def test_expand_tokens_statistics():
  tokens = jax.random.normal(jax.random.PRNGKey(0), (256, 32))
  grown = expand_tokens(jax.random.PRNGKey(1), tokens, 1024, noise_std=0.01)
  assert grown.shape == (1024, 32)
  np.testing.assert_array_equal(grown[:256], tokens)
  noise = np.asarray(grown[256:]) - np.tile(np.asarray(tokens), (3, 1))
  assert abs(noise.mean()) < 1e-3 and abs(noise.std() - 0.01) < 5e-4
  shrunk = expand_tokens(jax.random.PRNGKey(1), tokens, 4)
  np.testing.assert_array_equal(shrunk, tokens[np.array([0, 85, 170, 255])])


def test_dynamic_tokens_from_static():
  static = jnp.arange(12.0).reshape(4, 3)
  np.testing.assert_array_equal(
    dynamic_tokens_from_static(jax.random.PRNGKey(0), static, 6),
    static[np.array([0, 1, 2, 3, 0, 1])],
  )
  subset = np.asarray(dynamic_tokens_from_static(jax.random.PRNGKey(0), static, 2))
  assert subset.shape == (2, 3) and len({tuple(r) for r in subset}) == 2
  assert all(any((r == s).all() for s in np.asarray(static)) for r in subset)


def test_transplant_grows_tokens_and_reports():
  pretrained, fresh = toy_params(0, num_tokens=4), toy_params(1, num_tokens=16)
  fresh["dense2"]["kernel"] = jnp.zeros((16, 5))
  params, report = transplant_params(jax.random.PRNGKey(0), pretrained, fresh)
  np.testing.assert_array_equal(params["dense1"]["kernel"], pretrained["dense1"]["kernel"])
  np.testing.assert_array_equal(params["gs_tokens"][:4], pretrained["gs_tokens"])
  assert params["gs_tokens"].shape == (16, 2)
  np.testing.assert_array_equal(params["dense2"]["kernel"], fresh["dense2"]["kernel"])
  assert sorted(report) == [
    "dense2/kernel: kept fresh (shape (16, 2))",
    "gs_tokens: tokens 4 -> 16",
  ]
  fresh["gs_tokens_dynamic"] = jnp.zeros((6, 2))
  params, report = transplant_params(jax.random.PRNGKey(0), pretrained, fresh)
  np.testing.assert_array_equal(
    params["gs_tokens_dynamic"], pretrained["gs_tokens"][np.array([0, 1, 2, 3, 0, 1])]
  )
  assert "gs_tokens_dynamic: from static gs_tokens" in report


def test_split_gaussians_copies_each_parent_and_refuses_non_multiples():
  kernel = jax.random.normal(jax.random.PRNGKey(0), (5, 2 * 3))
  split = np.asarray(split_gaussians(jax.random.PRNGKey(1), kernel, 3, 6, noise_std=0.01))
  parents = np.asarray(kernel).reshape(5, 2, 3)
  children = split.reshape(5, 6, 3)
  np.testing.assert_allclose(children, np.repeat(parents, 3, axis=1), atol=0.01 * 6)
  assert (children[:, 0] != children[:, 1]).any()  # noise parts identical children
  bias = jnp.arange(6.0)
  np.testing.assert_array_equal(
    split_gaussians(jax.random.PRNGKey(1), bias, 3, 4), [0, 1, 2] * 2 + [3, 4, 5] * 2
  )
  with pytest.raises(ValueError, match="cannot split 2"):
    split_gaussians(jax.random.PRNGKey(1), kernel, 3, 5)


def test_transplant_splits_the_head_into_more_gaussians_per_token():
  """A head grown from 4 to 16 Gaussians per token decodes each pretrained Gaussian 4 times."""
  from scenes import MICRO, micro_params

  from tokengs_jax import model

  grown_config = MICRO.replace(dec_patch_size=4)
  fresh = model.init_params(jax.random.key(3), grown_config)
  params, report = transplant_params(jax.random.key(0), micro_params(), fresh, noise_std=0.0)
  assert sorted(r for r in report if "deconv" in r) == [
    "activation_head/deconv/bias: Gaussians per token 4 -> 16 (split)",
    "activation_head/deconv/kernel: Gaussians per token 4 -> 16 (split)",
  ]
  images = jax.random.normal(jax.random.key(4), (1, MICRO.num_input_views, 16, 16, 3))
  plucker = jax.random.normal(jax.random.key(5), (1, MICRO.num_input_views, 16, 16, 6))
  before = model.predict_gaussians(micro_params(), images, plucker, MICRO)
  after = model.predict_gaussians(params, images, plucker, grown_config)
  assert after.shape[1] == 4 * before.shape[1]
  np.testing.assert_allclose(after, np.repeat(np.asarray(before), 4, axis=1), atol=1e-5)
