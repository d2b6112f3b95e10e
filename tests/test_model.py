"""TokenGS network: parity with the official PyTorch model, checkpoint loading, semantics."""

import functools
import json
import struct

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import reference_fixture
from safetensors.numpy import load_file, save_file
from scenes import DYNAMIC_CONFIG, dynamic_batch, dynamic_params

from tokengs_jax import model
from tokengs_jax.camera import plucker_rays
from tokengs_jax.gaussians import Gaussians
from tokengs_jax.model import (
  ModelConfig,
  config_from_official,
  count_params,
  decode,
  decode_at_times,
  decode_tokens,
  encode,
  encode_views,
  init_params,
  initial_tokens,
  kv_from_latents,
  load_official_checkpoint,
  normalize_images,
  param_shapes,
  params_from_state_dict,
  predict_gaussians,
  preset,
  reconstruct,
  to_official_state_dict,
)
from tokengs_jax.model.configs import IMAGE_MEAN, IMAGE_STD
from tokengs_jax.model.decoder import block_causal_mask
from tokengs_jax.model.head import activate
from tokengs_jax.model.layers import attend, attention_tiling
from tokengs_jax.model.official import official_name, read_safetensors

# A config small enough that each test compiles in about a second.
MICRO = ModelConfig(
  patch_size=4,
  dec_patch_size=2,
  enc_depth=1,
  dec_depth=2,
  enc_embed_dim=32,
  enc_num_heads=2,
  num_gs_tokens=4,
  image_size=(16, 16),
)
# Every optional part at once: multiscale readout, latent bottleneck, dynamic tokens, time.
FULL = MICRO.replace(
  enc_depth=3,
  use_multiscale_encoder=True,
  multiscale_encoder_layers=(0, 1, 2),
  use_latent_bottleneck=True,
  num_latents=6,
  latent_cross_attn_depth=2,
  num_dynamic_gs_tokens=3,
  time_embedding=True,
  dec_init_values=0.01,
  clip_head_z_init=0.1,
)


@functools.cache
def micro_params():
  return init_params(jax.random.key(0), MICRO)


@functools.cache
def full_init():
  return init_params(jax.random.key(1), FULL)


@functools.cache
def full_params():
  """FULL params with non-zero time embeds (they start at zero) so that time really matters."""
  params = jax.tree.map(lambda x: x, full_init())
  keys = jax.random.split(jax.random.key(2), 2)
  for key, name in zip(keys, ("patch_time_embed", "patch_time_embed_tgt")):
    kernel = params[name]["proj"]["kernel"]
    params[name]["proj"]["kernel"] = jax.random.normal(key, kernel.shape)
  return params


@functools.cache
def official_fixture():
  config = config_from_official(
    json.loads((reference_fixture("official_tokengs_tiny", "options.json")).read_text())
  )
  params = load_official_checkpoint(
    reference_fixture("official_tokengs_tiny", "weights.safetensors"), config
  )
  io = dict(np.load(reference_fixture("official_tokengs_tiny", "io.npz")))
  # torch NCHW -> our NHWC
  io["images_rgb"] = io["images_rgb"].transpose(0, 1, 3, 4, 2)
  io["plucker"] = io["plucker"].transpose(0, 1, 3, 4, 2)
  return config, params, io


def random_inputs(key, batch, views, height, width):
  k1, k2, k3 = jax.random.split(key, 3)
  images = jax.random.uniform(k1, (batch, views, height, width, 3))
  angles = jax.random.normal(k2, (batch, views, 3)) * 0.3
  rot = jax.vmap(jax.vmap(lambda a: jax.scipy.linalg.expm(jnp.cross(jnp.eye(3), a))))(angles)
  c2w = jnp.zeros((batch, views, 4, 4)).at[..., :3, :3].set(rot).at[..., 3, 3].set(1.0)
  c2w = c2w.at[..., :3, 3].set(jax.random.normal(k3, (batch, views, 3)) * 0.2)
  intrinsics = jnp.broadcast_to(
    jnp.array([width * 1.1, height * 1.1, width / 2, height / 2]), (batch, views, 4)
  )
  return images, c2w, intrinsics


