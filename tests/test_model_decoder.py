"""The decoder (`tokengs_jax.model.decoder`): the block-causal mask, and what it means: dynamic
tokens and the target time never change the static Gaussians."""

import jax
import jax.numpy as jnp
import numpy as np
from scenes import FULL, full_params, random_inputs

from tokengs_jax.camera import plucker_rays
from tokengs_jax.model import decode, decode_tokens, encode, initial_tokens
from tokengs_jax.model.decoder import block_causal_mask


def test_block_causal_mask():
  mask = block_causal_mask(2, 3)
  expected = np.array(
    [[1, 1, 0, 0, 0], [1, 1, 0, 0, 0], [1, 1, 1, 1, 1], [1, 1, 1, 1, 1], [1, 1, 1, 1, 1]], bool
  )
  np.testing.assert_array_equal(mask, expected)
  assert block_causal_mask(4, 0) is None


def test_dynamic_tokens_and_time_never_change_static_gaussians():
  config, params = FULL, full_params()
  images, c2w, intrinsics = random_inputs(jax.random.key(3), 2, 2, 8, 8)
  plucker = plucker_rays(c2w, intrinsics, 8, 8)
  encoded = jax.jit(encode, static_argnums=3)(
    params, images, plucker, config, jnp.array([[0.0, 1.0], [0.2, 0.9]])
  )

  @jax.jit
  def run(tokens, times):  # (final decoder tokens, flat Gaussians)
    return (
      decode_tokens(params, encoded, config, tokens, times),
      decode(params, encoded, config, tokens, times),
    )

  tokens = initial_tokens(params, config, 2)
  split, first = config.num_static_gaussians, config.num_gs_tokens
  base_tokens, base = run(tokens, jnp.array([0.3, 0.5]))
  # tokens=None decodes the learnt tokens, in the order initial_tokens gives them
  np.testing.assert_allclose(
    decode(params, encoded, config, None, jnp.array([0.3, 0.5])), base, rtol=0, atol=1e-6
  )
  changed = run(
    tokens.at[:, first:].add(jax.random.normal(jax.random.key(4), (2, 3, 32))),
    jnp.array([0.9, 0.1]),
  )[1]
  np.testing.assert_allclose(changed[:, :split], base[:, :split], rtol=0, atol=1e-6)
  assert np.abs(np.asarray(changed[:, split:] - base[:, split:])).max() > 1e-3
  # the target time alone moves the dynamic Gaussians
  later = run(tokens, jnp.array([0.9, 0.1]))[1]
  np.testing.assert_allclose(later[:, :split], base[:, :split], rtol=0, atol=1e-6)
  assert np.abs(np.asarray(later[:, split:] - base[:, split:])).max() > 1e-3
  # a static token does reach the dynamic ones (dynamic attends to static); a random change,
  # since a constant shift of a token would vanish in the first LayerNorm
  static_changed = run(
    tokens.at[:, 0].add(jax.random.normal(jax.random.key(5), (32,))), jnp.array([0.3, 0.5])
  )[0]
  moved = np.abs(np.asarray(static_changed - base_tokens)).max(axis=(0, 2))
  assert np.all(moved[first:] > 1e-4) and moved[0] > 0.5
