"""The TokenGS network as one Flax Linen module with separate encode / decode methods.

Official counterparts: `TokenGS` (`tokengs/models/tokengs.py`) and `EncDecBackbone`
(`tokengs/models/enc_dec.py`). The module tree and parameter names follow them one to one
(`official.py` relies on it):

  patch_embed, patch_plucker_embed, [patch_time_embed, patch_time_embed_tgt],
  enc_dec_backbone/{encoder_i, encoder_norm | multiscale_norms_i, kv_proj, k_proj_norm,
                    [latents, latent_feature_kv_proj, latent_feature_k_norm, latent_blocks_i,
                     latent_kv_proj], decoder_blocks_i},
  activation_head/deconv, gs_tokens, [gs_tokens_dynamic]

plus, under `dynamic_motion="linear"` (not in the paper), `motion_head` (the dynamic Gaussians'
velocities) and no `patch_time_embed_tgt`. There are no positional embeddings: the Plücker rays
are the only position signal.
"""

from __future__ import annotations

import math

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp

from tokengs_jax.model.colours import InputViews, own_view_reading, with_input_colours
from tokengs_jax.model.configs import (
  LATENT_INIT_STD,
  LATENT_LAYER_SCALE_INIT,
  LINEAR_MOTION_REFERENCE_TIME,
  ModelConfig,
)
from tokengs_jax.model.decoder import DecoderBlock, block_causal_mask
from tokengs_jax.model.encoder import EncoderBlock, block_class
from tokengs_jax.model.head import GaussianHead, activate
from tokengs_jax.model.layers import PatchEmbed, dense, layer_norm, split_heads


@flax.struct.dataclass
class EncoderOutput:
  """What the decoder needs from the images; cache it to tune tokens without re-encoding.

  Attributes:
    keys: [B, heads, N, head_dim] shared (key-normed) keys of every decoder cross-attention.
    values: [B, heads, N, head_dim] shared values.
    latents: [B, num_latents, C] scene latents the keys/values came from (latent-bottleneck
      models only, else None); `kv_from_latents` recomputes keys/values after tuning them.
    views: the input views, for models that read Gaussian colours from them
      (`gaussian_colours="inputs"`; set by `api.encode_views`), else None.
  """

  keys: jax.Array
  values: jax.Array
  latents: jax.Array | None = None
  views: InputViews | None = None


def timestep_embedding(times: jax.Array, dim: int, max_period: float = 10000.0) -> jax.Array:
  """Sinusoidal embedding of normalised times: [cos(t f_i), sin(t f_i)], f_i = P^(-i/half).

  The official `tokengs.utils.data.timestep_embedding` is not in the public index we can read;
  this is the common (guided-diffusion) definition with that name. For the official dim = 2 it is
  [cos t, sin t].

  Args:
    times: [...] times in [0, 1].
    dim: embedding channels.

  Returns:
    [..., dim] float32.
  """
  half = dim // 2
  freqs = jnp.exp(-math.log(max_period) * jnp.arange(half, dtype=jnp.float32) / half)
  args = times.astype(jnp.float32)[..., None] * freqs
  emb = jnp.concatenate([jnp.cos(args), jnp.sin(args)], axis=-1)
  if dim % 2:
    emb = jnp.concatenate([emb, jnp.zeros_like(emb[..., :1])], axis=-1)
  return emb


def _split_kv(kv: jax.Array, num_heads: int) -> tuple[jax.Array, jax.Array]:
  """[B, N, 2C] (channel order (kv, heads, d)) -> keys, values [B, heads, N, d]."""
  keys, values = jnp.split(kv, 2, axis=-1)
  return split_heads(keys, num_heads), split_heads(values, num_heads)


