"""Official checkpoints (`tokengs_jax.model.official`): loading (strict names and shapes; BF16,
F16 and F32 safetensors; torch `.pth` files without torch), non-strict loads that seed a model with
more tokens, dynamic tokens or another latent count, the safetensors reader, the state-dict round
trip and official names."""

import json
import logging
import pathlib
import shutil
import struct
import zipfile

import jax
import numpy as np
import pytest
from conftest import reference_fixture
from safetensors.numpy import load_file, save_file
from scenes import FULL, full_init, official_fixture

from tokengs_jax.data.chunks import ChunkError, UnsafeChunkError, save_tensor_archive
from tokengs_jax.model import (
  load_official_checkpoint,
  param_shapes,
  params_from_state_dict,
  to_official_state_dict,
)
from tokengs_jax.model.official import official_name, read_safetensors
from tokengs_jax.train import transplant_params

# The tiny official fixture's weights as `torch.save(module.state_dict())` writes them (an
# OrderedDict with `_metadata`), made by `tests/data/make_official_tiny_pth.py` with real torch.
OFFICIAL_TINY_PTH = pathlib.Path(__file__).parent / "data" / "official_tiny.pth"


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


def test_linear_motion_weights_are_not_exported_as_official():
  config = FULL.replace(dynamic_motion="linear")
  params = jax.tree.map(np.zeros_like, param_shapes(config))
  assert "motion_head" in params and "patch_time_embed_tgt" not in params
  with pytest.raises(ValueError, match="no official counterpart"):
    to_official_state_dict(params, config)


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


def _assert_same_params(got, want):
  assert jax.tree.structure(got) == jax.tree.structure(want)
  for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
    assert a.dtype == np.float32 and a.flags.c_contiguous and a.flags.writeable
    np.testing.assert_array_equal(a, b)


def test_torch_pth_written_by_torch_loads_to_the_safetensors_params(tmp_path):
  config, params, _ = official_fixture()
  _assert_same_params(load_official_checkpoint(OFFICIAL_TINY_PTH, config), params)
  # the official loaders read anything not ending in "safetensors" with torch.load
  shutil.copyfile(OFFICIAL_TINY_PTH, tmp_path / "model.pt")
  _assert_same_params(load_official_checkpoint(tmp_path / "model.pt", config), params)
  # a plain dict (no OrderedDict metadata) loads too; strict checks apply to .pth files as well
  state = load_file(reference_fixture("official_tokengs_tiny", "weights.safetensors"))
  del state["enc_dec_backbone.kv_proj.bias"]
  save_tensor_archive(tmp_path / "broken.pth", state)
  with pytest.raises(ValueError, match="missing \\(1\\): enc_dec_backbone.kv_proj.bias"):
    load_official_checkpoint(tmp_path / "broken.pth", config)


def _with_pickle(tmp_path, pickle_bytes: bytes) -> pathlib.Path:
  """The fixture .pth with its data.pkl replaced (the storages stay)."""
  path = tmp_path / "forged.pth"
  with zipfile.ZipFile(OFFICIAL_TINY_PTH) as source, zipfile.ZipFile(path, "w") as forged:
    for info in source.infolist():
      data = pickle_bytes if info.filename.endswith("/data.pkl") else source.read(info)
      forged.writestr(info, data)
  return path


def test_torch_pth_reader_allows_only_state_dict_metadata(tmp_path):
  config, _, _ = official_fixture()
  ordered_dict = b"ccollections\nOrderedDict\n)R"  # OrderedDict()
  metadata = b"}X\x09\x00\x00\x00_metadata" + ordered_dict + b"s"  # {"_metadata": OrderedDict()}
  forged = {  # BUILD setting another attribute, or on anything but an OrderedDict, is refused
    b"\x80\x02" + ordered_dict + b"}X\x04\x00\x00\x00evilK\x01sb.": "BUILD on OrderedDict",
    b"\x80\x02]" + metadata + b"b.": "BUILD on list",
    b"\x80\x02cos\nsystem\nX\x04\x00\x00\x00true\x85R.": "global 'os.system'",
  }
  for data, refusal in forged.items():
    with pytest.raises(UnsafeChunkError, match=f"refusing .*{refusal}"):
      load_official_checkpoint(_with_pickle(tmp_path, data), config)
  # an empty state dict with metadata is read (and then lacks every tensor)
  with pytest.raises(ValueError, match="missing"):
    load_official_checkpoint(
      _with_pickle(tmp_path, b"\x80\x02" + ordered_dict + metadata + b"b."), config
    )
  # a top level that is not a name -> tensor mapping is named
  save_tensor_archive(tmp_path / "wrapped.pth", {"model": {"w": np.zeros(2, np.float32)}})
  with pytest.raises(ChunkError, match="not a state dict"):
    load_official_checkpoint(tmp_path / "wrapped.pth", config)
  (tmp_path / "junk.pth").write_bytes(b"not a zip")
  with pytest.raises(ChunkError, match="not a readable zip"):
    load_official_checkpoint(tmp_path / "junk.pth", config)