# ----- parity with the official model (top priority) ------------------------------------------


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


def test_official_reconstruct_from_raw_images_and_cameras():
  """reconstruct = our ImageNet normalisation + our Plücker rays + the network."""
  config, params, io = official_fixture()
  images01 = io["images_rgb"] * np.array(IMAGE_STD) + np.array(IMAGE_MEAN)
  run = jax.jit(functools.partial(reconstruct, config=config))
  gaussians = run(params, images01, io["c2w"], io["intrinsics"])
  assert isinstance(gaussians, Gaussians)
  np.testing.assert_allclose(gaussians.to_flat(), io["gaussians"], rtol=0, atol=1e-4)


def test_bfloat16_compute_keeps_float32_params_and_stays_close():
  config, params, io = official_fixture()
  bf16 = config.replace(dtype="bfloat16")
  flat = jax.jit(predict_gaussians, static_argnums=3)(params, io["images_rgb"], io["plucker"], bf16)
  assert flat.dtype == jnp.float32
  assert all(leaf.dtype == jnp.float32 for leaf in jax.tree.leaves(param_shapes(bf16)))
  err = np.abs(np.asarray(flat) - io["gaussians"]).max()
  assert 0 < err < 0.05  # bf16 rounding, but no gross error


# ----- tiled attention -----------------------------------------------------------------------------


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


# ----- official checkpoints ----------------------------------------------------------------------


def test_config_from_official_options():
  config, _, _ = official_fixture()
  assert (config.enc_depth, config.dec_depth, config.enc_embed_dim, config.enc_num_heads) == (
    2,
    2,
    32,
    2,
  )
  assert config.dec_patch_size == config.patch_size == 8  # dec_patch_size defaults to patch
  assert config.image_size == (16, 24) and config.num_gaussians == 4 * 64
  assert config_from_official({"patch_size": 4, "dec_patch_size": None}).dec_patch_size == 4
  latent = config_from_official(
    {
      "use_latent_bottleneck": True,
      "clip_head_z_init": 0.1,
      "multiscale_encoder_layers": [5, 7, 9, 11],
    }
  )
  assert latent.use_latent_bottleneck and latent.multiscale_encoder_layers == (5, 7, 9, 11)
  with pytest.raises(ValueError, match="token_dim"):
    config_from_official({"enc_embed_dim": 64, "token_dim": 32, "enc_num_heads": 2})


def test_loader_names_missing_unexpected_and_misshapen_tensors():
  config, _, _ = official_fixture()
  state = load_file(reference_fixture("official_tokengs_tiny", "weights.safetensors"))
  broken = dict(state)
  del broken["enc_dec_backbone.kv_proj.bias"]
  broken["enc_dec_backbone.extra_thing.weight"] = np.zeros(3, np.float32)
  broken["gs_tokens"] = np.zeros((5, 32), np.float32)
  with pytest.raises(ValueError) as error:
    params_from_state_dict(broken, config)
  message = str(error.value)
  assert "missing (1): enc_dec_backbone.kv_proj.bias" in message
  assert "unexpected (1): enc_dec_backbone.extra_thing.weight" in message
  assert "gs_tokens: checkpoint (5, 32) != model (4, 32)" in message
  # a config with more tokens than the checkpoint is refused too
  with pytest.raises(ValueError, match="gs_tokens"):
    params_from_state_dict(state, config.replace(num_gs_tokens=8))


def _bfloat16_bits(values: np.ndarray) -> np.ndarray:
  """float32 -> bfloat16 bit patterns (uint16), round to nearest even, written out by hand."""
  bits = np.ascontiguousarray(values, np.float32).view(np.uint32).astype(np.uint64)
  return ((bits + 0x7FFF + ((bits >> 16) & 1)) >> 16).astype(np.uint16)


