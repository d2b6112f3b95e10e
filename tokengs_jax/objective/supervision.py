"""Supervision of static renders: the memory-lean mean over target views and the loss terms.

`mean_over_view_chunks` is the JAX form of the official "deferred back-propagation": the views are
processed `chunk_size` at a time in a `lax.scan` whose body is rematerialised, so the backward pass
recomputes one chunk's render at a time and peak memory holds one chunk's intermediates instead
of every view's. The gradient is that of the one-shot mean (up to float summation order).

The terms are small top-level functions (`render_views`, `photometric_loss`, `add_visibility`,
`render_diagnostics`) composed by `supervision_loss`; `model_loss` builds the model losses on them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp

from tokengs_jax.gaussians import Gaussians
from tokengs_jax.objective.settings import ObjectiveConfig, render_settings


def mean_over_view_chunks(chunk_loss: Callable, views, chunk_size: int | None):
  """Mean of `chunk_loss` over chunks of views, rematerialised per chunk.

  Args:
    chunk_loss: `views_chunk -> (scalar, aux dict of scalars)`, itself a mean over the chunk's
      views (so that equal-size chunks average to the mean over all views).
    views: pytree of arrays `[B, V, ...]` (view axis 1).
    chunk_size: views per chunk (must divide V); None or >= V: one chunk, no scan.

  Returns:
    `(mean loss, mean aux)`.
  """
  num_views = jax.tree.leaves(views)[0].shape[1]
  if chunk_size is None or chunk_size >= num_views:
    return chunk_loss(views)
  if num_views % chunk_size:
    raise ValueError(f"chunk_size {chunk_size} must divide the {num_views} target views")
  num_chunks = num_views // chunk_size

  def to_chunks(x):  # [B, V, ...] -> [num_chunks, B, chunk_size, ...]
    x = x.reshape(x.shape[0], num_chunks, chunk_size, *x.shape[2:])
    return jnp.moveaxis(x, 1, 0)

  @jax.checkpoint
  def body(total, chunk):
    loss, aux = chunk_loss(chunk)
    return total + loss.astype(jnp.float32), aux

  total, aux = jax.lax.scan(body, jnp.zeros((), jnp.float32), jax.tree.map(to_chunks, views))
  return total / num_chunks, jax.tree.map(lambda a: jnp.mean(a, axis=0), aux)


def render_views(
  gaussians: Gaussians,
  world_to_camera: jax.Array,
  intrinsics: jax.Array,
  height: int,
  width: int,
  render_config,
  objective: ObjectiveConfig,
  context_images=None,
):
  """Float32 renders of Gaussians [B(, ...)] into views [B(, ...), V] (`splatting.render`) over
  the objective's `render_settings` (context_images [B, Vi, H, W, 3]: needed by "input_mean" only)."""
  from tokengs_jax import splatting  # the heavy areas only when this objective is used

  return splatting.render(
    gaussians,
    world_to_camera,
    intrinsics,
    height=height,
    width=width,
    **render_settings(objective, context_images, world_to_camera, render_config),
  )


def render_diagnostics(stats) -> dict:
  """Logged render health: "render_overflow" (fraction of renders whose tile budget overflowed),
  "render_pairs_needed" (the most (Gaussian, tile) pairs any view needed: the budget that would
  have held them, `splatting.larger_budget(..., needed=)`; under view chunks the mean of the
  chunks' maxima, a lower bound) and "visible" (mean number of Gaussians drawn per view)."""
  return {
    "render_overflow": jnp.mean(stats.overflow.astype(jnp.float32)),
    "render_pairs_needed": jnp.max(stats.num_intersections).astype(jnp.float32),
    "visible": jnp.mean(stats.num_visible.astype(jnp.float32)),
  }


