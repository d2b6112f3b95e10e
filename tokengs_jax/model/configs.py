"""Model configuration: one frozen dataclass, named presets, and the official `Options` mapping.

Field names follow the official `tokengs/options.py` where the official code has the concept, so
that a preset and an official `options.json` read the same. Only the architecture lives here
(losses, data and schedules belong to other areas); `image_size` and `num_input_views` are kept as
the shape a preset was trained for (benchmarks and experiments read them), the network itself
accepts any resolution divisible by the patch size and any number of views.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax.numpy as jnp

# Official constants that are not options (tokengs/models/enc_dec.py).
ENCODER_LAYER_SCALE_INIT = 0.01  # init_values of every encoder ViT block
LATENT_LAYER_SCALE_INIT = 0.01  # init_values of every latent-bottleneck block
LATENT_INIT_STD = 0.02  # std of the learnt scene latents
# Normalised time at which `dynamic_motion="linear"` decodes the dynamic Gaussians: the middle of
# the example's min-max normalised span, so no time is further than 0.5 from it.
LINEAR_MOTION_REFERENCE_TIME = 0.5
LAYER_NORM_EPS = 1e-5  # torch.nn.LayerNorm default, used by every norm of the network
# ImageNet statistics the official data provider normalises encoder RGB with.
IMAGE_MEAN = (0.485, 0.456, 0.406)
IMAGE_STD = (0.229, 0.224, 0.225)


@dataclasses.dataclass(frozen=True)
class ModelConfig:
  """Architecture of a TokenGS network (hashable: usable as a static jit argument).

  Attributes:
    patch_size: encoder patch size p (RGB, Plücker and time patch embeds).
    dec_patch_size: decoder patch size; each Gaussian token decodes dec_patch_size² Gaussians.
    enc_depth: number of encoder ViT blocks.
    dec_depth: number of decoder blocks (cross-attention -> self-attention -> MLP).
    enc_embed_dim: width C of every token (image, Gaussian and latent tokens).
    enc_num_heads: attention heads (encoder, decoder and latent blocks).
    mlp_ratio: MLP hidden width / C.
    num_gs_tokens: learnt static Gaussian tokens.
    num_dynamic_gs_tokens: learnt dynamic Gaussian tokens (time-conditioned; 0 = static model).
    gs_token_std: init std of the Gaussian tokens (also sets the default decoder LayerScale).
    dec_init_values: decoder LayerScale init; None -> 5e-3 * gs_token_std (official rule); a
      value that is 0 or None after that rule removes the decoder LayerScales (as official).
    clip_head_readout_std: init std of the head's linear layer.
    clip_head_z_init: if set, the head's z bias starts at log(1 + z_init) (latent presets).
    gaussian_scale_cap: upper bound on Gaussian scales.
    opacity_bias: opacity = sigmoid(raw - opacity_bias).
    gaussian_z_offset: added to every Gaussian's z after the head.
    time_embedding: add sinusoidal time embeddings (input views: to image tokens; target time:
      to the dynamic Gaussian tokens, or to all tokens if there are none).
    time_embedding_dim: channels of the sinusoidal time embedding.
    use_multiscale_encoder: read out several encoder layers (each with its own LayerNorm) and
      concatenate them instead of a single final LayerNorm.
    multiscale_encoder_layers: encoder block indices read out (0-based).
    use_latent_bottleneck: compress encoder features into learnt scene latents first.
    num_latents: number of scene latents.
    latent_cross_attn_depth: number of latent blocks (same block as the decoder's).
    image_size: (H, W) the preset was trained at (metadata, not architecture).
    num_input_views: context views the preset was trained with (metadata).
    dtype: compute dtype ("float32" or "bfloat16"); parameters always stay float32.
    matmul_dtype: dtype the operands of the transformer's matmuls/einsums (patch embeds, Dense
      layers, attention; forward and backward) are rounded to, products accumulated and returned
      in float32; None: the compute dtype. The Gaussian head's matmul keeps the compute dtype.
      "bfloat16" with dtype "float32" is the fast mixed-precision mode on CPUs with native bf16
      dots (about 2x the float32 matmul rate; LayerNorm, softmax, GELU, residuals and parameters
      stay float32; accuracy in docs/benchmarks.md, "Model").
    remat: rematerialise each transformer block in the backward pass (saves activation memory).
    gaussian_colours: "head" (official): RGB regressed by the head; "inputs": RGB read from the
      input views at each Gaussian's projection (`model.colours`; not in the paper), the head's
      RGB kept only where no view sees the Gaussian. Needs the views: `encode_views` /
      `reconstruct` carry them, `predict_gaussians` cannot.
    input_colour_weights: with colours read from the inputs, how the views are combined: "mean"
      (every view that sees the Gaussian alike) or "viewer" (weighted toward the view whose ray
      is nearest the rendering camera's, `model.colours.viewer_colours`): the Gaussians are then
      decoded for given cameras, one set per camera (`decode(..., viewers=)`); decoded without
      cameras (export, `predict_gaussians`) they take the mean.
    viewer_colour_sharpness: the "viewer" weights' softmax inverse temperature on the rays'
      cosine (100: a view whose ray is 8 degrees further off gets 1/e the weight).
    own_view_colours: with "viewer" weights, whether a camera at an input view's centre (that
      view rendered again: input supervision, token tuning) reads that view. False: it reads
      only the other views, so its render checks the geometry across views rather than copying
      its own pixels back (`model.colours.viewer_colours`; not in the paper). Renders from any
      other camera do not change.
    input_occlusion_tolerance: with colours read from the inputs, None reads every view a
      Gaussian projects into; a fraction leaves out the views that hide it (their render of the
      decoded scene is opaque at its projection, nearer than its own depth by more than this
      fraction; `model.colours`, not in the paper). Costs one render per input view.
    dynamic_colour_sharpness: the "viewer" weights' sharpness for the dynamic Gaussians (None:
      `viewer_colour_sharpness`). 0 averages the views, each read where the Gaussian was at its
      time: the colour then agrees across views only on a trajectory that follows what they saw
      (not in the paper; measured without a gain, docs/experiments.md "Session 16").
    dynamic_motion: how the dynamic Gaussians depend on the target time. "decoded" (official):
      the dynamic tokens are conditioned on it and decoded again for every time. "linear" (not
      in the paper): they are decoded once, unconditioned, into Gaussians at the middle of the
      example's normalised time span (`LINEAR_MOTION_REFERENCE_TIME`) plus a velocity each
      (`motion_head`, zero at initialisation); at time t a Gaussian's centre is
      centre + velocity (t - 0.5), everything else unchanged. Its centres move continuously by
      construction and its scene flow is the velocity.
  """

  patch_size: int = 8
  dec_patch_size: int = 8
  enc_depth: int = 3
  dec_depth: int = 12
  enc_embed_dim: int = 1024
  enc_num_heads: int = 16
  mlp_ratio: float = 4.0
  num_gs_tokens: int = 1024
  num_dynamic_gs_tokens: int = 0
  gs_token_std: float = 0.01
  dec_init_values: float | None = None
  clip_head_readout_std: float = 0.002
  clip_head_z_init: float | None = None
  gaussian_scale_cap: float = 0.075
  opacity_bias: float = 2.0
  gaussian_z_offset: float = 1.0
  time_embedding: bool = False
  time_embedding_dim: int = 2
  use_multiscale_encoder: bool = False
  multiscale_encoder_layers: tuple[int, ...] = (5, 7, 9, 11)
  use_latent_bottleneck: bool = False
  num_latents: int = 4096
  latent_cross_attn_depth: int = 12
  image_size: tuple[int, int] = (256, 256)
  num_input_views: int = 2
  dtype: str = "float32"
  matmul_dtype: str | None = None
  remat: bool = False
  gaussian_colours: str = "head"
  input_colour_weights: str = "mean"
  viewer_colour_sharpness: float = 100.0
  own_view_colours: bool = True
  input_occlusion_tolerance: float | None = None
  dynamic_colour_sharpness: float | None = None
  dynamic_motion: str = "decoded"

  def __post_init__(self):
    if self.enc_embed_dim % self.enc_num_heads:
      raise ValueError(
        f"enc_embed_dim={self.enc_embed_dim} is not divisible by enc_num_heads={self.enc_num_heads}"
      )
    if self.use_multiscale_encoder:
      bad = [i for i in self.multiscale_encoder_layers if not 0 <= i < self.enc_depth]
      if bad or not self.multiscale_encoder_layers:
        raise ValueError(
          f"multiscale_encoder_layers={self.multiscale_encoder_layers} must be "
          f"non-empty indices into enc_depth={self.enc_depth} blocks"
        )
      if list(self.multiscale_encoder_layers) != sorted(set(self.multiscale_encoder_layers)):
        raise ValueError(
          "multiscale_encoder_layers must be strictly increasing (the official "
          "model concatenates them in block order)"
        )
    if self.dtype not in ("float32", "bfloat16"):
      raise ValueError(f"dtype must be 'float32' or 'bfloat16', got {self.dtype!r}")
    if self.gaussian_colours not in ("head", "inputs"):
      raise ValueError(
        f"gaussian_colours must be 'head' or 'inputs', got {self.gaussian_colours!r}"
      )
    if self.input_colour_weights not in ("mean", "viewer"):
      raise ValueError(
        f"input_colour_weights must be 'mean' or 'viewer', got {self.input_colour_weights!r}"
      )
    if self.input_occlusion_tolerance is not None and not self.input_occlusion_tolerance >= 0:
      raise ValueError(
        f"input_occlusion_tolerance must be None or >= 0, got {self.input_occlusion_tolerance!r}"
      )
    for name in ("viewer_colour_sharpness", "dynamic_colour_sharpness"):
      value = getattr(self, name)
      if value is not None and not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value!r}")
    if self.dynamic_motion not in ("decoded", "linear"):
      raise ValueError(f"dynamic_motion must be 'decoded' or 'linear', got {self.dynamic_motion!r}")
    if self.dynamic_motion == "linear" and not (self.num_dynamic_gs_tokens and self.time_embedding):
      raise ValueError(
        'dynamic_motion="linear" moves the dynamic Gaussians: it needs num_dynamic_gs_tokens > 0 '
        "and time_embedding (the image tokens carry their views' times)"
      )
    if self.matmul_dtype not in (None, "float32", "bfloat16"):
      raise ValueError(
        f"matmul_dtype must be None, 'float32' or 'bfloat16', got {self.matmul_dtype!r}"
      )

  @property
  def head_dim(self) -> int:
    return self.enc_embed_dim // self.enc_num_heads

  @property
  def mlp_hidden_dim(self) -> int:
    return int(self.enc_embed_dim * self.mlp_ratio)

  @property
  def decoder_layer_scale(self) -> float | None:
    """Decoder LayerScale init (None: no LayerScale), by the official rule."""
    value = self.dec_init_values if self.dec_init_values is not None else 5e-3 * self.gs_token_std
    return value or None

  @property
  def gaussians_per_token(self) -> int:
    return self.dec_patch_size**2

  @property
  def num_tokens(self) -> int:
    """Static + dynamic Gaussian tokens."""
    return self.num_gs_tokens + self.num_dynamic_gs_tokens

  @property
  def num_gaussians(self) -> int:
    """Gaussians per scene: depends on tokens and decoder patch only, never on the views."""
    return self.num_tokens * self.gaussians_per_token

  @property
  def viewer_dependent(self) -> bool:
    """Colours depend on the rendering camera: decode for the cameras (`decode(viewers=)`)."""
    return self.gaussian_colours == "inputs" and self.input_colour_weights == "viewer"

  @property
  def num_static_gaussians(self) -> int:
    """The first num_static_gaussians of the output come from static tokens, the rest dynamic."""
    return self.num_gs_tokens * self.gaussians_per_token

  @property
  def scale_shift(self) -> float:
    """Scale activation exp(x - shift): shift = 1 - ln(cap), so raw 1 maps to the cap."""
    return 1.0 - math.log(self.gaussian_scale_cap)

  @property
  def compute_dtype(self):
    return jnp.dtype(self.dtype)

  @property
  def matmul_operand_dtype(self):
    """The modules' `matmul_dtype`: None (plain dots in the compute dtype) unless it differs."""
    if self.matmul_dtype in (None, self.dtype):
      return None
    return jnp.dtype(self.matmul_dtype)

  @property
  def encoder_feature_dim(self) -> int:
    """Width of what the encoder hands to the K/V (or latent) projection."""
    if self.use_multiscale_encoder:
      return self.enc_embed_dim * len(self.multiscale_encoder_layers)
    return self.enc_embed_dim

  def replace(self, **changes) -> ModelConfig:
    return dataclasses.replace(self, **changes)


