"""Transformer building blocks shared by the encoder, the decoder and the latent bottleneck.

Module and parameter names mirror the official PyTorch modules (`tokengs/models/attention.py`,
`enc_dec.py`) so that `official.py` maps checkpoints by a mechanical rule: Flax `kernel` is the
transposed torch `weight`, LayerNorm `scale` is torch `weight`, a list entry `name_3` is torch
`name.3`.

Conventions: tokens are [B, N, C]; attention heads are split as [B, heads, N, head_dim] with the
channel order (heads, head_dim) of the official `rearrange(..., "b n (h d) -> b h n d")`.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from tokengs_jax.model.configs import LAYER_NORM_EPS

# torch.nn.Linear / Conv2d default weight init: U(-1/sqrt(fan_in), 1/sqrt(fan_in)).
torch_default_kernel_init = nn.initializers.variance_scaling(1.0 / 3.0, "fan_in", "uniform")


def layer_norm(dtype, name: str | None = None) -> nn.LayerNorm:
  """LayerNorm with torch's eps (1e-5, Flax defaults to 1e-6) and the two-pass variance."""
  return nn.LayerNorm(epsilon=LAYER_NORM_EPS, use_fast_variance=False, dtype=dtype,
                      param_dtype=jnp.float32, name=name)


def dense(features: int, dtype, name: str | None = None, use_bias: bool = True,
          kernel_init=torch_default_kernel_init) -> nn.Dense:
  """Linear layer with float32 parameters computing in `dtype`."""
  return nn.Dense(features, use_bias=use_bias, dtype=dtype, param_dtype=jnp.float32,
                  kernel_init=kernel_init, name=name)


def split_heads(x: jax.Array, num_heads: int) -> jax.Array:
  """[B, N, heads * d] -> [B, heads, N, d]."""
  b, n, c = x.shape
  return x.reshape(b, n, num_heads, c // num_heads).transpose(0, 2, 1, 3)


def merge_heads(x: jax.Array) -> jax.Array:
  """[B, heads, N, d] -> [B, N, heads * d]."""
  b, h, n, d = x.shape
  return x.transpose(0, 2, 1, 3).reshape(b, n, h * d)


def attend(queries: jax.Array, keys: jax.Array, values: jax.Array,
           mask: jax.Array | None = None) -> jax.Array:
  """Scaled dot-product attention (torch SDPA semantics: scale 1/sqrt(d)).

  Logits and softmax are computed in float32 whatever the input dtype.

  Args:
    queries: [B, H, Nq, d].
    keys: [B, H, Nk, d].
    values: [B, H, Nk, d].
    mask: optional bool [Nq, Nk], True where attention is allowed.

  Returns:
    [B, H, Nq, d] in the values' dtype.
  """
  scale = queries.shape[-1] ** -0.5
  logits = jnp.einsum("bhqd,bhkd->bhqk", queries, keys.astype(queries.dtype),
                      preferred_element_type=jnp.float32) * scale
  if mask is not None:
    logits = jnp.where(mask, logits, -jnp.inf)
  weights = jax.nn.softmax(logits, axis=-1).astype(values.dtype)
  return jnp.einsum("bhqk,bhkd->bhqd", weights, values)


class LayerScale(nn.Module):
  """Per-channel residual scale gamma (LayerScale, Touvron et al.)."""
  dim: int
  init_value: float

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    gamma = self.param("gamma", nn.initializers.constant(self.init_value), (self.dim,),
                       jnp.float32)
    return x * gamma.astype(x.dtype)


def maybe_layer_scale(dim: int, init_value: float | None, name: str):
  """LayerScale, or the identity when init_value is falsy (as official `make_scale`)."""
  if not init_value:
    return lambda x: x
  return LayerScale(dim, init_value, name=name)


class Mlp(nn.Module):
  """fc1 -> exact (erf) GELU -> fc2, as torch nn.GELU()."""
  hidden_dim: int
  dtype: jnp.dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    hidden = dense(self.hidden_dim, self.dtype, name="fc1")(x)
    hidden = jax.nn.gelu(hidden, approximate=False)
    return dense(x.shape[-1], self.dtype, name="fc2")(hidden)


class SelfAttention(nn.Module):
  """Multi-head self-attention with a fused qkv projection and per-head QK LayerNorm.

  Parameters as the official `Attention` (qkv, q_norm, k_norm, proj).
  """
  num_heads: int
  dtype: jnp.dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array, mask: jax.Array | None = None) -> jax.Array:
    """x: [B, N, C]; mask: optional bool [N, N] -> [B, N, C]."""
    b, n, c = x.shape
    head_dim = c // self.num_heads
    qkv = dense(3 * c, self.dtype, name="qkv")(x)
    # Official channel order of qkv: (3, heads, head_dim).
    qkv = qkv.reshape(b, n, 3, self.num_heads, head_dim).transpose(2, 0, 3, 1, 4)
    queries = layer_norm(self.dtype, "q_norm")(qkv[0])
    keys = layer_norm(self.dtype, "k_norm")(qkv[1])
    out = attend(queries, keys, qkv[2], mask)
    return dense(c, self.dtype, name="proj")(merge_heads(out))


class PatchEmbed(nn.Module):
  """Non-overlapping p x p patches -> linear -> (optional LayerNorm).

  The official module is a stride-p Conv2d; a reshape plus one matmul is the same map and is
  faster on CPU. Patch vectors are flattened in (row, col, channel) order; `official.py` permutes
  the conv weight [out, in, p, p] into that order.
  """
  embed_dim: int
  patch_size: int
  use_norm: bool = True
  zero_init: bool = False  # the official time embeds start at exactly zero
  dtype: jnp.dtype = jnp.float32

  @nn.compact
  def __call__(self, images: jax.Array) -> jax.Array:
    """images: [..., H, W, Cin] -> [..., (H/p)*(W/p), C] (row-major patch order)."""
    *batch, h, w, cin = images.shape
    p = self.patch_size
    if h % p or w % p:
      raise ValueError(f"image size {h}x{w} is not divisible by the patch size {p}")
    patches = images.reshape(*batch, h // p, p, w // p, p, cin)
    patches = jnp.swapaxes(patches, -4, -3).reshape(*batch, (h // p) * (w // p), p * p * cin)
    init = nn.initializers.zeros if self.zero_init else torch_default_kernel_init
    tokens = nn.Dense(self.embed_dim, dtype=self.dtype, param_dtype=jnp.float32,
                      kernel_init=init, name="proj")(patches)
    if self.use_norm:
      tokens = layer_norm(self.dtype, "norm")(tokens)
    return tokens