def _write_bf16_safetensors(path, state: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
  """Writes `state` as a BF16 safetensors file byte by byte; returns the float32 values stored."""
  header, chunks, stored, offset = {"__metadata__": {"format": "pt"}}, [], {}, 0
  for name, value in state.items():
    bits = _bfloat16_bits(value)
    header[name] = {
      "dtype": "BF16",
      "shape": list(value.shape),
      "data_offsets": [offset, offset + bits.nbytes],
    }
    chunks.append(bits.astype("<u2").tobytes())
    stored[name] = (bits.astype(np.uint32) << 16).view(np.float32).reshape(value.shape)
    offset += bits.nbytes
  header_bytes = json.dumps(header).encode()
  header_bytes += b" " * (-len(header_bytes) % 8)  # the format pads the header to 8 bytes
  with open(path, "wb") as f:
    f.write(struct.pack("<Q", len(header_bytes)) + header_bytes + b"".join(chunks))
  return stored


def test_loader_reads_bf16_f16_and_f32_checkpoints(tmp_path):
  config, params, _ = official_fixture()
  state = load_file(reference_fixture("official_tokengs_tiny", "weights.safetensors"))
  stored_bf16 = _write_bf16_safetensors(tmp_path / "bf16.safetensors", state)
  save_file({k: v.astype(np.float16) for k, v in state.items()}, tmp_path / "f16.safetensors")
  save_file(state, tmp_path / "f32.safetensors")
  raw = read_safetensors(tmp_path / "bf16.safetensors")
  assert raw.keys() == state.keys() and raw["gs_tokens"].dtype.name == "bfloat16"
  # bf16 really rounds these weights (so the comparison below is not vacuous), f16 too
  assert np.abs(stored_bf16["gs_tokens"] - state["gs_tokens"]).max() > 0
  expected = {
    "bf16": params_from_state_dict(stored_bf16, config),
    "f16": params_from_state_dict(
      {k: v.astype(np.float16).astype(np.float32) for k, v in state.items()}, config
    ),
    "f32": params,
  }
  for name, want in expected.items():
    loaded = load_official_checkpoint(tmp_path / f"{name}.safetensors", config)
    assert jax.tree.structure(loaded) == jax.tree.structure(want)
    for got, ref in zip(jax.tree.leaves(loaded), jax.tree.leaves(want)):
      assert got.dtype == np.float32 and got.flags.c_contiguous and got.flags.writeable
      np.testing.assert_array_equal(got, ref, err_msg=name)
  # the strict checks still apply to bf16 files
  del stored_bf16["enc_dec_backbone.kv_proj.bias"]
  _write_bf16_safetensors(tmp_path / "broken.safetensors", stored_bf16)
  with pytest.raises(ValueError, match="missing \\(1\\): enc_dec_backbone.kv_proj.bias"):
    load_official_checkpoint(tmp_path / "broken.safetensors", config)


def test_safetensors_reader_rejects_bad_byte_ranges(tmp_path):
  header = json.dumps({"w": {"dtype": "BF16", "shape": [2, 3], "data_offsets": [0, 10]}}).encode()
  (tmp_path / "bad.safetensors").write_bytes(struct.pack("<Q", len(header)) + header + bytes(12))
  with pytest.raises(ValueError, match="byte range"):
    read_safetensors(tmp_path / "bad.safetensors")


def test_state_dict_round_trip_is_exact():
  config, params, _ = official_fixture()
  state = load_file(reference_fixture("official_tokengs_tiny", "weights.safetensors"))
  exported = to_official_state_dict(params, config)
  assert exported.keys() == state.keys()
  for name, value in state.items():
    np.testing.assert_array_equal(exported[name], value, err_msg=name)


def test_latent_multiscale_dynamic_names_follow_official_enc_dec():
  shapes = {
    official_name(tuple(k.key for k in path)): leaf.shape
    for path, leaf in jax.tree_util.tree_leaves_with_path(param_shapes(FULL))
  }
  backbone = "enc_dec_backbone."
  for name in (
    "latents",
    "latent_feature_k_norm.weight",
    "latent_kv_proj.bias",
    "latent_blocks.1.gs_cross_attn.q_norm.weight",
    "latent_blocks.1.mlp_scale.gamma",
    "multiscale_norms.2.bias",
    "k_proj_norm.weight",
    "encoder.2.ls2.gamma",
    "decoder_blocks.1.gs_self_attn.gs_self_attn.qkv.weight",
  ):
    assert backbone + name in shapes, name
  for name in ("kv_proj.weight", "encoder_norm.weight", "multiscale_norms.3.weight"):
    assert backbone + name not in shapes, name
  assert shapes["gs_tokens_dynamic"] == (3, 32)
  assert shapes["patch_time_embed.proj.weight"] == (16 * 2, 32)  # ours: [(p, p, T), C]
  assert "patch_time_embed.norm.weight" not in shapes  # time embeds have no norm
  assert shapes[backbone + "latent_feature_kv_proj.weight"] == (3 * 32, 64)  # ours [F=3C, 2C]
  assert shapes[backbone + "latents"] == (6, 32)
  params = full_init()
  # the 0.01 decoder LayerScale (dec_init_values) and zero-initialised time embeds
  np.testing.assert_allclose(
    params["enc_dec_backbone"]["decoder_blocks_0"]["mlp_scale"]["gamma"], 0.01, rtol=1e-6
  )
  assert not np.any(params["patch_time_embed_tgt"]["proj"]["kernel"])


def test_decoder_layer_scale_rule():
  assert MICRO.decoder_layer_scale == pytest.approx(5e-3 * 0.01)  # official default rule
  assert MICRO.replace(dec_init_values=0.01).decoder_layer_scale == 0.01
  no_scale = MICRO.replace(gs_token_std=0.0)  # official: Identity instead of LayerScale
  names = {
    official_name(tuple(k.key for k in path))
    for path, _ in jax.tree_util.tree_leaves_with_path(param_shapes(no_scale))
  }
  assert not any("gs_cross_attn_scale" in n for n in names)


# ----- head --------------------------------------------------------------------------------------


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


# ----- semantics ---------------------------------------------------------------------------------


def test_gaussian_count_is_independent_of_views_and_resolution():
  params = param_shapes(MICRO)
  counts = set()
  for views, height, width in ((1, 8, 8), (3, 12, 16), (6, 32, 4)):
    images, c2w, intrinsics = random_inputs(jax.random.key(views), 2, views, height, width)
    shapes = jax.eval_shape(
      functools.partial(reconstruct, config=MICRO), params, images, c2w, intrinsics
    )  # shapes only, nothing is computed
    counts.add(shapes.means.shape)
  assert counts == {(2, MICRO.num_gaussians, 3)}
  assert MICRO.num_gaussians == 4 * 2 * 2


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


def test_decode_at_times_equals_reconstruct_at_each_time():
  params = dynamic_params()
  batch = dynamic_batch([[0.0, 1.0], [0.2, 0.9]], [[0.5, 0.0, 1.0], [0.3, 0.6, 0.1]])
  context = (batch["context_images"], batch["context_c2w"], batch["context_intrinsics"])

  @jax.jit
  def decoded(params, images, c2w, intrinsics, times, target_times):
    encoded = model.encode_views(params, images, c2w, intrinsics, DYNAMIC_CONFIG, times=times)
    return decode_at_times(params, encoded, DYNAMIC_CONFIG, target_times)

  reconstruct = jax.jit(
    lambda *args, **kwargs: model.reconstruct(*args, config=DYNAMIC_CONFIG, **kwargs)
  )
  at_times = decoded(params, *context, batch["context_times"], batch["target_times"])
  assert at_times.batch_shape == (2, 3)
  static = DYNAMIC_CONFIG.num_static_gaussians
  for t in range(3):
    expected = reconstruct(
      params, *context, times=batch["context_times"], target_times=batch["target_times"][:, t]
    )
    at_t = jax.tree.map(lambda x, index=t: x[:, index], at_times)
    jax.tree.map(
      lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6), at_t, expected
    )
  # static Gaussians do not depend on the time, dynamic ones do
  means = np.asarray(at_times.means)
  np.testing.assert_allclose(means[:, 1, :static], means[:, 0, :static], rtol=1e-6, atol=1e-7)
  assert np.abs(means[:, 1, static:] - means[:, 0, static:]).max() > 1e-3


