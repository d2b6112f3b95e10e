"""Token decoder block (also the latent-bottleneck block) and the dynamic block-causal mask.

Official counterpart: `DecoderBlock` in `tokengs/models/enc_dec.py`. Each block runs, with a
residual and an optional LayerScale around each step:
cross-attention to the shared keys/values -> self-attention among the tokens -> MLP.
There is no final norm after the last block: the head reads the residual stream directly.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import numpy as np

from tokengs_jax.model.layers import (
  Mlp,
  SelfAttention,
  attend,
  dense,
  layer_norm,
  maybe_layer_scale,
  merge_heads,
  split_heads,
)


class CrossAttention(nn.Module):
  """Tokens (normed, projected, per-head q-normed) attend to precomputed keys/values.

  The keys/values are shared by every block (projected and key-normed once by the encoder), so a
  block only owns its query and output projections.
  """

  num_heads: int
  dtype: jax.typing.DTypeLike
  matmul_dtype: jax.typing.DTypeLike | None = None  # see `layers.dense` and `layers.attend`

  @nn.compact
  def __call__(self, tokens: jax.Array, keys: jax.Array, values: jax.Array) -> jax.Array:
    """tokens: [B, T, C]; keys, values: [B, heads, N, d] -> [B, T, C]."""
    c = tokens.shape[-1]
    q_proj = dense(c, self.dtype, "q_proj", matmul_dtype=self.matmul_dtype)
    queries = q_proj(layer_norm(self.dtype, "gs_token_norm")(tokens))
    queries = layer_norm(self.dtype, "q_norm")(split_heads(queries, self.num_heads))
    out = attend(queries, keys, values.astype(queries.dtype), matmul_dtype=self.matmul_dtype)
    return dense(c, self.dtype, "out_proj", matmul_dtype=self.matmul_dtype)(merge_heads(out))


class _NormedSelfAttention(nn.Module):
  """norm -> self-attention (official `DecoderBlock.SelfAttnBlock`)."""

  num_heads: int
  dtype: jax.typing.DTypeLike
  matmul_dtype: jax.typing.DTypeLike | None = None

  @nn.compact
  def __call__(
    self, tokens: jax.Array, mask: jax.Array | None, context: tuple[jax.Array, jax.Array] | None
  ) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
    """-> (output, the tokens' own (keys, values)); see `SelfAttention`."""
    normed = layer_norm(self.dtype, "norm")(tokens)
    attention = SelfAttention(self.num_heads, self.dtype, self.matmul_dtype, name="gs_self_attn")
    return attention(normed, mask, context, return_kv=True)


class _NormedMlp(nn.Module):
  """norm -> MLP (official `DecoderBlock.MlpBlock`)."""

  hidden_dim: int
  dtype: jax.typing.DTypeLike
  matmul_dtype: jax.typing.DTypeLike | None = None

  @nn.compact
  def __call__(self, tokens: jax.Array) -> jax.Array:
    mlp = Mlp(self.hidden_dim, self.dtype, self.matmul_dtype, name="mlp")
    return mlp(layer_norm(self.dtype, "norm")(tokens))


class DecoderBlock(nn.Module):
  """cross-attention -> self-attention -> MLP, each residual, each optionally LayerScaled.

  Attributes:
    num_heads: attention heads.
    mlp_hidden_dim: MLP hidden width.
    layer_scale: LayerScale init value; None removes the LayerScales (official Identity).
    dtype: compute dtype.
    matmul_dtype: operand dtype of the matmuls (`ModelConfig.matmul_operand_dtype`).
  """

  num_heads: int
  mlp_hidden_dim: int
  layer_scale: float | None
  dtype: jax.typing.DTypeLike
  matmul_dtype: jax.typing.DTypeLike | None = None

  @nn.compact
  def __call__(
    self,
    tokens: jax.Array,
    keys: jax.Array,
    values: jax.Array,
    mask: jax.Array | None = None,
    context: tuple[jax.Array, jax.Array] | None = None,
  ) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
    """One block.

    Args:
      tokens: [B, T, C].
      keys, values: [B, heads, N, d] shared cross-attention keys/values.
      mask: optional bool [T, M + T] self-attention mask (M = 0 without `context`).
      context: optional (keys, values) [B, heads, M, d] that this block returned for M other
        tokens: the tokens' self-attention also attends to those, placed before their own.

    Returns:
      [B, T, C], and the tokens' self-attention (keys, values) [B, heads, T, d].
    """
    c, dtype, matmul_dtype = tokens.shape[-1], self.dtype, self.matmul_dtype
    cross = CrossAttention(self.num_heads, dtype, matmul_dtype, name="gs_cross_attn")
    tokens = tokens + maybe_layer_scale(c, self.layer_scale, "gs_cross_attn_scale")(
      cross(tokens, keys, values)
    )
    attn = _NormedSelfAttention(self.num_heads, dtype, matmul_dtype, name="gs_self_attn")
    attended, self_kv = attn(tokens, mask, context)
    tokens = tokens + maybe_layer_scale(c, self.layer_scale, "gs_self_attn_scale")(attended)
    mlp = _NormedMlp(self.mlp_hidden_dim, dtype, matmul_dtype, name="mlp")(tokens)
    return tokens + maybe_layer_scale(c, self.layer_scale, "mlp_scale")(mlp), self_kv


def block_causal_mask(num_static: int, num_dynamic: int) -> np.ndarray | None:
  """Self-attention mask of the dynamic decoder (None when there are no dynamic tokens).

  Tokens are ordered [static, dynamic]. Attention is allowed within a block and from a later
  block to an earlier one: dynamic tokens see the static ones, static tokens never see dynamic
  ones, so the static Gaussians do not depend on the target time or the dynamic tokens, and
  neither do the static tokens' states at any block: the dynamic tokens can be decoded again at
  other times alone, attending to those states (`EncDecBackbone.decode_dynamic`).

  Returns:
    bool [T, T] (query, key), True where attention is allowed, T = num_static + num_dynamic.
  """
  if num_dynamic == 0:
    return None
  block_id = np.repeat([0, 1], [num_static, num_dynamic])
  index = np.arange(num_static + num_dynamic)
  same_block = block_id[:, None] == block_id[None, :]
  return same_block | (index[:, None] >= index[None, :])