class EncDecBackbone(nn.Module):
  """Encoder blocks, readout, shared K/V (optionally through latents) and decoder blocks."""

  config: ModelConfig

  def setup(self):
    cfg, dtype, matmul_dtype = (
      self.config,
      self.config.compute_dtype,
      self.config.matmul_operand_dtype,
    )
    c = cfg.enc_embed_dim
    self.encoder = [block_class(EncoderBlock, cfg)(cfg) for _ in range(cfg.enc_depth)]
    if cfg.use_multiscale_encoder:
      self.multiscale_norms = [layer_norm(dtype) for _ in cfg.multiscale_encoder_layers]
    else:
      self.encoder_norm = layer_norm(dtype)
    if not cfg.use_latent_bottleneck:
      self.kv_proj = dense(2 * c, dtype, matmul_dtype=matmul_dtype)
    self.k_proj_norm = layer_norm(dtype)
    decoder_block = block_class(DecoderBlock, cfg)
    if cfg.use_latent_bottleneck:
      self.latents = self.param(
        "latents", nn.initializers.normal(LATENT_INIT_STD), (cfg.num_latents, c), jnp.float32
      )
      self.latent_feature_kv_proj = dense(2 * c, dtype, matmul_dtype=matmul_dtype)
      self.latent_feature_k_norm = layer_norm(dtype)
      self.latent_blocks = [
        decoder_block(
          cfg.enc_num_heads, cfg.mlp_hidden_dim, LATENT_LAYER_SCALE_INIT, dtype, matmul_dtype
        )
        for _ in range(cfg.latent_cross_attn_depth)
      ]
      self.latent_kv_proj = dense(2 * c, dtype, matmul_dtype=matmul_dtype)
    self.decoder_blocks = [
      decoder_block(
        cfg.enc_num_heads, cfg.mlp_hidden_dim, cfg.decoder_layer_scale, dtype, matmul_dtype
      )
      for _ in range(cfg.dec_depth)
    ]

  def encode_features(self, tokens: jax.Array) -> jax.Array:
    """Encoder blocks + readout. tokens: [B, N, C] -> features [B, N, encoder_feature_dim]."""
    cfg = self.config
    readouts = []
    for i, block in enumerate(self.encoder):
      tokens = block(tokens)
      if cfg.use_multiscale_encoder and i in cfg.multiscale_encoder_layers:
        readouts.append(self.multiscale_norms[len(readouts)](tokens))
    if cfg.use_multiscale_encoder:
      return jnp.concatenate(readouts, axis=-1)
    return self.encoder_norm(tokens)

  def features_to_latents(self, features: jax.Array) -> jax.Array:
    """Learnt latents cross-attend to the features. [B, N, F] -> [B, num_latents, C]."""
    cfg = self.config
    keys, values = _split_kv(self.latent_feature_kv_proj(features), cfg.enc_num_heads)
    keys = self.latent_feature_k_norm(keys)
    latents = jnp.broadcast_to(
      self.latents.astype(cfg.compute_dtype), (features.shape[0], *self.latents.shape)
    )
    for block in self.latent_blocks:
      latents, _ = block(latents, keys, values)
    return latents

  def latents_to_kv(self, latents: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Scene latents -> decoder keys/values (keys normed by the shared k_proj_norm)."""
    keys, values = _split_kv(self.latent_kv_proj(latents), self.config.enc_num_heads)
    return self.k_proj_norm(keys), values

  def features_to_kv(self, features: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Features -> decoder keys/values [B, heads, N, d] (no bottleneck)."""
    keys, values = _split_kv(self.kv_proj(features), self.config.enc_num_heads)
    return self.k_proj_norm(keys), values

  def decode(
    self, tokens: jax.Array, keys: jax.Array, values: jax.Array
  ) -> tuple[jax.Array, list[tuple[jax.Array, jax.Array]]]:
    """Decoder blocks.

    Args:
      tokens: [B, T, C], static then dynamic (T = num_gs_tokens: the static ones alone).
      keys, values: [B, heads, N, d] shared keys/values.

    Returns:
      [B, T, C] (the head's input), and per block the static tokens' self-attention
      (keys, values) [B, heads, num_gs_tokens, d], for `decode_dynamic`.
    """
    num_static = self.config.num_gs_tokens
    mask = block_causal_mask(num_static, tokens.shape[1] - num_static)
    if mask is not None:
      mask = jnp.asarray(mask)
    static_kv = []
    for block in self.decoder_blocks:
      tokens, (block_keys, block_values) = block(tokens, keys, values, mask)
      static_kv.append((block_keys[:, :, :num_static], block_values[:, :, :num_static]))
    return tokens, static_kv

  def decode_dynamic(
    self,
    dynamic_tokens: jax.Array,
    static_kv: list[tuple[jax.Array, jax.Array]],
    keys: jax.Array,
    values: jax.Array,
  ) -> jax.Array:
    """`decode`'s dynamic rows, the static tokens' part taken from an earlier `decode`.

    Static tokens never attend to dynamic ones (`block_causal_mask`), so their states at every
    block, and the keys/values they offer the dynamic tokens, are the same whatever the dynamic
    tokens and the target time: decoding the dynamic tokens alone against them gives what
    decoding all tokens would, at a fraction of the cost.

    Args:
      dynamic_tokens: [B, Nd, C].
      static_kv: `decode`'s per-block static (keys, values).
      keys, values: [B, heads, N, d] shared keys/values.

    Returns:
      [B, Nd, C].
    """
    for block, context in zip(self.decoder_blocks, static_kv, strict=True):
      dynamic_tokens, _ = block(dynamic_tokens, keys, values, context=context)
    return dynamic_tokens


class TokenGS(nn.Module):
  """Patch embeds + backbone + Gaussian head + learnt Gaussian tokens."""

  config: ModelConfig

  def setup(self):
    cfg = self.config
    c, p = cfg.enc_embed_dim, cfg.patch_size
    dtypes = dict(dtype=cfg.compute_dtype, matmul_dtype=cfg.matmul_operand_dtype)
    self.patch_embed = PatchEmbed(c, p, **dtypes)
    self.patch_plucker_embed = PatchEmbed(c, p, **dtypes)
    if cfg.time_embedding:
      # No norm and zero init: a pretrained static model is unchanged until they learn.
      self.patch_time_embed = PatchEmbed(c, p, use_norm=False, zero_init=True, **dtypes)
      if cfg.dynamic_motion == "decoded":
        self.patch_time_embed_tgt = PatchEmbed(c, p, use_norm=False, zero_init=True, **dtypes)
    if cfg.dynamic_motion == "linear":
      # Zero init: the dynamic Gaussians start still, as the static Gaussians they are copied from.
      self.motion_head = nn.Dense(
        3 * cfg.gaussians_per_token,
        dtype=cfg.compute_dtype,
        param_dtype=jnp.float32,
        kernel_init=nn.initializers.zeros,
      )
    self.enc_dec_backbone = EncDecBackbone(cfg)
    self.activation_head = GaussianHead(cfg)
    token_init = nn.initializers.normal(cfg.gs_token_std)
    self.gs_tokens = self.param("gs_tokens", token_init, (cfg.num_gs_tokens, c), jnp.float32)
    if cfg.num_dynamic_gs_tokens:
      self.gs_tokens_dynamic = self.param(
        "gs_tokens_dynamic", token_init, (cfg.num_dynamic_gs_tokens, c), jnp.float32
      )

  def _time_patch(self, times: jax.Array) -> jax.Array:
    """One p x p patch filled with the time embedding: [...] -> [..., p, p, time_dim].

    The official model patch-embeds a full image whose every pixel holds the embedding; every
    patch of it is this same patch, so embedding one patch and broadcasting is the same map.
    """
    cfg = self.config
    emb = timestep_embedding(times, cfg.time_embedding_dim).astype(cfg.compute_dtype)
    return jnp.broadcast_to(
      emb[..., None, None, :], (*emb.shape[:-1], cfg.patch_size, cfg.patch_size, emb.shape[-1])
    )

  def embed(
    self, images: jax.Array, plucker: jax.Array, times: jax.Array | None = None
  ) -> jax.Array:
    """Image tokens of all views in one sequence.

    Args:
      images: [B, V, H, W, 3] normalised RGB.
      plucker: [B, V, H, W, 6].
      times: [B, V] normalised input-view times (time-embedding models only).

    Returns:
      [B, V * (H/p) * (W/p), C], view-major then row-major patches.
    """
    cfg = self.config
    dtype = cfg.compute_dtype
    tokens = self.patch_embed(images.astype(dtype)) + self.patch_plucker_embed(
      plucker.astype(dtype)
    )  # [B, V, n, C]
    if cfg.time_embedding:
      if times is None:
        raise ValueError("this model has time embeddings: pass the input-view times [B, V]")
      tokens = tokens + self.patch_time_embed(self._time_patch(times))  # [B, V, 1, C]
    b, v, n, c = tokens.shape
    return tokens.reshape(b, v * n, c)

  def encode(
    self, images: jax.Array, plucker: jax.Array, times: jax.Array | None = None
  ) -> EncoderOutput:
    """Images -> shared keys/values (through the scene latents if the model has them)."""
    backbone = self.enc_dec_backbone
    features = backbone.encode_features(self.embed(images, plucker, times))
    if self.config.use_latent_bottleneck:
      return self.kv_from_latents(backbone.features_to_latents(features))
    keys, values = backbone.features_to_kv(features)
    return EncoderOutput(keys, values)

  def kv_from_latents(self, latents: jax.Array) -> EncoderOutput:
    """Scene latents [B, L, C] -> EncoderOutput (for scene-latent tuning)."""
    keys, values = self.enc_dec_backbone.latents_to_kv(latents)
    return EncoderOutput(keys, values, latents)

  def initial_tokens(self, batch_size: int) -> jax.Array:
    """The learnt Gaussian tokens, [static, dynamic], broadcast: [B, T, C] float32."""
    tokens = self.gs_tokens
    if self.config.num_dynamic_gs_tokens:
      tokens = jnp.concatenate([tokens, self.gs_tokens_dynamic], axis=0)
    return jnp.broadcast_to(tokens, (batch_size, *tokens.shape))

  def decode_tokens(
    self,
    encoded: EncoderOutput,
    tokens: jax.Array | None = None,
    target_times: jax.Array | None = None,
  ) -> jax.Array:
    """Gaussian tokens after the last decoder block (the head's input).

    Args:
      encoded: the encoder output.
      tokens: [B, T, C] Gaussian tokens to decode (None: the learnt ones). Token tuning passes
        its own; they are time-conditioned here, so pass them un-conditioned.
      target_times: [B] normalised time to decode at (time-embedding models). None leaves the
        tokens unconditioned, as the official model does when no target time is given. Under
        `dynamic_motion="linear"` the tokens never see it (time moves the decoded Gaussians).

    Returns:
      [B, T, C].
    """
    return self._decode_tokens(encoded, tokens, target_times)[0]

  def _decode_tokens(
    self,
    encoded: EncoderOutput,
    tokens: jax.Array | None,
    target_times: jax.Array | None,
    static_scene: bool = False,
  ) -> tuple[jax.Array, list[tuple[jax.Array, jax.Array]]]:
    """`decode_tokens` (the static tokens alone for a `static_scene`), and the static tokens'
    per-block keys/values (`EncDecBackbone.decode`)."""
    cfg = self.config
    tokens = self._input_tokens(encoded, tokens)
    if static_scene:
      # Static tokens never attend to dynamic ones, so dropping these changes nothing else.
      tokens = tokens[:, : cfg.num_gs_tokens]
    elif cfg.time_embedding and target_times is not None and cfg.dynamic_motion == "decoded":
      time_token = self._target_time_token(target_times)
      if cfg.num_dynamic_gs_tokens:
        # Only the dynamic tokens see the target time; the static part stays time-invariant.
        tokens = tokens.at[:, cfg.num_gs_tokens :].add(time_token)
      else:
        tokens = tokens + time_token
    return self.enc_dec_backbone.decode(tokens, encoded.keys, encoded.values)

  def _input_tokens(self, encoded: EncoderOutput, tokens: jax.Array | None) -> jax.Array:
    """The tokens to decode, [B, T, C] in the compute dtype (None: the learnt ones)."""
    if tokens is None:
      tokens = self.initial_tokens(encoded.keys.shape[0])
    return tokens.astype(self.config.compute_dtype)

  def _target_time_token(self, target_times: jax.Array) -> jax.Array:
    """[B] -> [B, 1, C]: what conditioning a token on the target time adds to it."""
    return self.patch_time_embed_tgt(self._time_patch(target_times))

  def decode(
    self,
    encoded: EncoderOutput,
    tokens: jax.Array | None = None,
    target_times: jax.Array | None = None,
    viewers: jax.Array | None = None,
    static_scene: bool = False,
    own_view: jax.Array | None = None,
  ) -> jax.Array:
    """Flat Gaussians [B, T * p², 14] (see `decode_tokens` for the arguments), or with `viewers`
    [B, Vr, 3] (centres of the cameras they will be rendered from) one set per camera,
    [B, Vr, T * p², 14]: coloured for that camera under `input_colour_weights="viewer"`, else
    the same set repeated; `own_view` [Vr] bool: whether a viewer at an input view's centre
    reads that view (None: `own_view_colours` for every viewer, which False overrides). A
    `static_scene` skips the dynamic branch (tokens, head, motion and
    the re-decodes at the input times): the static Gaussians alone, exactly the first
    `num_static_gaussians` of the full decode, time-invariant (under `input_occlusion_tolerance`
    the views' occlusion renders then hold no dynamic Gaussians, as befits a static scene, so
    their colours can differ where a dynamic Gaussian hid them)."""
    cfg = self.config
    decoded, static_kv = self._decode_tokens(encoded, tokens, target_times, static_scene)
    flat = activate(self.activation_head(decoded), cfg)
    at_input_times = None
    if cfg.dynamic_motion == "linear" and not static_scene:
      flat, at_input_times = self._linear_motion(encoded, decoded, flat, target_times)
    elif not static_scene and cfg.gaussian_colours == "inputs":
      at_input_times = self._dynamic_at_input_times(encoded, tokens, target_times, static_kv)
    if cfg.gaussian_colours == "inputs":
      if encoded.views is None:
        raise ValueError(
          'gaussian_colours="inputs" reads colours from the input views: encode with '
          "`encode_views` / `reconstruct` (they carry the views), not `encode`"
        )
      flat = with_input_colours(
        flat,
        encoded.views,
        at_input_times,
        viewers if cfg.viewer_dependent else None,
        cfg.viewer_colour_sharpness,
        cfg.input_occlusion_tolerance,
        cfg.dynamic_colour_sharpness,
        own_view_reading(cfg.own_view_colours, own_view),
      )
    if viewers is not None and flat.ndim == 3:  # the same set for every camera
      flat = jnp.broadcast_to(flat[:, None], (flat.shape[0], viewers.shape[1]) + flat.shape[1:])
    return flat

  def _linear_motion(
    self,
    encoded: EncoderOutput,
    decoded: jax.Array,
    flat: jax.Array,
    target_times: jax.Array | None,
  ) -> tuple[jax.Array, jax.Array | None]:
    """`dynamic_motion="linear"`: the Gaussians [B, N, 14] moved to the target time, and the
    dynamic ones [B, V, Nd, 14] at each input view's time (None without a target time or the
    views' times, as `_dynamic_at_input_times`). Without a target time they stay at the
    reference time."""
    cfg = self.config
    if target_times is None:
      return flat, None
    velocity = self.motion_head(decoded[:, cfg.num_gs_tokens :]).astype(jnp.float32)
    velocity = velocity.reshape(velocity.shape[0], -1, 3)  # [B, Nd, 3], Gaussian = token p² + k
    static, dynamic = flat[:, : cfg.num_static_gaussians], flat[:, cfg.num_static_gaussians :]

    def moved(times: jax.Array) -> jax.Array:  # [B, K] -> [B, K, Nd, 14]
      shift = (times - LINEAR_MOTION_REFERENCE_TIME)[:, :, None, None] * velocity[:, None]
      at_times = jnp.broadcast_to(dynamic[:, None], shift.shape[:-1] + dynamic.shape[-1:])
      return at_times.at[..., :3].add(shift)

    flat = jnp.concatenate([static, moved(target_times[:, None])[:, 0]], axis=1)
    views_times = None if encoded.views is None else encoded.views.times
    return flat, None if views_times is None else moved(views_times)

  def _dynamic_at_input_times(
    self,
    encoded: EncoderOutput,
    tokens: jax.Array | None,
    target_times: jax.Array | None,
    static_kv: list[tuple[jax.Array, jax.Array]],
  ) -> jax.Array | None:
    """[B, V, Nd, 14]: the dynamic Gaussians decoded at each input view's time, where their
    colours are read (`colours` module docstring); None without dynamic tokens, a target time
    or the views' times.

    Only the dynamic tokens are decoded again, against `static_kv`, the static tokens'
    keys/values of the decode at the target time (`EncDecBackbone.decode_dynamic`): the same
    Gaussians as decoding every token at each time, with Nd tokens per time instead of T (the
    Kubric default's train step: 203 -> 128 CPU ms; docs/benchmarks.md, "Dynamic Gaussians at
    the input times")."""
    cfg = self.config
    times = None if encoded.views is None else encoded.views.times
    if not cfg.num_dynamic_gs_tokens or target_times is None or times is None:
      return None
    dynamic = self._input_tokens(encoded, tokens)[:, cfg.num_gs_tokens :]
    backbone = self.enc_dec_backbone
    at_times = [
      self.activation_head(
        backbone.decode_dynamic(
          dynamic + self._target_time_token(times[:, v]), static_kv, encoded.keys, encoded.values
        )
      )
      for v in range(times.shape[1])
    ]
    return activate(jnp.stack(at_times, axis=1), cfg)

  def __call__(
    self,
    images: jax.Array,
    plucker: jax.Array,
    times: jax.Array | None = None,
    target_times: jax.Array | None = None,
  ) -> jax.Array:
    """images [B, V, H, W, 3] (normalised), plucker [B, V, H, W, 6] -> [B, N, 14]."""
    return self.decode(self.encode(images, plucker, times), target_times=target_times)