def test_jit_vmap_grad_through_reconstruct():
  params = micro_params()
  images, c2w, intrinsics = random_inputs(jax.random.key(1), 3, 2, 8, 8)

  def loss(p, imgs, cams, intr):
    g = reconstruct(p, imgs, cams, intr, config=MICRO)
    return jnp.sum(g.means**2) + jnp.sum(g.colors) + jnp.sum(g.opacities), g

  grad = jax.grad(loss, argnums=(0, 1), has_aux=True)
  (grads, image_grad), batched = jax.jit(grad)(params, images, c2w, intrinsics)
  # the same per scene, through vmap: the batched loss is the sum of the per-scene ones
  per_scene = jax.jit(jax.vmap(lambda i, c, k: grad(params, i[None], c[None], k[None])))
  (scene_grads, scene_image_grad), scene_gaussians = per_scene(images, c2w, intrinsics)
  np.testing.assert_allclose(scene_gaussians.means[:, 0], batched.means, atol=1e-5)
  np.testing.assert_allclose(scene_image_grad[:, 0], image_grad, atol=1e-5)
  jax.tree.map(
    lambda a, b: np.testing.assert_allclose(a.sum(0), b, rtol=1e-4, atol=1e-5), scene_grads, grads
  )
  assert all(np.all(np.isfinite(g)) for g in jax.tree.leaves(grads))
  assert np.abs(np.asarray(grads["gs_tokens"])).max() > 0
  assert np.abs(np.asarray(grads["patch_embed"]["proj"]["kernel"])).max() > 0
  assert np.abs(np.asarray(image_grad)).max() > 0


