"""The TokenGS network (`tokengs_jax.model.network`): parity with the official PyTorch model
(decoder tokens and Gaussians; bfloat16 compute), the latent bottleneck's encoding, and decoding
the dynamic tokens alone."""

import jax
import jax.numpy as jnp
import numpy as np
from scenes import FULL, full_params, official_fixture, random_inputs

from tokengs_jax.camera import plucker_rays
from tokengs_jax.model import (
  TokenGS,
  decode_tokens,
  encode,
  kv_from_latents,
  param_shapes,
  predict_gaussians,
)


# ----- parity with the official model (top priority) ----------------------------------------------


def test_official_decoder_tokens_and_gaussians_match():
  config, params, io = official_fixture()
  encoded = jax.jit(encode, static_argnums=3)(params, io["images_rgb"], io["plucker"], config)
  tokens = jax.jit(decode_tokens, static_argnums=2)(params, encoded, config)
  np.testing.assert_allclose(tokens, io["decoder_tokens_out"], rtol=0, atol=1e-4)
  flat = jax.jit(predict_gaussians, static_argnums=3)(
    params, io["images_rgb"], io["plucker"], config
  )
  assert flat.shape == io["gaussians"].shape
  np.testing.assert_allclose(flat, io["gaussians"], rtol=0, atol=1e-4)


def test_bfloat16_compute_keeps_float32_params_and_stays_close():
  config, params, io = official_fixture()
  bf16 = config.replace(dtype="bfloat16")
  flat = jax.jit(predict_gaussians, static_argnums=3)(params, io["images_rgb"], io["plucker"], bf16)
  assert flat.dtype == jnp.float32
  assert all(leaf.dtype == jnp.float32 for leaf in jax.tree.leaves(param_shapes(bf16)))
  err = np.abs(np.asarray(flat) - io["gaussians"]).max()
  assert 0 < err < 0.05  # bf16 rounding, but no gross error


# ----- latent bottleneck --------------------------------------------------------------------------


def test_latent_bottleneck_encode_exposes_latents():
  config, params = FULL, full_params()
  images, c2w, intrinsics = random_inputs(jax.random.key(1), 2, 2, 8, 8)
  times = jnp.zeros((2, 2))
  encoded = jax.jit(encode, static_argnums=3)(
    params, images, plucker_rays(c2w, intrinsics, 8, 8), config, times
  )
  assert encoded.latents.shape == (2, 6, 32)
  assert encoded.keys.shape == (2, 2, 6, 16)  # the decoder sees latents, not image tokens
  again = kv_from_latents(params, encoded.latents, config)
  np.testing.assert_allclose(again.keys, encoded.keys, atol=1e-6)
  np.testing.assert_allclose(again.values, encoded.values, atol=1e-6)


# ----- dynamic tokens decoded alone ---------------------------------------------------------------


def test_dynamic_tokens_decoded_alone_match_their_rows_of_a_full_decode():
  """`EncDecBackbone.decode_dynamic` of other dynamic tokens, against the static keys/values of a
  decode of [static, dynamic]: the rows a decode of [static, other dynamic] gives them, with the
  same gradients (parameters, static and dynamic tokens)."""
  config, params = FULL, full_params()
  images, c2w, intrinsics = random_inputs(jax.random.key(6), 2, 2, 8, 8)
  encoded = jax.jit(encode, static_argnums=3)(
    params, images, plucker_rays(c2w, intrinsics, 8, 8), config, jnp.zeros((2, 2))
  )
  first, c = config.num_gs_tokens, config.enc_embed_dim
  tokens = jax.random.normal(jax.random.key(7), (2, config.num_tokens, c))
  other = jax.random.normal(jax.random.key(8), (2, config.num_dynamic_gs_tokens, c))

  def alone(params, tokens, other):
    def run(net):
      backbone = net.enc_dec_backbone
      _, static_kv = backbone.decode(tokens, encoded.keys, encoded.values)
      return backbone.decode_dynamic(other, static_kv, encoded.keys, encoded.values)

    return TokenGS(config).apply({"params": params}, method=run)

  def full(params, tokens, other):
    decoded = decode_tokens(params, encoded, config, tokens.at[:, first:].set(other))
    return decoded[:, first:]

  got, expected = jax.jit(alone)(params, tokens, other), jax.jit(full)(params, tokens, other)
  np.testing.assert_allclose(np.asarray(got), np.asarray(expected), rtol=0, atol=1e-5)
  assert float(jnp.abs(full(params, tokens, tokens[:, first:]) - expected).max()) > 1e-2

  weights = jax.random.normal(jax.random.key(9), got.shape)
  grads = [
    jax.jit(jax.grad(lambda *a, f=f: jnp.sum(f(*a) * weights), argnums=(0, 1, 2)))(
      params, tokens, other
    )
    for f in (alone, full)
  ]
  for new, old in zip(jax.tree.leaves(grads[0]), jax.tree.leaves(grads[1]), strict=True):
    np.testing.assert_allclose(
      np.asarray(new), np.asarray(old), rtol=0, atol=1e-5 * max(1.0, float(jnp.abs(old).max()))
    )
  assert float(jnp.abs(grads[0][1][:, :first]).max()) > 1e-3  # the static tokens reach them
