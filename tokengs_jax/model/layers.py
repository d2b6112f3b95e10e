"""Transformer building blocks shared by the encoder, the decoder and the latent bottleneck.

Module and parameter names mirror the official PyTorch modules (`tokengs/models/attention.py`,
`enc_dec.py`) so that `official.py` maps checkpoints by a mechanical rule: Flax `kernel` is the
transposed torch `weight`, LayerNorm `scale` is torch `weight`, a list entry `name_3` is torch
`name.3`.

Conventions: tokens are [B, N, C]; attention heads are split as [B, heads, N, head_dim] with the
channel order (heads, head_dim) of the official `rearrange(..., "b n (h d) -> b h n d")`.
"""

from __future__ import annotations

import functools

import einops
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from tokengs_jax.model import matmul
from tokengs_jax.model.configs import LAYER_NORM_EPS

# torch.nn.Linear / Conv2d default weight init: U(-1/sqrt(fan_in), 1/sqrt(fan_in)).
torch_default_kernel_init = nn.initializers.variance_scaling(1.0 / 3.0, "fan_in", "uniform")


@functools.partial(jax.custom_vjp, nondiff_argnums=(3,))
def _normalize(x: jax.Array, scale: jax.Array, bias: jax.Array, eps: float) -> jax.Array:
  """(x - mean) / sqrt(var + eps) * scale + bias over the last axis (x, scale, bias float32).

  A hand-written VJP: autodiff of the two-pass formula leaves XLA:CPU about twice as many
  separate reductions and broadcasts per LayerNorm (17 ops forward+backward in the tiny train
  step), and the model has one to three LayerNorms per matmul.
  """
  return _normalize_fwd(x, scale, bias, eps)[0]


def _normalize_fwd(x, scale, bias, eps):
  centred = x - jnp.mean(x, axis=-1, keepdims=True)
  inv_std = jax.lax.rsqrt(jnp.mean(jnp.square(centred), axis=-1, keepdims=True) + eps)
  normalized = centred * inv_std
  return normalized * scale + bias, (normalized, inv_std, scale)


def _normalize_bwd(eps, residuals, out_grad):
  del eps
  normalized, inv_std, scale = residuals
  leading = tuple(range(out_grad.ndim - 1))
  scale_grad = jnp.sum(out_grad * normalized, axis=leading)
  bias_grad = jnp.sum(out_grad, axis=leading)
  normalized_grad = out_grad * scale
  x_grad = inv_std * (
    normalized_grad
    - jnp.mean(normalized_grad, axis=-1, keepdims=True)
    - normalized * jnp.mean(normalized_grad * normalized, axis=-1, keepdims=True)
  )
  return x_grad, scale_grad, bias_grad


_normalize.defvjp(_normalize_fwd, _normalize_bwd)


class LayerNorm(nn.Module):
  """torch.nn.LayerNorm over the last axis: eps 1e-5 (Flax defaults to 1e-6), the two-pass
  variance, statistics in float32, parameters `scale` / `bias` as Flax's `nn.LayerNorm`."""

  dtype: jnp.dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    features = x.shape[-1]
    scale = self.param("scale", nn.initializers.ones, (features,), jnp.float32)
    bias = self.param("bias", nn.initializers.zeros, (features,), jnp.float32)
    # The casts sit outside the custom VJP, so autodiff returns each cotangent in its input dtype.
    return _normalize(x.astype(jnp.float32), scale, bias, LAYER_NORM_EPS).astype(self.dtype)


def layer_norm(dtype, name: str | None = None) -> LayerNorm:
  """The model's LayerNorm computing in float32 and returning `dtype`."""
  return LayerNorm(dtype=dtype, name=name)


def dense(
  features: int,
  dtype,
  name: str | None = None,
  use_bias: bool = True,
  kernel_init=torch_default_kernel_init,
  matmul_dtype=None,
) -> nn.Dense:
  """Linear layer with float32 parameters computing in `dtype`; with `matmul_dtype` set, its
  matmul rounds the operands to it and accumulates in float32 (`model.matmul`)."""
  return nn.Dense(
    features,
    use_bias=use_bias,
    dtype=dtype,
    param_dtype=jnp.float32,
    kernel_init=kernel_init,
    dot_general=None if matmul_dtype is None else matmul.dense_dot_general(matmul_dtype),
    name=name,
  )


