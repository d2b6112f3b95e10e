"""The TokenGS network (`tokengs_jax.model.network`): parity with the official PyTorch model
(decoder tokens and Gaussians; bfloat16 compute), the latent bottleneck's encoding, decoding
the dynamic tokens alone, linear motion and static scenes (the dynamic branch skipped)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scenes import FULL, full_params, official_fixture, random_inputs

from tokengs_jax import model
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


# ----- linear motion and static scenes ------------------------------------------------------------


def _tiny_dynamic(key, **overrides):
  """(config, params, encoded) of a tiny dynamic model on random views at times 0 and 1, its
  time-dependent parameters (target-time embedding or velocities) random: at initialisation they
  are zero, and time would move nothing."""
  config = model.preset(
    "tiny",
    image_size=(16, 16),
    num_gs_tokens=6,
    num_dynamic_gs_tokens=3,
    time_embedding=True,
    dec_patch_size=2,
    clip_head_readout_std=0.02,
    **overrides,
  )
  params = model.init_params(jax.random.key(key), config)
  for name in ("patch_time_embed", "patch_time_embed_tgt", "motion_head"):
    if name in params:
      layer = params[name].get("proj", params[name])
      layer["kernel"] = jax.random.normal(jax.random.key(key + 1), layer["kernel"].shape)
  images, c2w, intrinsics = random_inputs(jax.random.key(key + 2), 1, 2, 16, 16)
  encoded = model.encode_views(params, images, c2w, intrinsics, config, jnp.array([[0.0, 1.0]]))
  return config, params, encoded


def test_linear_motion_moves_only_the_dynamic_centres_linearly_in_time():
  """`dynamic_motion="linear"`: between two times only the dynamic Gaussians' centres change, by
  velocity x time difference: the same velocity for every interval, none at the reference time
  0.5 against an unconditioned decode, and none at all while the motion head is at its init."""
  config, params, encoded = _tiny_dynamic(3, dynamic_motion="linear")
  first = config.num_static_gaussians
  at = {t: model.decode(params, encoded, config, times=jnp.array([t])) for t in (0.1, 0.5, 0.9)}
  np.testing.assert_array_equal(np.asarray(at[0.1][:, :first]), np.asarray(at[0.9][:, :first]))
  np.testing.assert_array_equal(np.asarray(at[0.1][..., 3:]), np.asarray(at[0.9][..., 3:]))
  np.testing.assert_allclose(
    np.asarray(at[0.5]), np.asarray(model.decode(params, encoded, config)), rtol=0, atol=1e-6
  )
  late, early = at[0.9] - at[0.5], at[0.5] - at[0.1]
  np.testing.assert_allclose(np.asarray(late), np.asarray(early), rtol=0, atol=1e-5)
  assert float(jnp.abs(late[:, first:, :3]).min()) > 0  # every dynamic Gaussian moves

  still = dict(params, motion_head=jax.tree.map(jnp.zeros_like, params["motion_head"]))
  np.testing.assert_array_equal(
    np.asarray(model.decode(still, encoded, config, times=jnp.array([0.1]))),
    np.asarray(model.decode(still, encoded, config, times=jnp.array([0.9]))),
  )


def test_linear_motion_needs_dynamic_tokens_and_time():
  with pytest.raises(ValueError, match="dynamic_motion"):
    model.preset("tiny", dynamic_motion="linear")
  with pytest.raises(ValueError, match="dynamic_motion"):
    model.preset("tiny", dynamic_motion="spline")


@pytest.mark.parametrize("motion", ["decoded", "linear"])
def test_a_static_scene_skips_the_dynamic_branch_and_keeps_the_static_gaussians(motion):
  """`decode(static_scene=True)`: exactly the static rows of the full decode (whatever the target
  time), for a fraction of its work, and nothing of the dynamic branch reaches it."""
  config, params, encoded = _tiny_dynamic(5, dynamic_motion=motion)
  first = config.num_static_gaussians
  full = model.decode(params, encoded, config, times=jnp.array([0.7]))
  static = model.decode(params, encoded, config, times=jnp.array([0.7]), static_scene=True)
  assert static.shape == (1, first, 14)
  np.testing.assert_allclose(np.asarray(static), np.asarray(full[:, :first]), rtol=0, atol=1e-6)

  def flops(static_scene):
    run = jax.jit(
      lambda p: model.decode(p, encoded, config, times=jnp.array([0.7]), static_scene=static_scene)
    )
    return run.lower(params).compile().cost_analysis()["flops"]

  assert flops(True) < 0.8 * flops(False)
  grads = jax.grad(
    lambda p: jnp.sum(model.decode(p, encoded, config, times=jnp.array([0.7]), static_scene=True))
  )(params)
  for name in ("gs_tokens_dynamic", "patch_time_embed_tgt", "motion_head"):
    if name in grads:
      assert not any(bool(jnp.any(g != 0)) for g in jax.tree.leaves(grads[name])), name


def test_reconstruct_of_a_static_scene_returns_the_static_gaussians():
  config, params, _ = _tiny_dynamic(7)
  images, c2w, intrinsics = random_inputs(jax.random.key(8), 1, 2, 16, 16)
  times = jnp.array([[0.0, 1.0]])
  kwargs = dict(config=config, times=times, target_times=jnp.array([0.5]))
  full = model.reconstruct(params, images, c2w, intrinsics, **kwargs)
  static = model.reconstruct(params, images, c2w, intrinsics, static_scene=True, **kwargs)
  assert static.means.shape == (1, config.num_static_gaussians, 3)
  np.testing.assert_allclose(
    np.asarray(static.means), np.asarray(full.means[:, : config.num_static_gaussians]), atol=1e-6
  )
