"""Official PyTorch checkpoints (.safetensors) <-> our params pytree, without torch.

Our module tree mirrors the official one (see `network.py`), so names map by rule:
  path segments joined with "."; a list entry "encoder_3" is torch "encoder.3";
  Dense "kernel" = torch Linear "weight" transposed ([in, out] vs [out, in]);
  patch-embed "kernel" [(p, p, Cin), out] = torch Conv2d "weight" [out, Cin, p, p] permuted;
  LayerNorm "scale" = torch "weight"; "bias", LayerScale "gamma", "gs_tokens",
  "gs_tokens_dynamic" and "latents" are stored as they are.
"""

from __future__ import annotations

import os
import re

import jax
import numpy as np

from tokengs_jax.model.api import Params, param_shapes
from tokengs_jax.model.configs import ModelConfig

# Keys the official `state_dict()` strips anyway (frozen LPIPS network inside the module).
_IGNORED_PREFIXES = ("lpips_loss.",)
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
    cin = value.shape[0] // (patch_size * patch_size)
    return value.reshape(patch_size, patch_size, cin, -1).transpose(3, 2, 0, 1)
  if path[-1] == "kernel":
    return value.T
  return value


def _from_torch_layout(path: tuple[str, ...], value: np.ndarray) -> np.ndarray:
  if _is_patch_embed(path):
    out, cin, p, _ = value.shape
    return value.transpose(2, 3, 1, 0).reshape(p * p * cin, out)
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


def params_from_state_dict(state_dict: dict[str, np.ndarray], config: ModelConfig) -> Params:
  """Official state_dict (numpy, torch layouts) -> params, with strict key and shape checks.

  Raises:
    ValueError: naming every missing tensor, unexpected tensor and shape mismatch.
  """
  expected = {official_name(path): (path, shape.shape)
              for path, shape in _flat_paths(param_shapes(config))}
  present = {k for k in state_dict if not k.startswith(_IGNORED_PREFIXES)}
  missing = sorted(set(expected) - present)
  unexpected = sorted(present - set(expected))
  mismatched = []
  for name in sorted(present & set(expected)):
    path, shape = expected[name]
    want = _torch_shape(path, shape, config.patch_size)
    if tuple(state_dict[name].shape) != tuple(want):
      mismatched.append(f"{name}: checkpoint {tuple(state_dict[name].shape)} != model {want}")
  if missing or unexpected or mismatched:
    lines = ["official checkpoint does not match the config:"]
    for title, items in (("missing", missing), ("unexpected", unexpected),
                         ("shape mismatch", mismatched)):
      if items:
        lines.append(f"  {title} ({len(items)}): " + ", ".join(items))
    raise ValueError("\n".join(lines))
  items = {path: np.asarray(_from_torch_layout(path, np.asarray(state_dict[name])), np.float32)
           for name, (path, _) in expected.items()}
  return _unflatten(items)


def to_official_state_dict(params: Params, config: ModelConfig) -> dict[str, np.ndarray]:
  """params -> official state_dict (numpy float32, torch layouts), e.g. to export."""
  return {official_name(path): np.ascontiguousarray(
      _to_torch_layout(path, np.asarray(value, np.float32), config.patch_size))
          for path, value in _flat_paths(params)}


def load_official_checkpoint(path: str | os.PathLike, config: ModelConfig) -> Params:
  """Read an official TokenGS `.safetensors` checkpoint into our params pytree.

  Args:
    path: the .safetensors file (official parameter names, torch layouts).
    config: the architecture it was trained with (see `config_from_official`).

  Returns:
    The params pytree (float32 numpy arrays; jax.device_put them as needed).

  Raises:
    ValueError: if any tensor is missing, unexpected or of the wrong shape (all are named).
  """
  from safetensors.numpy import load_file

  return params_from_state_dict(load_file(os.fspath(path)), config)
