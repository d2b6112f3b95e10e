"""Training losses of TokenGS (official `tokengs/models/losses.py`, `tokengs.py`, `options.py`).

    loss = lambda_rgb * rgb + lambda_ssim * (1 - SSIM) / 2 + lambda_vis * visibility
           + lambda_lpips * LPIPS + lambda_opacity * mean(-log(opacity + 1e-6))
           + lambda_mask * mean((alpha - mask)^2)
           [+ lambda_dyn_aux(step) * loss of the dynamic Gaussians alone]

- rgb: MSE ("l2", official default) or L1 over every pixel and channel.
- SSIM term: fused-ssim conventions of the official code (11-tap Gaussian window, sigma 1.5,
  zero "same" padding, population covariance, C1 = 0.01^2, C2 = 0.03^2), mapped to (1 - SSIM) / 2.
- visibility: projected centres outside every supervision view are pulled back (below).
- LPIPS: VGG v0.1, `normalize=True`, mean over views (optional; `lpips_params` must be given).
- opacity (`opacity_loss`, official `lambda_opacity`, 0 by default): the mean of -log(opacity)
  over every Gaussian, a pull of each Gaussian towards full opacity.
- mask (`mask_loss`, official `lambda_mask`, 0 by default): the squared error between the rendered
  alpha and the target views' foreground masks, averaged over views and pixels. Where the targets
  carry masks they are also the photometric terms' background: `composite_on_white`.

Deviation from the official visibility loss: the official code takes gsplat's `means2d`, which
are projections made without looking at depth (and are zero for culled centres), so a centre
behind every camera can land "inside" an image and escape the loss. Here a centre whose depth is
<= `near` in a view counts as not visible there: its distance in that view is the clamp value
`threshold`, the most any view can contribute. A centre behind all views therefore costs
`threshold` (with no gradient, like an official centre far outside every image), and a centre
behind some views is pulled towards the nearest view in which it lies in front of the camera.

Everything is a pure function of arrays; values and gradients stay finite for constant images,
points on or behind the camera plane, and identical prediction/target.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

import jax
import jax.numpy as jnp

from tokengs_jax import camera
from tokengs_jax import metrics


@dataclasses.dataclass(frozen=True)
class LossConfig:
  """Loss weights and options; defaults as the official `Options` (base training preset).

  Attributes:
    rgb_loss: "l2" (MSE, official default) or "l1" (the latent/Kubric presets).
    lambda_rgb: weight of the photometric term (0.8 in the official L1+SSIM presets).
    lambda_ssim: weight of the (1 - SSIM) / 2 term.
    lambda_vis: weight of the visibility loss.
    visibility_threshold: clamp of the per-Gaussian visibility distance (official 1.0); > 0.
    near: depth at or below which a centre counts as not visible in a view (official znear).
    lambda_lpips: weight of the LPIPS term (0.5 in the official LPIPS presets).
    lambda_dyn_aux: base weight of the dynamic-only auxiliary loss (0.3 in the Kubric release).
    dyn_aux_hold_steps: steps for which the base weight is held (official warmup_steps, 5000).
    dyn_aux_decay_steps: steps of the linear decay after that (10000); <= 0 keeps it constant.
    dyn_aux_min: weight reached at the end of the decay.
    lambda_depth: weight of the depth term (`depth_loss`) on supervision views that carry true
      depth (the synthetic sets). Not in the paper or the official code (0 there): a geometry
      prior for training on synthetic data, where the truth is known (docs/deviations.md).
    lambda_motion: dynamic models: the photometric error of the target pixels where the scene
      moved (`moving_pixels`) counts `1 + lambda_motion` times (`motion_loss`). Not in the paper
      or the official code (0 there; docs/deviations.md): most of a target is static, and the
      input view from its own camera already explains that part.
    dyn_aux_on_motion: the dynamic auxiliary loss scores the dynamic Gaussians' render on the
      moving pixels only (RGB + visibility; needs `lambda_motion > 0`), so they answer for what
      moved and leave the static scene to the static Gaussians. Not official (docs/deviations.md).
    dyn_aux_on_objects: the dynamic auxiliary loss scores the dynamic Gaussians' render on the
      target pixels where the data's segmentation shows an object (RGB), its alpha against that
      mask (squared error toward 1 on the objects and toward 0 elsewhere, each averaged over its
      own pixels, so that an empty render is not the cheap answer) and their visibility;
      needs the batch's `target_objects`. The dynamic Gaussians are told where the objects are
      at the target time instead of finding the split alone. Not official (docs/deviations.md);
      excludes `dyn_aux_on_motion`.
    motion_threshold: the colour change (max over channels, in [0, 1]) that marks a target pixel
      as moving.
    lambda_coverage: weight of `coverage_loss`, the share of each supervision render left
      uncovered (1 - alpha). Not in the paper or the official code (0 there;
      docs/deviations.md): in scenes where every pixel is a surface (Kubric's opaque dome, closed
      rooms) a hole shows the background, and the photometric gradient cannot pull a Gaussian
      that does not overlap the hole into it; this term gives the Gaussians at its rim a reason
      to grow and move over it.
    lambda_opacity: weight of `opacity_loss` (official `lambda_opacity`, 0 in every official
      preset): mean -log(opacity + 1e-6) of the Gaussians, pulling each towards opacity 1.
    lambda_mask: weight of `mask_loss` (official `lambda_mask`, 0 in every official preset): the
      rendered alpha against the target views' foreground masks; > 0 needs the batch's
      `target_masks` (the model losses raise ValueError without them).
    lambda_flow: weight of the scene-flow term (`objective.flow.flow_loss`): the dynamic
      Gaussians' velocities, rendered into the target views, against alpha x the velocity of the
      surface each moving pixel sees (the batch's `target_flows`, from Kubric's depths,
      segmentations and object poses).
      Not in the paper or the official code (0 there; docs/deviations.md): the photometric loss
      alone does not make dynamic Gaussians follow small moving objects (issue 24).

  Every weight (`lambda_*`, `dyn_aux_min`) must be finite and >= 0.
  """

  rgb_loss: Literal["l2", "l1"] = "l2"
  lambda_rgb: float = 1.0
  lambda_ssim: float = 0.2
  lambda_vis: float = 1.0
  visibility_threshold: float = 1.0
  near: float = 0.025
  lambda_lpips: float = 0.0
  lambda_dyn_aux: float = 0.0
  dyn_aux_hold_steps: int = 0
  dyn_aux_decay_steps: int = 0
  dyn_aux_min: float = 0.0
  lambda_depth: float = 0.0
  lambda_motion: float = 0.0
  motion_threshold: float = 0.1
  dyn_aux_on_motion: bool = False
  dyn_aux_on_objects: bool = False
  lambda_coverage: float = 0.0
  lambda_opacity: float = 0.0
  lambda_mask: float = 0.0
  lambda_flow: float = 0.0

  def __post_init__(self):
    check_weights(
      {
        field.name: getattr(self, field.name)
        for field in dataclasses.fields(self)
        if field.name.startswith("lambda_") or field.name == "dyn_aux_min"
      }
    )
    if self.rgb_loss not in ("l2", "l1"):
      raise ValueError(f"rgb_loss must be 'l2' or 'l1', got {self.rgb_loss!r}")
    if self.visibility_threshold <= 0:
      raise ValueError("visibility_threshold must be > 0: it is also the cost of a hidden centre")
    if self.dyn_aux_on_motion and not self.lambda_motion > 0:
      raise ValueError("dyn_aux_on_motion needs lambda_motion > 0 (the moving pixels' mask)")
    if self.dyn_aux_on_motion and self.dyn_aux_on_objects:
      raise ValueError("dyn_aux_on_motion and dyn_aux_on_objects are two masks for one term")


def check_weights(weights: dict[str, float]) -> None:
  """Raises ValueError naming each loss weight (name -> value) that is negative or not finite: a
  negative weight would reward the error its term measures."""
  bad = [f"{name}={value!r}" for name, value in weights.items() if not 0 <= value < math.inf]
  if bad:
    raise ValueError(f"loss weights must be finite and >= 0, got {', '.join(bad)}")


def rgb_loss(pred: jax.Array, target: jax.Array, kind: str = "l2") -> jax.Array:
  """Mean squared ("l2") or absolute ("l1") error.  pred, target: [..., H, W, 3] -> []."""
  diff = pred - target
  return jnp.mean(diff * diff) if kind == "l2" else jnp.mean(jnp.abs(diff))


def moving_pixels(
  target_images: jax.Array,
  target_c2w: jax.Array,
  context_images: jax.Array,
  context_c2w: jax.Array,
  threshold: float,
) -> jax.Array:
  """Target pixels where the scene moved: their colour differs by more than `threshold` (max
  over channels) from the input view whose camera centre is nearest the target's (in bullet-time
  data, the target camera's own view at another time; any parallax left counts as motion).

  target_images: [B, T, H, W, 3]; target_c2w: [B, T, 4, 4]; context_images: [B, V, H, W, 3];
  context_c2w: [B, V, 4, 4] -> [B, T, H, W] float32 (1: moved), without gradient.
  """
  gap = jnp.linalg.norm(target_c2w[:, :, None, :3, 3] - context_c2w[:, None, :, :3, 3], axis=-1)
  nearest = jnp.argmin(gap, axis=-1)  # [B, T]
  source = jnp.take_along_axis(context_images, nearest[:, :, None, None, None], axis=1)
  change = jnp.max(jnp.abs(target_images - source), axis=-1)
  return jax.lax.stop_gradient((change > threshold).astype(jnp.float32))


def motion_loss(pred: jax.Array, target: jax.Array, moving: jax.Array, kind: str = "l2"):
  """`rgb_loss`'s error restricted to the moving pixels, averaged over all pixels (so that
  `lambda_rgb * (rgb_loss + lambda_motion * motion_loss)` weighs a moving pixel
  `1 + lambda_motion` times).

  pred, target: [..., H, W, 3]; moving: [..., H, W] in {0, 1} -> [].
  """
  diff = pred - target
  error = diff * diff if kind == "l2" else jnp.abs(diff)
  return jnp.mean(moving[..., None] * error)


def ssim_loss(pred: jax.Array, target: jax.Array) -> jax.Array:
  """(1 - SSIM) / 2 with the official fused-ssim conventions.  [..., H, W, 3] -> []."""
  values = metrics.ssim_map(pred, target, zero_pad=True, sample_covariance=False)
  return (1.0 - jnp.mean(values)) / 2.0


def visibility_loss(
  means: jax.Array,
  world_to_camera: jax.Array,
  intrinsics: jax.Array,
  height: int,
  width: int,
  *,
  threshold: float = 1.0,
  near: float = 0.025,
) -> jax.Array:
  """Mean over Gaussians of how far each centre lies outside the closest supervision view.

  In each view the centre is projected to normalised coordinates (u / W, v / H) * 2 - 1; its
  distance is relu(|u_n| - 1) + relu(|v_n| - 1), or `threshold` where depth <= `near` (see the
  module docstring). Per Gaussian: minimum over views, clamped at `threshold`.

  Args:
    means: [..., N, 3] Gaussian centres (world).
    world_to_camera: [..., V, 4, 4].
    intrinsics: [..., V, 4] (fx, fy, cx, cy) in pixels.
    height, width: image size in pixels.
    threshold: clamp value (> 0), also the distance assigned to a hidden centre.
    near: depth at or below which a centre is hidden in a view.

  Returns:
    [...] the loss per scene.
  """
  with jax.default_matmul_precision("float32"):  # full float32 dots on GPU / TPU too
    uv, depth = camera.project_points(means, world_to_camera, intrinsics)  # [...,V,N,2], [...,V,N]
  size = jnp.asarray([width, height], uv.dtype)
  uv_normalised = uv / size * 2.0 - 1.0
  outside = jnp.sum(jax.nn.relu(jnp.abs(uv_normalised) - 1.0), axis=-1)  # [..., V, N]
  in_front = depth > near
  # The where's other branch gets a zero cotangent, so the huge uv of a centre near the camera
  # plane (finite thanks to project_points' floored division) never reaches the gradient.
  distance = jnp.where(in_front, outside, threshold)
  per_gaussian = jnp.minimum(jnp.min(distance, axis=-2), threshold)  # [..., N]
  return jnp.mean(per_gaussian, axis=-1)


def dynamic_aux_weight(step: jax.Array | int, config: LossConfig) -> jax.Array:
  """Hold-then-decay weight of the dynamic auxiliary loss (official compute_lambda_dyn_aux_eff).

  The base weight holds while step <= dyn_aux_hold_steps, then moves linearly to dyn_aux_min over
  dyn_aux_decay_steps and stays there; with dyn_aux_decay_steps <= 0 it is constant. step: [] int.
  """
  base = config.lambda_dyn_aux
  if base <= 0:
    return jnp.zeros((), jnp.float32)
  if config.dyn_aux_decay_steps <= 0:
    return jnp.full((), base, jnp.float32)
  past_hold = jnp.asarray(step, jnp.float32) - config.dyn_aux_hold_steps
  fraction = jnp.clip(past_hold / config.dyn_aux_decay_steps, 0.0, 1.0)
  return base + fraction * (config.dyn_aux_min - base)


def coverage_loss(alpha: jax.Array) -> jax.Array:
  """Mean uncovered share of the renders: mean(1 - alpha).  alpha: [..., H, W, 1] -> []."""
  return jnp.mean(1.0 - alpha)


def opacity_loss(opacities: jax.Array) -> jax.Array:
  """Official opacity regulariser: mean of -log(opacity + 1e-6).  opacities: [..., N] -> []."""
  return -jnp.mean(jnp.log(opacities + 1e-6))


def mask_loss(alpha: jax.Array, masks: jax.Array) -> jax.Array:
  """Official foreground-mask term: mean squared error between the rendered alpha and the target
  masks (official `F.mse_loss(pred_masks, gt_masks)` per scene, then the mean over scenes: every
  scene here has its masks, so that is the mean over all of them).

  alpha: [..., H, W, 1] rendered opacity; masks: [..., H, W] in [0, 1] (1: foreground) -> [].
  """
  return jnp.mean(jnp.square(alpha[..., 0] - masks))


def composite_on_white(images: jax.Array, masks: jax.Array) -> jax.Array:
  """Target images with their background (mask 0) replaced by white, as the official loss sees
  a masked target whatever `bg_color` the renders use (`gt * mask + 1 * (1 - mask)`).

  images: [..., H, W, 3] in [0, 1]; masks: [..., H, W] in [0, 1] -> [..., H, W, 3].
  """
  masks = masks[..., None].astype(images.dtype)
  return images * masks + (1.0 - masks)


def depth_loss(depth: jax.Array, alpha: jax.Array, true_depth: jax.Array) -> jax.Array:
  """Opacity-weighted relative depth error over the pixels whose true depth is known:
  mean of alpha |d - d*| / d* where d* > 0 (0 with no such pixel).

  Weighting by alpha (= |D - alpha d*| / d* with D the accumulated depth) keeps the gradient
  bounded where the render is nearly empty, where the expected depth d = D / alpha is noise.

  depth, alpha: [..., H, W, 1] rendered expected depth and opacity; true_depth: [..., H, W]
  (0: unknown) -> [].
  """
  known = true_depth > 0
  safe_truth = jnp.where(known, true_depth, 1.0)
  error = alpha[..., 0] * jnp.abs(depth[..., 0] - safe_truth) / safe_truth
  return jnp.sum(jnp.where(known, error, 0.0)) / jnp.maximum(jnp.sum(known), 1)


def render_loss(
  pred_rgb: jax.Array,
  target_rgb: jax.Array,
  config: LossConfig = LossConfig(),
  *,
  means: jax.Array | None = None,
  world_to_camera: jax.Array | None = None,
  intrinsics: jax.Array | None = None,
  lpips_params: dict | None = None,
) -> tuple[jax.Array, dict[str, jax.Array]]:
  """Total training loss of rendered target views and its terms.

  Args:
    pred_rgb: [B, V, H, W, 3] renders (any leading shape works; terms average over it).
    target_rgb: [B, V, H, W, 3] ground truth in [0, 1].
    config: weights and options.
    means: [B, N, 3] Gaussian centres; with the cameras, needed when lambda_vis > 0.
    world_to_camera: [B, V, 4, 4] the supervision views.
    intrinsics: [B, V, 4] in pixels.
    lpips_params: `tokengs_jax.lpips.load_vgg_params()`; needed when lambda_lpips > 0.

  Returns:
    (loss [], terms) with terms "rgb", "ssim", "visibility", "lpips" (those that are on), "loss",
    and "psnr" (of clipped images, no gradient; for logging).
  """
  terms = {"rgb": rgb_loss(pred_rgb, target_rgb, config.rgb_loss)}
  loss = config.lambda_rgb * terms["rgb"]
  if config.lambda_ssim > 0:
    terms["ssim"] = ssim_loss(pred_rgb, target_rgb)
    loss = loss + config.lambda_ssim * terms["ssim"]
  if config.lambda_vis > 0:
    if means is None or world_to_camera is None or intrinsics is None:
      raise ValueError("lambda_vis > 0 needs means, world_to_camera and intrinsics")
    height, width = pred_rgb.shape[-3], pred_rgb.shape[-2]
    terms["visibility"] = jnp.mean(
      visibility_loss(
        means,
        world_to_camera,
        intrinsics,
        height,
        width,
        threshold=config.visibility_threshold,
        near=config.near,
      )
    )
    loss = loss + config.lambda_vis * terms["visibility"]
  if config.lambda_lpips > 0:
    if lpips_params is None:
      raise ValueError("lambda_lpips > 0 needs lpips_params (tokengs_jax.lpips.load_vgg_params())")
    from tokengs_jax import lpips as lpips_lib  # VGG code only when the term is on

    terms["lpips"] = jnp.mean(lpips_lib.lpips_distance(lpips_params, pred_rgb, target_rgb))
    loss = loss + config.lambda_lpips * terms["lpips"]
  terms["loss"] = loss
  terms["psnr"] = jnp.mean(metrics.psnr(jax.lax.stop_gradient(pred_rgb), target_rgb))
  return loss, terms


def add_dynamic_aux(
  loss: jax.Array,
  terms: dict[str, jax.Array],
  dynamic_loss: jax.Array,
  step: jax.Array | int,
  config: LossConfig,
) -> tuple[jax.Array, dict[str, jax.Array]]:
  """Adds the dynamic-only auxiliary loss with its scheduled weight.

  As the official Kubric models: `dynamic_loss` is `render_loss` of a render of the dynamic
  Gaussians alone (the last num_dynamic_tokens * patch^2 of them, visibility on their means),
  against the same targets. Returns (loss + weight * dynamic_loss, terms + "dyn_aux",
  "dyn_aux_weight").
  """
  weight = dynamic_aux_weight(step, config)
  terms = dict(terms, dyn_aux=jax.lax.stop_gradient(dynamic_loss), dyn_aux_weight=weight)
  loss = loss + weight * dynamic_loss
  terms["loss"] = loss
  return loss, terms
