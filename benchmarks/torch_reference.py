"""An independent PyTorch forward of the TokenGS network, for timing comparisons only.

Written for this project from our own JAX model (`tokengs_jax.model`), not from the official
code: it reads our params pytree and computes the same map with torch ops (static models without
latent bottleneck or multiscale readout). `benchmarks/model.py --torch` checks it against
`predict_gaussians` before timing it. Needs `pip install torch` (not a project dependency).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from tokengs_jax.model.configs import LAYER_NORM_EPS, ModelConfig
from tokengs_jax.model.head import RAW_CHANNELS


def _tensors(tree):
  """Params pytree -> same nesting of float32 torch tensors; Dense kernels [in, out] become
  torch.nn.Linear-style contiguous weights [out, in]."""
  if isinstance(tree, dict):
    return {
      ("weight" if k == "kernel" else k): _tensors(v.T if k == "kernel" else v)
      for k, v in tree.items()
    }
  return torch.from_numpy(np.array(tree, np.float32))  # a writable, C-contiguous copy


def _linear(x, p):
  return F.linear(x, p["weight"], p.get("bias"))


def _norm(x, p):
  return F.layer_norm(x, x.shape[-1:], p["scale"], p["bias"], LAYER_NORM_EPS)


class TorchTokenGS:
  """`forward(images, plucker) -> [B, N, 14]` for normalised images [B, V, H, W, 3] and Plücker
  rays [B, V, H, W, 6] (NHWC, as ours); weights are pre-transposed once."""

  def __init__(self, params, config: ModelConfig):
    if config.use_latent_bottleneck or config.use_multiscale_encoder or config.time_embedding:
      raise NotImplementedError("the torch reference covers static single-readout models")
    self.config = config
    self.p = _tensors(params)

  def _heads(self, x):  # [B, N, C] -> [B, h, N, d]
    b, n, c = x.shape
    return x.view(b, n, self.config.enc_num_heads, -1).transpose(1, 2)

  def _self_attention(self, x, p):
    b, n, c = x.shape
    h = self.config.enc_num_heads
    qkv = _linear(x, p["qkv"]).view(b, n, 3, h, c // h).permute(2, 0, 3, 1, 4)
    q, k = _norm(qkv[0], p["q_norm"]), _norm(qkv[1], p["k_norm"])
    out = F.scaled_dot_product_attention(q, k, qkv[2])
    return _linear(out.transpose(1, 2).reshape(b, n, c), p["proj"])

  def _mlp(self, x, p):
    return _linear(F.gelu(_linear(x, p["fc1"])), p["fc2"])

  def _embed(self, images, p):
    b, v, height, width, cin = images.shape
    s = self.config.patch_size
    patches = images.view(b, v, height // s, s, width // s, s, cin).transpose(3, 4)
    patches = patches.reshape(b, v, (height // s) * (width // s), s * s * cin)
    return _norm(_linear(patches, p["proj"]), p["norm"])

  def _scale(self, x, p, name):
    return x * p[name]["gamma"] if name in p else x

  @torch.inference_mode()
  def forward(self, images: torch.Tensor, plucker: torch.Tensor) -> torch.Tensor:
    cfg, p = self.config, self.p
    tokens = self._embed(images, p["patch_embed"]) + self._embed(plucker, p["patch_plucker_embed"])
    x = tokens.flatten(1, 2)
    backbone = p["enc_dec_backbone"]
    for i in range(cfg.enc_depth):
      block = backbone[f"encoder_{i}"]
      x = x + self._scale(
        self._self_attention(_norm(x, block["norm1"]), block["attn"]), block, "ls1"
      )
      x = x + self._scale(self._mlp(_norm(x, block["norm2"]), block["mlp"]), block, "ls2")
    features = _norm(x, backbone["encoder_norm"])
    keys, values = _linear(features, backbone["kv_proj"]).chunk(2, dim=-1)
    keys = _norm(self._heads(keys), backbone["k_proj_norm"])
    values = self._heads(values)
    t = p["gs_tokens"].expand(x.shape[0], -1, -1)
    for i in range(cfg.dec_depth):
      block = backbone[f"decoder_blocks_{i}"]
      cross = block["gs_cross_attn"]
      q = _linear(_norm(t, cross["gs_token_norm"]), cross["q_proj"])
      q = _norm(self._heads(q), cross["q_norm"])
      out = F.scaled_dot_product_attention(q, keys, values)
      out = _linear(out.transpose(1, 2).flatten(2), cross["out_proj"])
      t = t + self._scale(out, block, "gs_cross_attn_scale")
      attn = block["gs_self_attn"]
      out = self._self_attention(_norm(t, attn["norm"]), attn["gs_self_attn"])
      t = t + self._scale(out, block, "gs_self_attn_scale")
      mlp = block["mlp"]
      t = t + self._scale(self._mlp(_norm(t, mlp["norm"]), mlp["mlp"]), block, "mlp_scale")
    raw = _linear(t, p["activation_head"]["deconv"])
    return self._activate(raw.reshape(raw.shape[0], -1, RAW_CHANNELS))

  def _activate(self, raw):
    cfg = self.config
    xyz, rgb, scale, quat, opacity = raw.split([3, 3, 3, 4, 1], dim=-1)
    xyz = torch.sign(xyz) * torch.expm1(xyz.abs())
    xyz = xyz + torch.tensor([0.0, 0.0, cfg.gaussian_z_offset])
    opacity = torch.sigmoid(opacity - cfg.opacity_bias)
    scale = torch.clamp(torch.exp(scale - cfg.scale_shift), max=cfg.gaussian_scale_cap)
    quat = F.normalize(quat, dim=-1)
    rgb = 0.5 * torch.tanh(rgb) + 0.5
    return torch.cat([xyz, opacity, scale, quat, rgb], dim=-1)
