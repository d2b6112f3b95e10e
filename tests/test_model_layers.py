"""Network layers (`tokengs_jax.model.layers`): tiled attention (values, gradients, tiling) and
the two-pass layer norm."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tokengs_jax.model.layers import attend, attention_tiling


def _plain_attention(queries, keys, values, mask=None):
  """The textbook formula, materialising all logits (what `attend` must equal)."""
  logits = jnp.einsum("bhqd,bhkd->bhqk", queries, keys) / np.sqrt(queries.shape[-1])
  if mask is not None:
    logits = jnp.where(mask, logits, -jnp.inf)
  return jnp.einsum("bhqk,bhkd->bhqd", jax.nn.softmax(logits, axis=-1), values)


@pytest.mark.parametrize("tile", [1 << 20, 84, 30, 12])
@pytest.mark.parametrize("masked", [False, True])
def test_tiled_attention_values_and_gradients_match_plain_attention(tile, masked):
  batch_heads, num_queries, num_keys = 6, 7, 12
  keys_ = jax.random.split(jax.random.key(3), 4)
  queries = jax.random.normal(keys_[0], (2, 3, num_queries, 8))
  keys = jax.random.normal(keys_[1], (2, 3, num_keys, 8))
  values = jax.random.normal(keys_[2], (2, 3, num_keys, 8))
  # causal with two keys of look-ahead: query i sees keys 0..i+2
  mask = np.tri(num_queries, num_keys, k=2, dtype=bool) if masked else None
  if masked:
    assert not mask.all() and mask.any(axis=1).all()  # some masking, no empty row
  # weight the output so that every output element has a different cotangent
  weights = jax.random.normal(keys_[3], (2, 3, num_queries, 8))

  def loss(attention):
    return lambda q, k, v: jnp.sum(weights * attention(q, k, v, mask))

  np.testing.assert_allclose(
    attend(queries, keys, values, mask, tile),
    _plain_attention(queries, keys, values, mask),
    rtol=0,
    atol=1e-6,
  )
  grads = jax.grad(loss(functools.partial(attend, tile=tile)), argnums=(0, 1, 2))(
    queries, keys, values
  )
  reference = jax.grad(loss(_plain_attention), argnums=(0, 1, 2))(queries, keys, values)
  for got, want in zip(grads, reference):
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-6)
  heads_per_step, rows, row_steps = attention_tiling(batch_heads, num_queries, num_keys, tile)
  assert heads_per_step * rows * num_keys <= max(tile, num_keys) and rows * row_steps >= num_queries


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.bfloat16])
def test_layer_norm_matches_flax_two_pass_layer_norm_and_its_gradients(dtype):
  from flax import linen as nn

  from tokengs_jax.model.layers import layer_norm

  rng = np.random.default_rng(0)
  # An offset far from zero: the variance must be the two-pass one to stay accurate.
  x = jnp.asarray(rng.normal(3.0, 0.5, (2, 5, 48)), dtype)
  weights = jnp.asarray(rng.normal(size=(2, 5, 48)), jnp.float32)
  ours = layer_norm(dtype)
  flax_norm = nn.LayerNorm(epsilon=1e-5, use_fast_variance=False, dtype=dtype)
  params = {
    "params": {
      "scale": jnp.asarray(rng.normal(1.0, 0.2, 48), jnp.float32),
      "bias": jnp.asarray(rng.normal(0.0, 0.2, 48), jnp.float32),
    }
  }

  def loss(module, params, x):
    return jnp.sum(module.apply(params, x).astype(jnp.float32) * weights)

  assert ours.apply(params, x).dtype == dtype
  value, grads = jax.value_and_grad(functools.partial(loss, ours), argnums=(0, 1))(params, x)
  ref_value, ref_grads = jax.value_and_grad(functools.partial(loss, flax_norm), argnums=(0, 1))(
    params, x
  )
  tol = 1e-5 if dtype == jnp.float32 else 2e-2
  np.testing.assert_allclose(value, ref_value, rtol=tol)
  for got, ref in zip(jax.tree.leaves(grads), jax.tree.leaves(ref_grads)):
    got, ref = np.asarray(got, np.float32), np.asarray(ref, np.float32)
    np.testing.assert_allclose(got, ref, rtol=0, atol=tol * np.abs(ref).max())


def test_attention_tiling_splits_big_problems():
  assert attention_tiling(32, 128, 128) == (32, 128, 1)  # tiny preset: a single step
  assert attention_tiling(16, 896, 896) == (1, 896, 1)  # one head at a time
  heads, rows, steps = attention_tiling(16, 4096, 3584)  # full DL3DV cross-attention
  assert heads == 1 and rows * 3584 <= 1 << 20 and rows * steps >= 4096
  assert attention_tiling(6, 7, 12, tile=30) == (1, 2, 4)  # 7 rows -> 4 chunks of 2 (1 padded)
