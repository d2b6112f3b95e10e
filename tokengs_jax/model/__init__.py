"""TokenGS network (Flax Linen), architecturally identical to the official PyTorch model.

from tokengs_jax.model import preset, init_params, reconstruct
"""

from tokengs_jax.model.api import (
  cast_matmul_kernels,
  count_params,
  decode,
  decode_at_times,
  decode_tokens,
  encode,
  encode_views,
  init_params,
  initial_tokens,
  kv_from_latents,
  normalize_images,
  param_shapes,
  predict_gaussians,
  reconstruct,
)
from tokengs_jax.model.configs import PRESETS, ModelConfig, config_from_official, preset
from tokengs_jax.model.network import EncoderOutput, TokenGS, timestep_embedding
from tokengs_jax.model.official import (
  load_official_checkpoint,
  params_from_state_dict,
  to_official_state_dict,
)

__all__ = [
  "PRESETS",
  "EncoderOutput",
  "ModelConfig",
  "TokenGS",
  "cast_matmul_kernels",
  "config_from_official",
  "count_params",
  "decode",
  "decode_at_times",
  "decode_tokens",
  "encode",
  "encode_views",
  "init_params",
  "initial_tokens",
  "kv_from_latents",
  "load_official_checkpoint",
  "normalize_images",
  "param_shapes",
  "params_from_state_dict",
  "predict_gaussians",
  "preset",
  "reconstruct",
  "timestep_embedding",
  "to_official_state_dict",
]