def split_heads(x: jax.Array, num_heads: int) -> jax.Array:
  """[B, N, heads * d] -> [B, heads, N, d]."""
  return einops.rearrange(x, "b n (h d) -> b h n d", h=num_heads)


def merge_heads(x: jax.Array) -> jax.Array:
  """[B, heads, N, d] -> [B, N, heads * d]."""
  return einops.rearrange(x, "b h n d -> b n (h d)")


# Attention runs in tiles of at most this many logits (4 MB in float32). On XLA:CPU, materialising
# the whole [B, H, Nq, Nk] logits costs more than the matmuls: glibc serves buffers above 32 MB
# with fresh mmap pages, so every call page-faults them in (about 30 ms per 50 MB here), and the
# reverse-mode softmax allocates several of them. Tiles this size stay in cache and in the heap
# (docs/benchmarks.md has the measurements).
ATTENTION_TILE = 1 << 20


def _largest_divisor_at_most(n: int, cap: int) -> int:
  cap = max(1, min(n, cap))
  return max(g for g in range(1, cap + 1) if n % g == 0)


def attention_tiling(
  batch_heads: int, num_queries: int, num_keys: int, tile: int = ATTENTION_TILE
) -> tuple[int, int, int]:
  """How `attend` splits the work: (heads per step, query rows per step, row steps).

  Whole heads are grouped while one head's logits fit in a tile; otherwise one head at a time,
  its query rows split into balanced chunks (the last padded) of about tile / num_keys rows.
  """
  if num_queries * num_keys <= tile:
    return _largest_divisor_at_most(batch_heads, tile // (num_queries * num_keys)), num_queries, 1
  row_steps = -(-num_queries // max(1, tile // num_keys))
  return 1, -(-num_queries // row_steps), row_steps


def _to_row_chunks(x: jax.Array, row_steps: int, rows: int, fill=0) -> jax.Array:
  """[..., N, X] -> [row_steps, ..., rows, X], padding N up to row_steps * rows with `fill`."""
  pad = row_steps * rows - x.shape[-2]
  if pad:
    x = jnp.pad(x, [(0, 0)] * (x.ndim - 2) + [(0, pad), (0, 0)], constant_values=fill)
  return jnp.moveaxis(x.reshape(*x.shape[:-2], row_steps, rows, x.shape[-1]), -3, 0)


def _from_row_chunks(x: jax.Array, num_rows: int) -> jax.Array:
  """Inverse of `_to_row_chunks` (drops the padding rows)."""
  x = jnp.moveaxis(x, 0, -3)
  return x.reshape(*x.shape[:-3], -1, x.shape[-1])[..., :num_rows, :]


def _masked_logits(queries, keys, mask, operand_dtype):
  """[G, q, d], [G, k, d], bool [q, k] or None -> float32 [G, q, k]."""
  logits = matmul.einsum("gqd,gkd->gqk", queries, keys, operand_dtype)
  return logits if mask is None else jnp.where(mask, logits, -jnp.inf)


def _head_groups(x: jax.Array, heads_per_step: int) -> jax.Array:
  """[B, H, N, X] -> [B * H / heads_per_step, heads_per_step, N, X] (a free reshape)."""
  return x.reshape(-1, heads_per_step, *x.shape[-2:])


def _tile_transposed_product(tile_t, right, operand_dtype):
  """tile_t [G, k, q], right [G, k, d] -> tile_t^T right [G, q, d].

  With several heads in the group (G > 1), XLA:CPU runs this batched product, which contracts
  both operands' row axis, in its generic dot at a third to a half of the library dot's speed,
  and XLA folds a plain transpose of the tile back into it; the barrier keeps a transposed copy
  (tiny train step 48.6-49.1 -> 47.3-47.8 ms). A single-head group (G = 1) is a 2-D product the
  library takes transposed as it is: there the copy costs (mid train step 5.1 -> 6.0 s with it).
  """
  if tile_t.shape[0] == 1:
    return matmul.einsum("gkq,gkd->gqd", tile_t, right, operand_dtype)
  tile = jax.lax.optimization_barrier(jnp.swapaxes(tile_t, -1, -2))
  return matmul.einsum("gqk,gkd->gqd", tile, right, operand_dtype)


@functools.partial(jax.custom_vjp, nondiff_argnums=(4, 5))
def _tiled_attention(queries, keys, values, mask, tile, operand_dtype):
  """softmax(queries keys^T) values (no 1/sqrt(d): `attend` scales the queries)."""
  return _tiled_attention_fwd(queries, keys, values, mask, tile, operand_dtype)[0]


def _tiled_attention_fwd(queries, keys, values, mask, tile, operand_dtype):
  b, h, num_queries, _ = queries.shape
  heads_per_step, rows, row_steps = attention_tiling(b * h, num_queries, keys.shape[2], tile)
  # Padded query rows attend everywhere so that their (discarded) softmax stays finite.
  mask_chunks = None if mask is None else _to_row_chunks(mask, row_steps, rows, True)

  def head_group(_, group):
    group_queries, group_keys, group_values = group

    def row_chunk(_, chunk):
      chunk_queries, chunk_mask = chunk
      logits = _masked_logits(chunk_queries, group_keys, chunk_mask, operand_dtype)
      row_max = jnp.max(logits, axis=-1, keepdims=True)
      exp = jnp.exp(logits - row_max)
      row_sum = jnp.sum(exp, axis=-1, keepdims=True)
      out = matmul.einsum("gqk,gkd->gqd", exp / row_sum, group_values, operand_dtype)
      return None, (out.astype(group_values.dtype), row_max + jnp.log(row_sum))

    _, (out, log_sum_exp) = jax.lax.scan(
      row_chunk, None, (_to_row_chunks(group_queries, row_steps, rows), mask_chunks)
    )
    return None, (_from_row_chunks(out, num_queries), _from_row_chunks(log_sum_exp, num_queries))

  _, (out, log_sum_exp) = jax.lax.scan(
    head_group, None, tuple(_head_groups(x, heads_per_step) for x in (queries, keys, values))
  )
  out = out.reshape(queries.shape)
  return out, (queries, keys, values, mask, out, log_sum_exp)


def _tiled_attention_bwd(tile, operand_dtype, residuals, out_grad):
  """Flash-attention backward: recompute each tile's probabilities from the saved row
  log-sum-exp instead of storing them; dK, dV accumulate over a head group's row chunks.

  The tile is recomputed transposed, [keys, queries]: then dV = P^T dO and dK = dS^T Q are plain
  products, and only dQ = dS K contracts the tile's leading axis (`_tile_transposed_product`).
  XLA:CPU runs a batched product that contracts both operands' row axis in its generic dot at a
  fifth to a half of the speed of the library dots (docs/benchmarks.md); the untransposed tile
  would need two of them.
  """
  queries, keys, values, mask, out, log_sum_exp = residuals
  b, h, num_queries, _ = queries.shape
  heads_per_step, rows, row_steps = attention_tiling(b * h, num_queries, keys.shape[2], tile)
  # d softmax: dlogits = p * (dp - sum_k p dp) and sum_k p dp = sum_d out * dout.
  out_dot_grad = jnp.sum(
    out.astype(jnp.float32) * out_grad.astype(jnp.float32), axis=-1, keepdims=True
  )
  mask_chunks = None if mask is None else _to_row_chunks(mask, row_steps, rows, True)

  def head_group(_, group):
    group_queries, group_keys, group_values, group_out_grad, group_out_dot, group_lse = group

    def row_chunk(carry, chunk):
      keys_grad, values_grad = carry
      chunk_queries, chunk_out_grad, chunk_out_dot, chunk_lse, chunk_mask = chunk
      logits_t = matmul.einsum("gkd,gqd->gkq", group_keys, chunk_queries, operand_dtype)
      if chunk_mask is not None:
        logits_t = jnp.where(chunk_mask.T, logits_t, -jnp.inf)
      probs_t = jnp.exp(logits_t - jnp.swapaxes(chunk_lse, -1, -2))
      values_grad += matmul.einsum("gkq,gqd->gkd", probs_t, chunk_out_grad, operand_dtype)
      probs_grad_t = matmul.einsum("gkd,gqd->gkq", group_values, chunk_out_grad, operand_dtype)
      logits_grad_t = probs_t * (probs_grad_t - jnp.swapaxes(chunk_out_dot, -1, -2))
      queries_grad = _tile_transposed_product(logits_grad_t, group_keys, operand_dtype)
      keys_grad += matmul.einsum("gkq,gqd->gkd", logits_grad_t, chunk_queries, operand_dtype)
      return (keys_grad, values_grad), queries_grad.astype(chunk_queries.dtype)

    zeros = jnp.zeros(group_keys.shape, jnp.float32)
    chunks = tuple(
      _to_row_chunks(x, row_steps, rows)
      for x in (group_queries, group_out_grad, group_out_dot, group_lse)
    )
    (keys_grad, values_grad), queries_grad = jax.lax.scan(
      row_chunk, (zeros, zeros), (*chunks, mask_chunks)
    )
    return None, (
      _from_row_chunks(queries_grad, num_queries),
      keys_grad.astype(group_keys.dtype),
      values_grad.astype(group_values.dtype),
    )

  _, (queries_grad, keys_grad, values_grad) = jax.lax.scan(
    head_group,
    None,
    tuple(
      _head_groups(x, heads_per_step)
      for x in (queries, keys, values, out_grad, out_dot_grad, log_sum_exp)
    ),
  )
  return (
    queries_grad.reshape(queries.shape),
    keys_grad.reshape(keys.shape),
    values_grad.reshape(values.shape),
    None,
  )


_tiled_attention.defvjp(_tiled_attention_fwd, _tiled_attention_bwd)


def attend(
  queries: jax.Array,
  keys: jax.Array,
  values: jax.Array,
  mask: jax.Array | None = None,
  tile: int = ATTENTION_TILE,
  matmul_dtype=None,
) -> jax.Array:
  """Scaled dot-product attention (torch SDPA semantics: scale 1/sqrt(d)), tiled.

  Logits and softmax are computed in float32 whatever the input dtype, one tile of at most
  `tile` logits at a time (`attention_tiling`); each query row's softmax is still
  computed over all keys at once, so values equal the plain formula up to float rounding. The
  backward recomputes the probabilities tile by tile (flash-attention style) rather than
  storing them, so no [B, H, Nq, Nk] array exists in either pass.

  Args:
    queries: [B, H, Nq, d].
    keys: [B, H, Nk, d].
    values: [B, H, Nk, d].
    mask: optional bool [Nq, Nk], True where attention is allowed.
    tile: logits per step (tests use small tiles to exercise the chunking).
    matmul_dtype: dtype the operands of every product (forward and backward) are rounded to,
      products accumulated in float32; None: the queries' dtype.

  Returns:
    [B, H, Nq, d] in the values' dtype.
  """
  operand_dtype = queries.dtype if matmul_dtype is None else jnp.dtype(matmul_dtype)
  # Scaling the [.., Nq, d] queries rather than the [.., Nq, Nk] logits saves a pass over every
  # logits tile in the forward and in the backward.
  scaled_queries = queries * queries.shape[-1] ** -0.5
  keys = keys.astype(queries.dtype)
  return _tiled_attention(scaled_queries, keys, values, mask, tile, operand_dtype)


class LayerScale(nn.Module):
  """Per-channel residual scale gamma (LayerScale, Touvron et al.)."""

  dim: int
  init_value: float

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    gamma = self.param("gamma", nn.initializers.constant(self.init_value), (self.dim,), jnp.float32)
    return x * gamma.astype(x.dtype)


def maybe_layer_scale(dim: int, init_value: float | None, name: str):
  """LayerScale, or the identity when init_value is falsy (as official `make_scale`)."""
  if not init_value:
    return lambda x: x
  return LayerScale(dim, init_value, name=name)


def gelu(x: jax.Array) -> jax.Array:
  """Exact GELU x Phi(x) written with erf, as torch's nn.GELU(): within 2e-6 of
  `jax.nn.gelu(approximate=False)`, whose erfc form costs an exponential more (2.8x slower
  forward, 1.3x slower forward+backward on XLA:CPU)."""
  return 0.5 * x * (1.0 + jax.lax.erf(x * np.sqrt(0.5).astype(x.dtype)))


class Mlp(nn.Module):
  """fc1 -> exact (erf) GELU -> fc2, as torch nn.GELU()."""

  hidden_dim: int
  dtype: jnp.dtype = jnp.float32
  matmul_dtype: jnp.dtype | None = None  # see `dense`

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    hidden = dense(self.hidden_dim, self.dtype, "fc1", matmul_dtype=self.matmul_dtype)(x)
    hidden = gelu(hidden)
    return dense(x.shape[-1], self.dtype, "fc2", matmul_dtype=self.matmul_dtype)(hidden)


class SelfAttention(nn.Module):
  """Multi-head self-attention with a fused qkv projection and per-head QK LayerNorm.

  Parameters as the official `Attention` (qkv, q_norm, k_norm, proj).
  """

  num_heads: int
  dtype: jnp.dtype = jnp.float32
  matmul_dtype: jnp.dtype | None = None  # see `dense` and `attend`

  @nn.compact
  def __call__(
    self,
    x: jax.Array,
    mask: jax.Array | None = None,
    context: tuple[jax.Array, jax.Array] | None = None,
    return_kv: bool = False,
  ) -> jax.Array | tuple[jax.Array, tuple[jax.Array, jax.Array]]:
    """x's tokens attend to each other and, with `context`, to M other tokens before them.

    Args:
      x: [B, N, C].
      mask: optional bool [N, M + N] (M = 0 without `context`), True where attention is allowed.
      context: optional (keys, values) [B, heads, M, d] of the other tokens, as `return_kv`
        returned them from this module: attending to them needs no pass over those tokens.
      return_kv: also return x's own (keys, values) [B, heads, N, d].

    Returns:
      [B, N, C], and x's (keys, values) with `return_kv`.
    """
    c = x.shape[-1]
    qkv = dense(3 * c, self.dtype, "qkv", matmul_dtype=self.matmul_dtype)(x)
    # Official channel order of qkv: (3, heads, head_dim).
    qkv = einops.rearrange(qkv, "b n (three h d) -> three b h n d", three=3, h=self.num_heads)
    queries = layer_norm(self.dtype, "q_norm")(qkv[0])
    keys = layer_norm(self.dtype, "k_norm")(qkv[1])
    all_keys, all_values = keys, qkv[2]
    if context is not None:
      all_keys = jnp.concatenate([context[0], keys], axis=2)
      all_values = jnp.concatenate([context[1], qkv[2]], axis=2)
    out = attend(queries, all_keys, all_values, mask, matmul_dtype=self.matmul_dtype)
    out = dense(c, self.dtype, "proj", matmul_dtype=self.matmul_dtype)(merge_heads(out))
    return (out, (keys, qkv[2])) if return_kv else out


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
  matmul_dtype: jnp.dtype | None = None  # see `dense`

  @nn.compact
  def __call__(self, images: jax.Array) -> jax.Array:
    """images: [..., H, W, Cin] -> [..., (H/p)*(W/p), C] (row-major patch order)."""
    h, w = images.shape[-3:-1]
    p = self.patch_size
    if h % p or w % p:
      raise ValueError(f"image size {h}x{w} is not divisible by the patch size {p}")
    patches = einops.rearrange(images, "... (hp p) (wp q) c -> ... (hp wp) (p q c)", p=p, q=p)
    init = nn.initializers.zeros if self.zero_init else torch_default_kernel_init
    tokens = dense(
      self.embed_dim, self.dtype, "proj", kernel_init=init, matmul_dtype=self.matmul_dtype
    )(patches)
    if self.use_norm:
      tokens = layer_norm(self.dtype, "norm")(tokens)
    return tokens