def add_visibility(
  loss: jax.Array,
  terms: dict,
  means: jax.Array,
  world_to_camera: jax.Array,
  intrinsics: jax.Array,
  height: int,
  width: int,
  loss_config,
):
  """`loss + lambda_vis * visibility` (terms gain "visibility" and the new "loss").

  means: [B, ..., N, 3] projected into every view [B, V] (min over views, as official).
  The visibility term only projects centres, so it is taken over all views at once even when
  the photometric terms are chunked (its minimum over views does not split into chunks).
  """
  from tokengs_jax import losses

  if loss_config.lambda_vis <= 0:
    return loss, terms
  visibility = jnp.mean(
    losses.visibility_loss(
      means,
      world_to_camera,
      intrinsics,
      height,
      width,
      threshold=loss_config.visibility_threshold,
      near=loss_config.near,
    )
  )
  loss = loss + loss_config.lambda_vis * visibility
  return loss, {**terms, "visibility": visibility, "loss": loss}


def add_coverage(loss: jax.Array, terms: dict, alpha: jax.Array, loss_config):
  """`loss + lambda_coverage * coverage` (terms gain "coverage" and the new "loss") where
  `loss_config.lambda_coverage > 0`; alpha: [..., H, W, 1] the renders' opacity."""
  from tokengs_jax import losses

  if loss_config.lambda_coverage <= 0:
    return loss, terms
  coverage = losses.coverage_loss(alpha)
  loss = loss + loss_config.lambda_coverage * coverage
  return loss, {**terms, "coverage": coverage, "loss": loss}


def add_mask(loss: jax.Array, terms: dict, alpha: jax.Array, masks, loss_config):
  """`loss + lambda_mask * losses.mask_loss` (terms gain "mask" and the new "loss") where
  `loss_config.lambda_mask > 0`; alpha: [..., H, W, 1] the renders' opacity, masks: [..., H, W]
  the views' foreground masks (None with lambda_mask > 0: ValueError)."""
  from tokengs_jax import losses

  if loss_config.lambda_mask <= 0:
    return loss, terms
  if masks is None:
    raise ValueError("lambda_mask > 0 needs the views' foreground masks (`target_masks`)")
  mask = losses.mask_loss(alpha, masks)
  loss = loss + loss_config.lambda_mask * mask
  return loss, {**terms, "mask": mask, "loss": loss}


def add_opacity(loss: jax.Array, terms: dict, opacities: jax.Array, loss_config):
  """`loss + lambda_opacity * losses.opacity_loss` (terms gain "opacity" and the new "loss")
  where `loss_config.lambda_opacity > 0`; opacities: [..., N] of the scored Gaussians."""
  from tokengs_jax import losses

  if loss_config.lambda_opacity <= 0:
    return loss, terms
  opacity = losses.opacity_loss(opacities)
  loss = loss + loss_config.lambda_opacity * opacity
  return loss, {**terms, "opacity": opacity, "loss": loss}


def _add_depth(loss: jax.Array, terms: dict, rendered, depths, loss_config):
  """`loss + lambda_depth * losses.depth_loss` (terms gain "depth" and the new "loss") where
  the views carry true depths [..., H, W] (None: unchanged)."""
  from tokengs_jax import losses

  if depths is None:
    return loss, terms
  depth = losses.depth_loss(rendered.depth, rendered.alpha, depths)
  loss = loss + loss_config.lambda_depth * depth
  return loss, {**terms, "depth": depth, "loss": loss}


def _pixel_truth(depths, masks, loss_config) -> dict:
  """The views' per-pixel truth that the terms which are on score, float32 [B, V, H, W]:
  "depths" (given and `lambda_depth > 0`), "masks" (given and `lambda_mask > 0`)."""
  truth = {}
  if depths is not None and loss_config.lambda_depth > 0:
    truth["depths"] = depths.astype(jnp.float32)
  if masks is not None and loss_config.lambda_mask > 0:
    truth["masks"] = masks.astype(jnp.float32)
  return truth


def _add_pixel_truth_terms(loss: jax.Array, terms: dict, rendered, views: dict, loss_config):
  """The depth and mask terms (`_add_depth`, `add_mask`) of a chunk's render against its views'
  `_pixel_truth`; `add_mask` refuses a mask weight without masks."""
  loss, terms = _add_depth(loss, terms, rendered, views.get("depths"), loss_config)
  return add_mask(loss, terms, rendered.alpha, views.get("masks"), loss_config)


