"""A pixel-aligned GS-LRM-style baseline, for the studies' like-for-like comparisons.

GS-LRM (Zhang et al. 2024) patchifies the posed input images (RGB + Plücker rays), runs a plain
transformer over all views' patch tokens, and unpatchifies every output token into one Gaussian
per pixel whose centre lies on that pixel's ray at a predicted depth. Here the blocks, widths and
activations are TokenGS's own (`tokengs_jax.model` layers, `head.activate`), the transformer has
`enc_depth + dec_depth` blocks of the same width, so the two models differ in what the paper
contrasts: Gaussians tied to pixel rays versus free Gaussians decoded from learnt tokens.

With `gaussian_colours="inputs"` its Gaussians read their colours from the input views exactly as
TokenGS's do (`tokengs_jax.model.colours`).

Not part of the library: it exists so that the studies (`experiments/studies/camera_noise.py`)
and a run with `--eval.pixel-baseline` can train it with exactly the data, loss, optimiser and loop
the TokenGS model gets, and score it beside TokenGS (`method`).
"""

from __future__ import annotations

import functools

import flax.linen as nn
import jax
import jax.numpy as jnp

from tokengs_jax.camera import invert_rigid, plucker_rays, ray_directions
from tokengs_jax.gaussians import Gaussians
from tokengs_jax.model import ModelConfig, normalize_images
from tokengs_jax.model.colours import InputViews, own_view_reading, with_input_colours
from tokengs_jax.model.encoder import EncoderBlock
from tokengs_jax.model.head import RAW_CHANNELS, activate
from tokengs_jax.model.layers import PatchEmbed, layer_norm

# Depth along each ray = NEAR + (FAR - NEAR) * sigmoid(raw): cameras are normalised so scene
# depths are about 1 (translation scale 0.25 on RE10K), so this range covers every room.
DEPTH_NEAR = 0.05
DEPTH_FAR = 6.0
_DEPTH_CHANNEL = 2  # the raw z channel of the TokenGS head layout carries the depth logit


