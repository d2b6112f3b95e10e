"""Official checkpoints (`tokengs_jax.model.official`): loading (strict names and shapes; BF16,
F16 and F32 safetensors), the safetensors reader, the state-dict round trip and official names."""

import json
import struct

import jax
import numpy as np
import pytest
from conftest import reference_fixture
from safetensors.numpy import load_file, save_file
from scenes import FULL, full_init, official_fixture

from tokengs_jax.model import (
  load_official_checkpoint,
  param_shapes,
  params_from_state_dict,
  to_official_state_dict,
)
from tokengs_jax.model.official import official_name, read_safetensors


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
