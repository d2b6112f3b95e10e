"""Official PyTorch checkpoints (.safetensors, torch .pth) <-> our params pytree, without torch.

Our module tree mirrors the official one (see `network.py`), so names map by rule:
  path segments joined with "."; a list entry "encoder_3" is torch "encoder.3";
  Dense "kernel" = torch Linear "weight" transposed ([in, out] vs [out, in]);
  patch-embed "kernel" [(p, p, Cin), out] = torch Conv2d "weight" [out, Cin, p, p] permuted;
  LayerNorm "scale" = torch "weight"; "bias", LayerScale "gamma", "gs_tokens",
  "gs_tokens_dynamic" and "latents" are stored as they are.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re

import einops
import jax
import ml_dtypes
import numpy as np

from tokengs_jax.model.api import Params, param_shapes
from tokengs_jax.model.configs import ModelConfig

# Keys the official `state_dict()` strips anyway (frozen LPIPS network inside the module).
_IGNORED_PREFIXES = ("lpips_loss.",)
# The [rows, width] tables the official finetuning resizes from a checkpoint with another count.
RESIZABLE_TABLES = ("gs_tokens", "gs_tokens_dynamic", "enc_dec_backbone.latents")
_LOG = logging.getLogger(__name__)
_LIST_ENTRY = re.compile(r"_(\d+)$")


def _is_patch_embed(path: tuple[str, ...]) -> bool:
  return path[0].startswith("patch_") and path[-1] == "kernel"


def official_name(path: tuple[str, ...]) -> str:
  """Our param path -> the official state_dict key."""
  *modules, leaf = path
  leaf = {"kernel": "weight", "scale": "weight"}.get(leaf, leaf)
  return ".".join([_LIST_ENTRY.sub(r".\1", m) for m in modules] + [leaf])


def _to_torch_layout(path: tuple[str, ...], value: np.ndarray, patch_size: int) -> np.ndarray:
  if _is_patch_embed(path):
    return einops.rearrange(value, "(p q c) o -> o c p q", p=patch_size, q=patch_size)
  if path[-1] == "kernel":
    return value.T
  return value


def _from_torch_layout(path: tuple[str, ...], value: np.ndarray) -> np.ndarray:
  if _is_patch_embed(path):
    return einops.rearrange(value, "o c p q -> (p q c) o")
  if path[-1] == "kernel":
    return value.T
  return value


def _torch_shape(path: tuple[str, ...], shape: tuple[int, ...], patch_size: int):
  return _to_torch_layout(path, np.empty(shape, np.bool_), patch_size).shape


def _flat_paths(tree) -> list[tuple[tuple[str, ...], object]]:
  leaves = jax.tree_util.tree_leaves_with_path(tree)
  return [(tuple(k.key for k in path), leaf) for path, leaf in leaves]


def _unflatten(items: dict[tuple[str, ...], np.ndarray]) -> Params:
  tree: dict = {}
  for path, value in items.items():
    node = tree
    for name in path[:-1]:
      node = node.setdefault(name, {})
    node[path[-1]] = value
  return tree


def _fits(name: str, stored: tuple[int, ...], wanted: tuple[int, ...], strict: bool) -> bool:
  if stored == wanted:
    return True
  resized = name in RESIZABLE_TABLES and len(stored) == len(wanted) == 2
  return not strict and resized and stored[1] == wanted[1]


def params_from_state_dict(
  state_dict: dict[str, np.ndarray], config: ModelConfig, *, strict: bool = True
) -> Params:
  """Official state_dict (numpy, torch layouts) -> params, with key and shape checks.

  Args:
    state_dict: official names -> tensors (the frozen LPIPS network's are ignored).
    config: the model's architecture.
    strict: the checkpoint must hold exactly the model's tensors. With False, as the official
      tolerant load (`load_model_checkpoint`) that seeds a model of another architecture from
      pretrained weights: missing and unexpected tensors are left out and logged (a warning
      naming every one), and the `RESIZABLE_TABLES` may have another row count (they come back
      at the checkpoint's size). The params are then partial: `train.transplant_params` fills
      them into fresh ones, growing or thinning the tables and seeding dynamic tokens from static
      ones as the official `init_tokens_from_existing`, `init_latents_from_existing` and
      `init_dynamic_tokens_from_static`.

  Raises:
    ValueError: naming every missing tensor, unexpected tensor and shape mismatch, on a
      mis-shaped tensor (strict or not) or, when strict, a missing or unexpected one.
  """
  expected = {
    official_name(path): (path, shape.shape) for path, shape in _flat_paths(param_shapes(config))
  }
  present = {k for k in state_dict if not k.startswith(_IGNORED_PREFIXES)}
  missing = sorted(set(expected) - present)
  unexpected = sorted(present - set(expected))
  mismatched = []
  for name in sorted(present & set(expected)):
    path, shape = expected[name]
    want = tuple(_torch_shape(path, shape, config.patch_size))
    if not _fits(name, tuple(state_dict[name].shape), want, strict):
      mismatched.append(f"{name}: checkpoint {tuple(state_dict[name].shape)} != model {want}")
  listing = [
    f"  {title} ({len(items)}): " + ", ".join(items)
    for title, items in (
      ("missing", missing),
      ("unexpected", unexpected),
      ("shape mismatch", mismatched),
    )
    if items
  ]
  if mismatched or (strict and listing):
    raise ValueError("\n".join(["official checkpoint does not match the config:", *listing]))
  if listing:
    _LOG.warning("\n".join(["official checkpoint loaded non-strictly, left out:", *listing]))
  # Own C-contiguous float32 copies: no views into (possibly memory-mapped) checkpoint data.
  items = {
    path: np.array(_from_torch_layout(path, np.asarray(state_dict[name])), np.float32, order="C")
    for name, (path, _) in expected.items()
    if name in present
  }
  return _unflatten(items)


def to_official_state_dict(params: Params, config: ModelConfig) -> dict[str, np.ndarray]:
  """params -> official state_dict (numpy float32, torch layouts), e.g. to export.

  Raises ValueError for `dynamic_motion="linear"`: the official network has no velocities and
  conditions its dynamic tokens on the target time, so no official model computes these weights'
  Gaussians."""
  if config.dynamic_motion != "decoded":
    raise ValueError(
      f'dynamic_motion="{config.dynamic_motion}" has no official counterpart (velocities, no '
      "target-time embedding): its weights cannot be exported as an official state_dict"
    )
  return {
    official_name(path): np.ascontiguousarray(
      _to_torch_layout(path, np.asarray(value, np.float32), config.patch_size)
    )
    for path, value in _flat_paths(params)
  }


# safetensors dtype names -> little-endian numpy dtypes. numpy has no bfloat16, which is why the
# safetensors numpy API cannot read BF16 checkpoints; ml_dtypes (a jax dependency) supplies it.
_SAFETENSORS_DTYPES = {
  "F64": np.dtype("<f8"),
  "F32": np.dtype("<f4"),
  "F16": np.dtype("<f2"),
  "BF16": np.dtype(ml_dtypes.bfloat16),
  "I64": np.dtype("<i8"),
  "I32": np.dtype("<i4"),
  "I16": np.dtype("<i2"),
  "I8": np.dtype("i1"),
  "U8": np.dtype("u1"),
  "BOOL": np.dtype("?"),
}


def read_safetensors(path: str | os.PathLike) -> dict[str, np.ndarray]:
  """All tensors of a `.safetensors` file as numpy arrays in their stored dtype (BF16 included).

  The format: an 8-byte little-endian header length n, n bytes of JSON mapping each tensor name
  to {"dtype", "shape", "data_offsets": [begin, end]} (byte offsets into the data that follows
  the header), and an optional "__metadata__" entry. The file is memory-mapped; arrays are
  read-only views into it.

  Raises:
    ValueError: on a malformed header, an unknown dtype or a byte range that does not match the
      tensor's shape and dtype.
  """
  data = np.memmap(path, dtype=np.uint8, mode="r")
  if data.size < 8:
    raise ValueError(f"{path}: too short for a safetensors header")
  header_len = int(data[:8].view("<u8")[0])
  if header_len > data.size - 8:
    raise ValueError(f"{path}: header length {header_len} exceeds the file size {data.size}")
  header = json.loads(bytes(data[8 : 8 + header_len]))
  body = data[8 + header_len :]
  tensors = {}
  for name, info in header.items():
    if name == "__metadata__":
      continue
    if info["dtype"] not in _SAFETENSORS_DTYPES:
      raise ValueError(f"{path}: tensor {name} has unsupported dtype {info['dtype']}")
    dtype = _SAFETENSORS_DTYPES[info["dtype"]]
    shape = tuple(int(n) for n in info["shape"])
    begin, end = (int(n) for n in info["data_offsets"])
    if end - begin != math.prod(shape) * dtype.itemsize or not 0 <= begin <= end <= body.size:
      raise ValueError(
        f"{path}: tensor {name} ({info['dtype']} {list(shape)}) has byte range "
        f"[{begin}, {end}) in a data section of {body.size} bytes"
      )
    tensors[name] = body[begin:end].view(dtype).reshape(shape)
  return tensors


def load_official_checkpoint(
  path: str | os.PathLike, config: ModelConfig, *, strict: bool = True
) -> Params:
  """Read an official TokenGS checkpoint into our params pytree.

  A `.safetensors` file, or (any other name, as the official loaders) a `torch.save`d state dict
  (`.pth`, `.pt`), read without torch and without executing anything in it
  (`official_pth.read_torch_state_dict`). Tensors stored as F32, F16 or BF16 are all converted
  (exactly) to float32.

  Args:
    path: the checkpoint (official parameter names, torch layouts).
    config: the architecture to load into (see `config_from_official`).
    strict: see `params_from_state_dict`; False seeds a model with more or fewer tokens or
      latents, or with dynamic tokens, from the checkpoint (then `train.transplant_params`).

  Returns:
    The params pytree (float32 numpy arrays; jax.device_put them as needed).

  Raises:
    ValueError: if a tensor is mis-shaped or (strict) missing or unexpected (all are named), or
      if the file is not valid safetensors or a readable torch state dict.
  """
  path = os.fspath(path)
  if path.endswith("safetensors"):
    return params_from_state_dict(read_safetensors(path), config, strict=strict)
  # imported here: the torch reader builds on the data package's chunk reader, and importing the
  # model should not load the data pipeline (grain and all) for it
  from tokengs_jax.model.official_pth import read_torch_state_dict

  return params_from_state_dict(read_torch_state_dict(path), config, strict=strict)