def test_encode_views_is_normalise_plucker_encode():
  params = micro_params()
  images, c2w, intrinsics = random_inputs(jax.random.key(4), 2, 2, 8, 8)
  run = jax.jit(functools.partial(encode_views, config=MICRO))
  encoded = run(params, images, c2w, intrinsics)
  expected = jax.jit(encode, static_argnums=3)(
    params, normalize_images(images), plucker_rays(c2w, intrinsics, 8, 8), MICRO
  )
  # one program vs two: equal up to XLA's fusion-dependent rounding
  chex.assert_trees_all_close(encoded, expected, rtol=0, atol=1e-5)


def _bad_views(change: str):
  """(config, images, c2w, intrinsics, times, target_times) valid but for `change`."""
  images, c2w, intrinsics = (np.asarray(x) for x in random_inputs(jax.random.key(5), 2, 3, 8, 8))
  config, times, target_times = MICRO, None, None
  if change == "images rank":
    images = images[0]
  elif change == "images channels":
    images = images[..., :2]
  elif change == "images dtype":
    images = (images * 255).astype(np.int32)
  elif change == "patch size":
    images = images[:, :, :6]
  elif change == "c2w shape":
    c2w = c2w[..., :3, :]
  elif change == "c2w dtype":
    c2w = c2w.astype(np.int32)
  elif change == "intrinsics shape":
    intrinsics = intrinsics[:, :2]
  elif change == "intrinsics dtype":
    intrinsics = intrinsics.astype(np.int32)
  elif change == "focal":
    intrinsics = intrinsics.copy()
    intrinsics[1, 2, 1] = 0.0
  elif change == "times missing":
    config = FULL
  elif change == "times unexpected":
    times = np.zeros((2, 3), np.float32)
  elif change == "times shape":
    config, times = FULL, np.zeros((2, 2), np.float32)
  elif change == "times dtype":
    config, times = FULL, np.zeros((2, 3), np.int32)
  elif change == "target_times shape":
    config, times, target_times = FULL, np.zeros((2, 3), np.float32), np.zeros((2, 1), np.float32)
  return config, images, c2w, intrinsics, times, target_times