# ----- presets ---------------------------------------------------------------------------------

# The 2026.6 latent-bottleneck release architecture (official `_LATENT_D12_ARCH`).
_LATENT_D12 = {
  "enc_depth": 12,
  "dec_depth": 1,
  "dec_patch_size": 8,
  "clip_head_readout_std": 0.002,
  "clip_head_z_init": 0.1,
  "dec_init_values": 0.01,
  "gaussian_z_offset": 0.0,
  "opacity_bias": 2.0,
  "gs_token_std": 0.02,
  "use_multiscale_encoder": True,
  "multiscale_encoder_layers": (5, 7, 9, 11),
  "use_latent_bottleneck": True,
  "num_latents": 4096,
  "latent_cross_attn_depth": 12,
}


def _build_presets() -> dict[str, ModelConfig]:
  base = ModelConfig()  # official Options defaults: 3 enc / 12 dec, C=1024, 16 heads
  # Paper, RE10K: 6 encoder / 24 decoder layers, C=1024, 256x256, 2 views; 1024 tokens for the
  # base model, 4096 after finetuning.
  re10k = base.replace(
    enc_depth=6, dec_depth=24, num_gs_tokens=1024, image_size=(256, 256), num_input_views=2
  )
  presets = {
    "tiny": ModelConfig(
      patch_size=8,
      dec_patch_size=8,
      enc_depth=2,
      dec_depth=2,
      enc_embed_dim=128,
      enc_num_heads=4,
      num_gs_tokens=32,
      image_size=(64, 64),
      num_input_views=2,
    ),
    "re10k": re10k,
    "re10k_4096": re10k.replace(num_gs_tokens=4096),
  }
  # Official DL3DV eval/finetune presets: 3 / 12 layers, 4096 tokens, 448x256.
  for views in (2, 4, 6):
    presets[f"dl3dv_{views}view"] = base.replace(
      num_gs_tokens=4096, image_size=(256, 448), num_input_views=views
    )
    presets[f"dl3dv_latent_{views}view"] = base.replace(
      num_gs_tokens=4096, image_size=(256, 448), num_input_views=views, **_LATENT_D12
    )
  # Official `finetune_dl3dv_kubric_dyn`: latent architecture + 256 dynamic tokens, time.
  presets["kubric_dyn"] = base.replace(
    num_gs_tokens=1024,
    num_dynamic_gs_tokens=256,
    time_embedding=True,
    time_embedding_dim=2,
    image_size=(256, 256),
    num_input_views=4,
    **_LATENT_D12,
  )
  presets["kubric_static"] = presets["kubric_dyn"].replace(
    num_dynamic_gs_tokens=0, time_embedding=False
  )
  return presets


