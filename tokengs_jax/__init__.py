"""tokengs_jax: TokenGS (learnable Gaussian tokens for feed-forward 3D Gaussian splatting) in JAX.

Public names are resolved lazily (PEP 562) so that `import tokengs_jax` stays cheap and a
downstream user who only renders never imports the model, the data pipeline or orbax.

    from tokengs_jax import Gaussians, render, reconstruct
"""

from __future__ import annotations

import importlib

# public name -> module that defines it
_PUBLIC = {
  "Gaussians": "tokengs_jax.gaussians",
  "render": "tokengs_jax.splatting",
  "render_exact": "tokengs_jax.splatting",
  "RenderConfig": "tokengs_jax.splatting",
  "RenderResult": "tokengs_jax.splatting",
  "plucker_rays": "tokengs_jax.camera",
  "ModelConfig": "tokengs_jax.model",
  "preset": "tokengs_jax.model",
  "reconstruct": "tokengs_jax.model",
  "encode_views": "tokengs_jax.model",
  "decode": "tokengs_jax.model",
  "decode_at_times": "tokengs_jax.model",
  "init_params": "tokengs_jax.model",
  "config_from_official": "tokengs_jax.model",
  "load_official_checkpoint": "tokengs_jax.model",
  "tune": "tokengs_jax.tuning",
  "TuningConfig": "tokengs_jax.tuning",
}
_SUBMODULES = (
  "camera",
  "math",
  "gaussians",
  "splatting",
  "model",
  "losses",
  "objective",
  "metrics",
  "data",
  "train",
  "tuning",
  "evaluation",
  "export",
  "process",
)

__all__ = sorted(_PUBLIC) + list(_SUBMODULES)


def __getattr__(name: str):
  if name in _PUBLIC:
    value = getattr(importlib.import_module(_PUBLIC[name]), name)
  elif name in _SUBMODULES:
    value = importlib.import_module(f"tokengs_jax.{name}")
  else:
    raise AttributeError(f"module 'tokengs_jax' has no attribute {name!r}")
  globals()[name] = value  # cache: later look-ups skip this function
  return value


def __dir__():
  return __all__