@pytest.mark.parametrize(
  "change, error, message",
  [
    ("images rank", ValueError, r"images must be \[B, V, H, W, 3\]"),
    ("images channels", ValueError, r"images must be \[B, V, H, W, 3\]"),
    ("images dtype", TypeError, "images must be floating point in \\[0, 1\\] or uint8"),
    ("patch size", ValueError, "divisible by the patch size 4"),
    ("c2w shape", ValueError, r"c2w must be \[B, V, 4, 4\] = \(2, 3, 4, 4\), got shape"),
    ("c2w dtype", TypeError, "c2w must be floating point"),
    ("intrinsics shape", ValueError, r"intrinsics must be \[B, V, 4\]"),
    ("intrinsics dtype", TypeError, "intrinsics must be floating point"),
    ("focal", ValueError, "fx, fy must be > 0"),
    ("times missing", ValueError, "pass the input-view times"),
    ("times unexpected", ValueError, "without time embedding"),
    ("times shape", ValueError, r"times must be \[B, V\] = \(2, 3\), got shape \(2, 2\)"),
    ("times dtype", TypeError, "times must be floating point"),
    ("target_times shape", ValueError, r"target_times must be \[B\]"),
  ],
)
def test_reconstruct_rejects_bad_inputs_at_trace_time(change, error, message):
  config, images, c2w, intrinsics, times, target_times = _bad_views(change)
  params = jax.eval_shape(lambda: init_params(jax.random.key(0), config))
  trace = jax.eval_shape if change != "focal" else lambda f, *a: f(*a)  # values: concrete only
  with pytest.raises(error, match=message):
    trace(
      lambda *a: reconstruct(*a, config=config, times=times, target_times=target_times),
      params,
      images,
      c2w,
      intrinsics,
    )


def test_reconstruct_accepts_uint8_images_and_valid_views():
  for change in ("none", "images uint8"):
    config, images, c2w, intrinsics, _, _ = _bad_views(change)
    if change == "images uint8":
      images = (images * 255).astype(np.uint8)
    params = jax.eval_shape(lambda: init_params(jax.random.key(0), config))
    out = jax.eval_shape(lambda *a: reconstruct(*a, config=config), params, images, c2w, intrinsics)
    assert out.means.shape == (2, config.num_gaussians, 3)


@pytest.mark.slow
def test_remat_changes_nothing_but_memory():
  params = micro_params()
  images, c2w, intrinsics = random_inputs(jax.random.key(1), 1, 2, 8, 8)

  def loss(p, config):
    return jnp.sum(reconstruct(p, images, c2w, intrinsics, config=config).means)

  grad = jax.jit(jax.grad(loss), static_argnums=1)
  plain = grad(params, MICRO)
  remat = grad(params, MICRO.replace(remat=True))
  chex.assert_trees_all_close(plain, remat, rtol=1e-5, atol=1e-7)


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


# ----- presets -----------------------------------------------------------------------------------


def expected_param_count(c: ModelConfig) -> int:
  """Parameter count written out from the official module definitions."""
  width, head, hidden = c.enc_embed_dim, c.head_dim, c.mlp_hidden_dim

  def linear(i, o):
    return i * o + o

  norm = lambda n: 2 * n
  attention = linear(width, 3 * width) + 2 * norm(head) + linear(width, width)
  mlp = linear(width, hidden) + linear(hidden, width)
  encoder_block = 2 * norm(width) + attention + mlp + 2 * width

  def decoder_block(layer_scale):
    cross = norm(width) + 2 * linear(width, width) + norm(head)
    return cross + norm(width) + attention + norm(width) + mlp + (3 * width if layer_scale else 0)

  p = c.patch_size
  total = linear(3 * p * p, width) + linear(6 * p * p, width) + 2 * norm(width)
  if c.time_embedding:
    total += 2 * linear(c.time_embedding_dim * p * p, width)
  total += c.enc_depth * encoder_block
  total += (len(c.multiscale_encoder_layers) if c.use_multiscale_encoder else 1) * norm(width)
  if c.use_latent_bottleneck:
    total += linear(c.encoder_feature_dim, 2 * width) + norm(head) + c.num_latents * width
    total += c.latent_cross_attn_depth * decoder_block(True) + linear(width, 2 * width)
  else:
    total += linear(c.encoder_feature_dim, 2 * width)
  total += norm(head)  # k_proj_norm
  total += c.dec_depth * decoder_block(c.decoder_layer_scale)
  total += linear(width, 14 * c.dec_patch_size**2) + c.num_tokens * width
  return total