def _zeros_like(config):
  return jax.tree.map(lambda s: np.zeros(s.shape, np.float32), param_shapes(config))


def test_non_strict_load_seeds_more_tokens_and_dynamic_tokens(caplog):
  config, params, _ = official_fixture()
  grown = config.replace(num_gs_tokens=10, num_dynamic_gs_tokens=6, time_embedding=True)
  with caplog.at_level(logging.WARNING, logger="tokengs_jax.model.official"):
    loaded = load_official_checkpoint(OFFICIAL_TINY_PTH, grown, strict=False)
  # what the model has and the checkpoint lacks is listed, the tables keep the checkpoint's rows
  assert "missing (5): gs_tokens_dynamic, patch_time_embed.proj.bias" in caplog.text
  assert loaded["gs_tokens"].shape == (4, 32) and "gs_tokens_dynamic" not in loaded
  seeded, report = transplant_params(jax.random.key(0), loaded, _zeros_like(grown))
  tokens = np.asarray(seeded["gs_tokens"])
  np.testing.assert_array_equal(tokens[:4], params["gs_tokens"])
  extra = tokens[4:] - params["gs_tokens"][np.array([0, 1, 2, 3, 0, 1])]  # cyclic copies + noise
  assert 0 < np.abs(extra).max() < 0.1
  np.testing.assert_array_equal(
    seeded["gs_tokens_dynamic"], params["gs_tokens"][np.array([0, 1, 2, 3, 0, 1])]
  )
  assert {"gs_tokens: tokens 4 -> 10", "gs_tokens_dynamic: from static gs_tokens"} <= set(report)
  np.testing.assert_array_equal(
    seeded["enc_dec_backbone"]["kv_proj"]["kernel"], params["enc_dec_backbone"]["kv_proj"]["kernel"]
  )


def test_non_strict_load_still_refuses_misshapen_tensors_and_lists_unexpected(caplog):
  config, _, _ = official_fixture()
  state = load_file(reference_fixture("official_tokengs_tiny", "weights.safetensors"))
  state["enc_dec_backbone.extra_thing.weight"] = np.zeros(3, np.float32)
  with caplog.at_level(logging.WARNING, logger="tokengs_jax.model.official"):
    params_from_state_dict(state, config, strict=False)
  assert "unexpected (1): enc_dec_backbone.extra_thing.weight" in caplog.text
  for name, shape in (("enc_dec_backbone.kv_proj.bias", (5,)), ("gs_tokens", (4, 16))):
    broken = dict(state, **{name: np.zeros(shape, np.float32)})
    with pytest.raises(ValueError, match=f"shape mismatch \\(1\\): {name}"):
      params_from_state_dict(broken, config, strict=False)


def test_non_strict_load_grows_or_thins_the_latent_table_as_the_official_code():
  pretrained = jax.tree.map(
    lambda s: np.random.default_rng(0).normal(size=s.shape).astype(np.float32), param_shapes(FULL)
  )
  state = to_official_state_dict(pretrained, FULL)
  latents = pretrained["enc_dec_backbone"]["latents"]  # [6, 32]
  for count, expected_rows in ((3, latents[np.array([0, 2, 5])]), (9, None)):
    config = FULL.replace(num_latents=count)
    loaded = params_from_state_dict(state, config, strict=False)
    seeded, report = transplant_params(jax.random.key(0), loaded, _zeros_like(config))
    table = np.asarray(seeded["enc_dec_backbone"]["latents"])
    assert f"enc_dec_backbone/latents: tokens 6 -> {count}" in report
    if expected_rows is not None:  # fewer: torch.linspace(0, 5, 3).long() rows
      np.testing.assert_array_equal(table, expected_rows)
    else:  # more: the old rows, then cyclic copies plus N(0, 0.01^2) noise
      np.testing.assert_array_equal(table[:6], latents)
      assert 0 < np.abs(table[6:] - latents[:3]).max() < 0.1