PRESETS: dict[str, ModelConfig] = _build_presets()


def preset(name: str, **overrides) -> ModelConfig:
  """A named configuration, optionally with fields replaced (e.g. dtype="bfloat16").

  Names: tiny, re10k, re10k_4096, dl3dv_{2,4,6}view, dl3dv_latent_{2,4,6}view, kubric_dyn,
  kubric_static.
  """
  if name not in PRESETS:
    raise KeyError(f"unknown preset {name!r}; known: {', '.join(sorted(PRESETS))}")
  return PRESETS[name].replace(**overrides)


# ----- official options.json -> ModelConfig ---------------------------------------------------

# Official option names copied as they are; everything else in options.json (data, losses,
# schedules, logging) is not architecture and is ignored.
_SAME_NAME = (
  "patch_size",
  "enc_depth",
  "dec_depth",
  "enc_embed_dim",
  "enc_num_heads",
  "mlp_ratio",
  "num_gs_tokens",
  "num_dynamic_gs_tokens",
  "gs_token_std",
  "dec_init_values",
  "clip_head_readout_std",
  "clip_head_z_init",
  "gaussian_scale_cap",
  "opacity_bias",
  "gaussian_z_offset",
  "time_embedding",
  "time_embedding_dim",
  "use_multiscale_encoder",
  "use_latent_bottleneck",
  "num_latents",
  "latent_cross_attn_depth",
  "num_input_views",
)
_NULLABLE = ("dec_init_values", "clip_head_z_init")  # None is a meaningful value for these