@pytest.mark.parametrize(
  "name", ["tiny", "re10k", "dl3dv_4view", "dl3dv_latent_6view", "kubric_dyn"]
)
def test_preset_parameter_counts(name):
  config = preset(name)
  count = count_params(config)  # jax.eval_shape: nothing is allocated
  assert count == expected_param_count(config)
  print(f"{name}: {count / 1e6:.2f} M parameters")


def test_preset_values():
  re10k = preset("re10k")
  assert (re10k.enc_depth, re10k.dec_depth, re10k.enc_embed_dim, re10k.num_gs_tokens) == (
    6,
    24,
    1024,
    1024,
  )
  assert preset("re10k_4096").num_gaussians == 4096 * 64
  dl3dv = preset("dl3dv_6view")
  assert (dl3dv.enc_depth, dl3dv.dec_depth, dl3dv.image_size, dl3dv.num_input_views) == (
    3,
    12,
    (256, 448),
    6,
  )
  latent = preset("dl3dv_latent_2view")
  assert latent.use_latent_bottleneck and latent.gaussian_z_offset == 0.0
  assert latent.multiscale_encoder_layers == (5, 7, 9, 11) and latent.decoder_layer_scale == 0.01
  kubric = preset("kubric_dyn")
  assert kubric.num_dynamic_gs_tokens == 256 and kubric.time_embedding
  assert preset("tiny", dtype="bfloat16").dtype == "bfloat16"
  with pytest.raises(KeyError, match="unknown preset"):
    preset("nope")


@pytest.mark.slow
def test_tiny_preset_runs_at_its_resolution():
  config = preset("tiny")
  params = init_params(jax.random.key(0), config)
  images, c2w, intrinsics = random_inputs(
    jax.random.key(1), 1, config.num_input_views, *config.image_size
  )
  gaussians = jax.jit(functools.partial(reconstruct, config=config))(
    params, images, c2w, intrinsics
  )
  assert gaussians.means.shape == (1, config.num_gaussians, 3)
  # at initialisation the Gaussians sit in front of the first camera (z-offset 1)
  np.testing.assert_allclose(np.asarray(gaussians.means[..., 2]).mean(), 1.0, atol=0.1)


def test_normalize_images_scales_uint8_and_refuses_what_it_cannot_convert():
  """uint8 is scaled by 1/255 (it once cast the ImageNet mean/std to uint8: NaN Gaussians);
  grayscale, integer types and 0..255 floats are refused with a message naming `images`."""
  rng = np.random.default_rng(0)
  pixels = rng.integers(0, 256, (2, 4, 5, 3), dtype=np.uint8)
  from_uint8 = np.asarray(normalize_images(pixels))
  assert from_uint8.dtype == np.float32 and np.isfinite(from_uint8).all()
  np.testing.assert_allclose(
    from_uint8, np.asarray(normalize_images(pixels / np.float32(255))), atol=1e-6
  )
  np.testing.assert_allclose(np.asarray(jax.jit(normalize_images)(pixels)), from_uint8, atol=1e-6)
  with pytest.raises(ValueError, match=r"images: expected RGB \[\.\.\., 3\].*grayscale"):
    normalize_images(pixels[..., :1])
  with pytest.raises(TypeError, match="images: expected float in .0, 1. or uint8.*int32"):
    normalize_images(pixels.astype(np.int32))
  with pytest.raises(ValueError, match=r"images: expected float values in \[0, 1\].*divide by 255"):
    normalize_images(pixels.astype(np.float32))


def test_normalize_images_checks_a_constant_captured_by_an_outer_jit():
  """A concrete array closed over by a jitted function is range-checked on the host (numpy),
  not with jnp ops that the outer trace would stage."""
  images = jnp.full((1, 2, 2, 3), 0.5)
  np.testing.assert_allclose(
    jax.jit(lambda: normalize_images(images))(), normalize_images(images), atol=1e-6
  )
