"""Encoder ViT block (official `Block` in `tokengs/models/attention.py`, as `EncDecBackbone`
builds it: qkv/proj/ffn biases, QK-norm, LayerScale 0.01, no drop-path, no RoPE)."""

from __future__ import annotations

import flax.linen as nn
import jax

from tokengs_jax.model.configs import ENCODER_LAYER_SCALE_INIT, ModelConfig
from tokengs_jax.model.layers import LayerScale, Mlp, SelfAttention, layer_norm


class EncoderBlock(nn.Module):
  """Pre-norm ViT block: x + ls1(attn(norm1(x))), then x + ls2(mlp(norm2(x)))."""

  config: ModelConfig

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    cfg, dtype, matmul_dtype = (
      self.config,
      self.config.compute_dtype,
      self.config.matmul_operand_dtype,
    )
    c = cfg.enc_embed_dim
    attention = SelfAttention(cfg.enc_num_heads, dtype, matmul_dtype, name="attn")
    x = x + LayerScale(c, ENCODER_LAYER_SCALE_INIT, name="ls1")(
      attention(layer_norm(dtype, "norm1")(x))
    )
    mlp = Mlp(cfg.mlp_hidden_dim, dtype, matmul_dtype, name="mlp")(layer_norm(dtype, "norm2")(x))
    return x + LayerScale(c, ENCODER_LAYER_SCALE_INIT, name="ls2")(mlp)


def block_class(module_class, config: ModelConfig):
  """The block class, rematerialised in the backward pass when config.remat is set."""
  return nn.remat(module_class) if config.remat else module_class