class PixelAlignedGS(nn.Module):
  """Posed images -> one Gaussian per input pixel (depth along its ray)."""

  config: ModelConfig

  @nn.compact
  def __call__(self, images: jax.Array, plucker: jax.Array) -> jax.Array:
    """images (normalised) [B, V, H, W, 3], plucker [B, V, H, W, 6] -> raw [B, V, H, W, 14]."""
    cfg, dtype = self.config, self.config.compute_dtype
    b, v, h, w, _ = images.shape
    p = cfg.patch_size
    tokens = PatchEmbed(cfg.enc_embed_dim, p, dtype=dtype, name="rgb_embed")(images) + PatchEmbed(
      cfg.enc_embed_dim, p, dtype=dtype, name="ray_embed"
    )(plucker)
    tokens = tokens.reshape(b, v * (h // p) * (w // p), cfg.enc_embed_dim)
    for i in range(cfg.enc_depth + cfg.dec_depth):
      tokens = EncoderBlock(cfg, name=f"block_{i}")(tokens)
    tokens = layer_norm(dtype, "norm")(tokens)
    raw = nn.Dense(
      RAW_CHANNELS * p * p,
      dtype=dtype,
      param_dtype=jnp.float32,
      kernel_init=nn.initializers.normal(cfg.clip_head_readout_std),
      name="unpatchify",
    )(tokens)
    # [B, V, h/p, w/p, p, p, 14] -> [B, V, H, W, 14]
    raw = raw.reshape(b, v, h // p, w // p, p, p, RAW_CHANNELS)
    return jnp.swapaxes(raw, 3, 4).reshape(b, v, h, w, RAW_CHANNELS).astype(jnp.float32)


def init_params(key: jax.Array, config: ModelConfig) -> dict:
  p = config.patch_size
  return PixelAlignedGS(config).init(key, jnp.zeros((1, 1, p, p, 3)), jnp.zeros((1, 1, p, p, 6)))[
    "params"
  ]


def reconstruct(
  params,
  images: jax.Array,
  c2w: jax.Array,
  intrinsics: jax.Array,
  *,
  config: ModelConfig,
  viewer_c2w: jax.Array | None = None,
  own_view: jax.Array | None = None,
) -> Gaussians:
  """Images in [0, 1] [B, V, H, W, 3] + cameras -> Gaussians [B, V * H * W] on the pixel rays.

  Where `config.viewer_dependent`, colours are read for the cameras `viewer_c2w` [B, T, 4, 4]
  as TokenGS's are: one set per camera, Gaussians [B, T, V * H * W], and `own_view` [T] bool
  per camera as `model.reconstruct`'s."""
  height, width = images.shape[-3:-1]
  raw = PixelAlignedGS(config).apply(
    {"params": params}, normalize_images(images), plucker_rays(c2w, intrinsics, height, width)
  )
  flat = activate(raw, config)
  depth = DEPTH_NEAR + (DEPTH_FAR - DEPTH_NEAR) * jax.nn.sigmoid(
    raw[..., _DEPTH_CHANNEL : _DEPTH_CHANNEL + 1]
  )
  origins = c2w[..., None, None, :3, 3]
  means = origins + depth * ray_directions(c2w, intrinsics, height, width)
  flat = jnp.concatenate([means, flat[..., 3:]], axis=-1)
  flat = flat.reshape(flat.shape[0], -1, flat.shape[-1])
  if config.gaussian_colours == "inputs":  # the same colour source as the TokenGS it is set beside
    viewers = viewer_c2w[..., :3, 3] if config.viewer_dependent else None
    flat = with_input_colours(
      flat,
      InputViews(images, invert_rigid(c2w), intrinsics),
      viewers=viewers,
      sharpness=config.viewer_colour_sharpness,
      occlusion_tolerance=config.input_occlusion_tolerance,
      own_view=own_view_reading(config.own_view_colours, own_view),
    )
  return Gaussians.from_flat(flat)


def loss_fn(
  config: ModelConfig, loss_config=None, render_config=None, objective=None, lpips_params=None
):
  """The TokenGS training objective with this model in place of TokenGS (`static_model_loss`
  with this `reconstruct`: same terms, same renders, colours read for the target cameras where
  they depend on the viewer; `lpips_params`: VGG weights when `loss_config.lambda_lpips > 0`)."""
  from tokengs_jax import losses, splatting
  from tokengs_jax.objective import ObjectiveConfig, static_model_loss

  loss_config = losses.LossConfig() if loss_config is None else loss_config
  render_config = splatting.RenderConfig() if render_config is None else render_config
  objective = ObjectiveConfig() if objective is None else objective

  def compute(params, batch, key, step):
    del key, step
    return static_model_loss(
      params,
      batch,
      model_config=config,
      loss_config=loss_config,
      render_config=render_config,
      objective=objective,
      lpips_params=lpips_params,
      reconstruct=reconstruct,
    )

  return compute


@functools.partial(jax.jit, static_argnames=("config",))
def jitted_reconstruct(params, images, c2w, intrinsics, config, viewer_c2w=None):
  return reconstruct(params, images, c2w, intrinsics, config=config, viewer_c2w=viewer_c2w)


def method(params, config: ModelConfig, objective=None):
  """The trained baseline as an evaluation method: its Gaussians rendered at the targets with
  the objective it was trained with (`loss_fn`'s; None: `ObjectiveConfig()`)."""
  from tokengs_jax import evaluation
  from tokengs_jax.objective import ObjectiveConfig

  return evaluation.Method(
    gaussians=lambda batch: jitted_reconstruct(
      params,
      batch["context_images"],
      batch["context_c2w"],
      batch["context_intrinsics"],
      config,
      batch["target_c2w"],
    ),
    objective=ObjectiveConfig() if objective is None else objective,
  )
