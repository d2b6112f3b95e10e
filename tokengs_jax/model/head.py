"""Gaussian head: one linear layer per token -> p² Gaussians, and the official activations.

Official counterpart: `ClipActivationHead` in `tokengs/models/activations.py`. The linear layer
writes, per token, p² blocks of 14 raw channels in the order
[xyz 3, rgb 3, scale 3, quat 4, opacity 1]; after activation they are re-ordered into the flat
output layout [xyz 3, opacity 1, scale 3, quat 4, rgb 3] (`tokengs_jax.gaussians` layout).
"""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp

from tokengs_jax.math import safe_exp, safe_normalize
from tokengs_jax.model.configs import ModelConfig

RAW_CHANNELS = 14
_RAW_SPLITS = (3, 6, 9, 13)  # xyz | rgb | scale | quat | opacity
_RAW_Z = 2  # raw channel of z (clip_head_z_init sets its bias)


def signed_expm1(x: jax.Array) -> jax.Array:
  """sign(x) * (exp|x| - 1), written per branch so the gradient at 0 is 1 (not 0)."""
  return jnp.where(x >= 0, jnp.expm1(x), -jnp.expm1(-x))


def activate(raw: jax.Array, config: ModelConfig) -> jax.Array:
  """Raw head channels -> flat Gaussians (z-offset included).

  Args:
    raw: [..., 14] in the head's raw order [xyz, rgb, scale, quat, opacity].
    config: the model config (scale cap, opacity bias, z-offset).

  Returns:
    [..., 14] float32: [xyz 3, opacity 1, scale 3, quat 4 (unit), rgb 3].
  """
  raw = raw.astype(jnp.float32)
  xyz, rgb, scale, quat, opacity = jnp.split(raw, _RAW_SPLITS, axis=-1)
  xyz = signed_expm1(xyz) + jnp.array([0.0, 0.0, config.gaussian_z_offset], jnp.float32)
  opacity = jax.nn.sigmoid(opacity - config.opacity_bias)
  # safe_exp: identical values below the cap, no inf * 0 gradient when the cap is active.
  scale = jnp.minimum(safe_exp(scale - config.scale_shift), config.gaussian_scale_cap)
  quat = safe_normalize(quat)  # x / max(|x|, 1e-12), as F.normalize
  rgb = 0.5 * jnp.tanh(rgb) + 0.5
  return jnp.concatenate([xyz, opacity, scale, quat, rgb], axis=-1)


class GaussianHead(nn.Module):
  """Linear `deconv` [C -> 14 p²] (official name), reshaped to p² Gaussians per token."""

  config: ModelConfig

  def _bias_init(self, key, shape, dtype=jnp.float32):
    del key
    bias = jnp.zeros((self.config.gaussians_per_token, RAW_CHANNELS), dtype)
    if self.config.clip_head_z_init is not None:
      bias = bias.at[:, _RAW_Z].set(math.log(1.0 + self.config.clip_head_z_init))
    return bias.reshape(shape)

  @nn.compact
  def __call__(self, tokens: jax.Array) -> jax.Array:
    """tokens: [B, T, C] -> raw channels [B, T * p², 14] (Gaussian index = token * p² + k).

    `ModelConfig.matmul_dtype` does not apply here: the raw Gaussian channels come straight out
    of this matmul, and keeping it in the compute dtype cuts the bf16 mode's Gaussian error about
    4x for 0.4-4% of the FLOPs (docs/benchmarks.md, "Model").
    """
    cfg = self.config
    raw = nn.Dense(
      RAW_CHANNELS * cfg.gaussians_per_token,
      dtype=cfg.compute_dtype,
      param_dtype=jnp.float32,
      # torch trunc_normal_(std) truncates at +-2 absolute, i.e. never at these stds.
      kernel_init=nn.initializers.normal(cfg.clip_head_readout_std),
      bias_init=self._bias_init,
      name="deconv",
    )(tokens)
    b, t, _ = raw.shape
    return raw.reshape(b, t * cfg.gaussians_per_token, RAW_CHANNELS)