def photometric_loss(rgb: jax.Array, images: jax.Array, loss_config, lpips_params=None):
  """RGB, SSIM and LPIPS terms of renders against images (`losses.render_loss` without the
  visibility term, which `add_visibility` adds over all views)."""
  from tokengs_jax import losses

  return losses.render_loss(
    rgb, images, dataclasses.replace(loss_config, lambda_vis=0.0), lpips_params=lpips_params
  )


def gaussians_in_float32(gaussians: Gaussians) -> Gaussians:
  """Gaussians with every field in float32 (what the objective renders)."""
  return jax.tree.map(lambda x: x.astype(jnp.float32), gaussians)


def supervision_loss(
  gaussians,
  images,
  world_to_camera,
  intrinsics,
  loss_config,
  render_config,
  objective: ObjectiveConfig = ObjectiveConfig(),
  lpips_params=None,
  depths=None,
  context_images=None,
  masks=None,
):
  """Loss of Gaussians against supervision views (training targets, or the inputs when tuning).

  Views rendered in remat chunks of `objective.view_chunk_size`, `photometric_loss` averaged
  over chunks, then `add_visibility` over all views (= `losses.render_loss` of one render) and
  `add_opacity` of the Gaussians.

  Args:
    gaussians: `Gaussians` with batch shape [B] (rendered in float32), or [B, V]: set v seen by
      view v only (colours that depend on the viewer, `model.decode(viewer_c2w=)`).
    images: [B, V, H, W, 3] supervision images in [0, 1].
    world_to_camera: [B, V, 4, 4].
    intrinsics: [B, V, 4] in pixels.
    loss_config: `losses.LossConfig`.
    render_config: `splatting.RenderConfig`.
    objective: view chunking, background, near/far.
    lpips_params: VGG weights when `loss_config.lambda_lpips > 0`.
    depths: [B, V, H, W] true depth of the views (0: unknown), or None; with
      `loss_config.lambda_depth > 0` it adds `lambda_depth * losses.depth_loss` (term "depth").
    context_images: [B, Vi, H, W, 3] the input views (the "input_mean" background's colour).
    masks: [B, V, H, W] foreground masks, needed by `loss_config.lambda_mask > 0` ("mask").

  Returns:
    `(loss, terms)`: the loss terms, "psnr", and `render_diagnostics`.
  """
  gaussians = gaussians_in_float32(gaussians)
  height, width = images.shape[-3], images.shape[-2]
  world_to_camera = world_to_camera.astype(jnp.float32)
  intrinsics = intrinsics.astype(jnp.float32)

  per_view = len(gaussians.batch_shape) == 2

  def chunk_loss(views):
    w2c, intrinsics = views["world_to_camera"], views["intrinsics"]
    if per_view:  # each view's own set: a batch [B, Vc] of single-camera renders
      w2c, intrinsics = w2c[:, :, None], intrinsics[:, :, None]
    rendered = render_views(
      views["gaussians"] if per_view else gaussians,
      w2c,
      intrinsics,
      height,
      width,
      render_config,
      objective,
      context_images,
    )
    if per_view:
      rendered = jax.tree.map(lambda x: x[:, :, 0], rendered)
    loss, terms = photometric_loss(rendered.rgb, views["images"], loss_config, lpips_params)
    loss, terms = add_coverage(loss, terms, rendered.alpha, loss_config)
    loss, terms = _add_pixel_truth_terms(loss, terms, rendered, views, loss_config)
    return loss, {**terms, **render_diagnostics(rendered.stats)}

  views = {
    "world_to_camera": world_to_camera,
    "intrinsics": intrinsics,
    "images": images.astype(jnp.float32),
    **_pixel_truth(depths, masks, loss_config),
  }
  if per_view:
    views["gaussians"] = gaussians
  loss, terms = mean_over_view_chunks(chunk_loss, views, objective.view_chunk_size)
  # the sets of one scene differ in colour only: their centres are the first set's
  means = gaussians.means[:, 0] if per_view else gaussians.means
  loss, terms = add_visibility(
    loss, terms, means, world_to_camera, intrinsics, height, width, loss_config
  )
  return add_opacity(loss, terms, gaussians.opacities, loss_config)