def config_from_official(options: dict[str, Any], **overrides) -> ModelConfig:
  """The ModelConfig of an official `Options` (an options.json dict or a preset's fields).

  Missing keys take the official defaults (which are this dataclass's defaults); `dec_patch_size`
  None means "same as patch_size" as in the official `__post_init__`.

  Raises:
    ValueError: if token_dim differs from enc_embed_dim (the official model adds Gaussian tokens
      to enc_embed_dim-wide attention, so it only works when they are equal).
  """
  fields = {}
  for name in _SAME_NAME:
    if name in options and (options[name] is not None or name in _NULLABLE):
      fields[name] = options[name]
  if "mlp_ratio" in fields:
    fields["mlp_ratio"] = float(fields["mlp_ratio"])
  patch = int(options.get("patch_size", ModelConfig.patch_size))
  fields["dec_patch_size"] = int(options.get("dec_patch_size") or patch)
  if "multiscale_encoder_layers" in options:
    fields["multiscale_encoder_layers"] = tuple(
      int(i) for i in options["multiscale_encoder_layers"]
    )
  if "img_size" in options:
    size = options["img_size"]
    fields["image_size"] = (
      (int(size), int(size)) if isinstance(size, int) else tuple(int(s) for s in size)
    )
  token_dim = options.get("token_dim", fields.get("enc_embed_dim", ModelConfig.enc_embed_dim))
  if token_dim != fields.get("enc_embed_dim", ModelConfig.enc_embed_dim):
    raise ValueError(
      f"token_dim={token_dim} != enc_embed_dim; the official network needs them equal"
    )
  fields.update(overrides)
  return ModelConfig(**fields)
