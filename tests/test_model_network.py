"""The TokenGS network (`tokengs_jax.model.network`): parity with the official PyTorch model
(decoder tokens and Gaussians; bfloat16 compute) and the latent bottleneck's encoding."""

import jax
import jax.numpy as jnp
import numpy as np
from scenes import FULL, full_params, official_fixture, random_inputs

from tokengs_jax.camera import plucker_rays
from tokengs_jax.model import (
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
