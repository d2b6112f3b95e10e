"""The TokenGS training loss: static and dynamic (time-conditioned) models.

Static models are scored by `supervision.supervision_loss` (the memory-lean mean over target
views of the render, SSIM/LPIPS and visibility terms).

Dynamic (time-conditioned) models: the context is encoded once; the Gaussians are decoded once
per target view at that view's time (`model.decode_at_times`, a vmap over times with the
keys/values shared), inside the view chunks, so the memory-lean path bounds the decoder's
activations too; each view is rendered from the Gaussians of its own time
(`time_conditioned_loss`), plus the dynamic auxiliary loss of the official Kubric models (the same
loss on a render of the dynamic Gaussians alone) weighted by `losses.dynamic_aux_weight(step)`.

`tokengs_loss_fn` picks `static_model_loss` or `dynamic_model_loss` and receives the training
step as an argument (`loss_fn(params, batch, key, step)`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp

from tokengs_jax.gaussians import Gaussians
from tokengs_jax.objective import flow
from tokengs_jax.objective.settings import ObjectiveConfig, check_cross_view, cross_view_flags
from tokengs_jax.objective.supervision import (
  add_coverage,
  add_mask,
  add_opacity,
  add_visibility,
  gaussians_in_float32,
  mean_over_view_chunks,
  photometric_loss,
  render_diagnostics,
  render_views,
  supervision_loss,
)


def time_conditioned_loss(
  gaussians_at: Callable[[jax.Array, jax.Array], Gaussians],
  times: jax.Array,
  images: jax.Array,
  world_to_camera: jax.Array,
  intrinsics: jax.Array,
  loss_config,
  render_config,
  objective: ObjectiveConfig = ObjectiveConfig(),
  lpips_params=None,
  *,
  num_static_gaussians: int | None = None,
  step: jax.Array | int = 0,
  context_images: jax.Array | None = None,
  moving: jax.Array | None = None,
  objects: jax.Array | None = None,
  masks: jax.Array | None = None,
  flows: jax.Array | None = None,
):
  """Loss of time-conditioned Gaussians against views taken at different times.

  Each view is rendered from `gaussians_at` its own time (`objective.decode_times == "first"`:
  every view from one decode at the first view's time) and scored with `losses.render_loss`, in
  rematerialised chunks of `objective.view_chunk_size` views; `gaussians_at` runs inside each
  chunk, so peak memory holds one chunk's decodes and renders. Visibility: the Gaussians of each
  view's time projected into all views (min over views, as official), averaged over the times.

  Args:
    gaussians_at: `(times [B, T], world_to_camera [B, T, 4, 4]) -> Gaussians [B, T]` to render
      at those times from those cameras (e.g. `model.decode_at_times`); under "first" called
      once with times [B, 1] and every view's camera: one set [B, 1] or one per view [B, V].
    times: [B, V] normalised time of each view; images: [B, V, H, W, 3] its image in [0, 1].
    world_to_camera: [B, V, 4, 4]; intrinsics: [B, V, 4] in pixels.
    loss_config, render_config: `losses.LossConfig`, `splatting.RenderConfig`.
    objective: view chunking, background, near/far, decode_times; lpips_params: LPIPS's VGG.
    num_static_gaussians: where the dynamic Gaussians start (the flow term's; None: all). With
      `lambda_dyn_aux > 0` the official auxiliary loss (the loss of their render alone) is added,
      weighted by `losses.dynamic_aux_weight(step)`, not evaluated while that is 0 (None: off).
    step: [] int, the training step the auxiliary weight's schedule reads.
    context_images: [B, Vi, H, W, 3] the input views ("input_mean" backgrounds' colour).
    moving: [B, V, H, W] the views' moving pixels (`losses.moving_pixels`), weighted
      `1 + loss_config.lambda_motion` (None or lambda_motion 0: no motion term).
    objects: [B, V, H, W] the views' object pixels (the batch's `target_objects`), which the
      auxiliary loss scores under `loss_config.dyn_aux_on_objects`.
    masks: [B, V, H, W] foreground masks, for `loss_config.lambda_mask` (both renders' alpha).
    flows: [B, V, H, W, 3] the velocity each view's pixel sees (`flow.flow_term`).

  Returns:
    `(loss, terms)`: as `supervision_loss`, plus "dyn_aux" (0 while its weight is 0),
    "dyn_aux_weight", "dyn_aux_psnr" with the auxiliary loss, and "flow" with the flow term.
  """
  world_to_camera, intrinsics = world_to_camera.astype(jnp.float32), intrinsics.astype(jnp.float32)
  views, shared = _chunked_views(
    gaussians_at, times, images, world_to_camera, intrinsics, objective.decode_times
  )
  views.update(_pixel_masks(moving, objects, masks, loss_config, num_static_gaussians))
  views, with_flow = flow.flow_term(
    gaussians_at, views, shared, flows, num_static_gaussians, loss_config, render_config, objective
  )
  scored = functools.partial(
    _score_at_times,
    world_to_camera=world_to_camera,
    intrinsics=intrinsics,
    loss_config=loss_config,
    render_config=render_config,
    objective=objective,
    lpips_params=lpips_params,
    context_images=context_images,
  )

  def chunk_loss(views):
    gaussians = shared if shared is not None else views.get("gaussians")
    if gaussians is None:
      gaussians = gaussians_in_float32(gaussians_at(views["times"], views["world_to_camera"]))
    loss, terms = _scored_with_dynamic_aux(
      scored, gaussians, views, num_static_gaussians, step, loss_config
    )
    return with_flow(loss, terms, gaussians, views)

  return mean_over_view_chunks(chunk_loss, views, objective.view_chunk_size)


def _pixel_masks(moving, objects, foreground, loss_config, num_static_gaussians) -> dict:
  """The per-pixel masks the time-conditioned loss chunks with its views: "moving" (the motion
  term's weights) when `loss_config.lambda_motion > 0`, "objects" (float32) when the dynamic
  auxiliary loss scores the object pixels, "masks" (float32, the foreground) when
  `loss_config.lambda_mask > 0`."""
  masks = {}
  if moving is not None and loss_config.lambda_motion > 0:
    masks["moving"] = moving
  if loss_config.dyn_aux_on_objects and num_static_gaussians is not None:
    if objects is None:
      raise ValueError("dyn_aux_on_objects needs the views' object pixels (`target_objects`)")
    masks["objects"] = objects.astype(jnp.float32)
  if loss_config.lambda_mask > 0:
    if foreground is None:
      raise ValueError("lambda_mask > 0 needs the views' foreground masks (`target_masks`)")
    masks["masks"] = foreground.astype(jnp.float32)
  return masks


def _chunked_views(gaussians_at, times, images, world_to_camera, intrinsics, decode_times):
  """(the views `mean_over_view_chunks` splits, the Gaussians every view shares or None).

  Under `decode_times == "first"` the one decode at the first view's time is shared by every
  view ([B, 1]), or, one set per view ([B, V]: viewer-dependent colours), chunked with them
  under "gaussians"; otherwise each chunk decodes its own.
  """
  views = {
    "world_to_camera": world_to_camera,
    "intrinsics": intrinsics,
    "images": images.astype(jnp.float32),
    "times": jnp.asarray(times, jnp.float32),
  }
  if decode_times != "first":
    return views, None
  shared = gaussians_in_float32(gaussians_at(views["times"][:, :1], world_to_camera))
  if shared.batch_shape[1] > 1:
    return {**views, "gaussians": shared}, None
  return views, shared


def _score_at_times(
  gaussians: Gaussians,
  views: dict,
  *,
  world_to_camera: jax.Array,
  intrinsics: jax.Array,
  loss_config,
  render_config,
  objective: ObjectiveConfig,
  lpips_params,
  context_images,
  auxiliary: bool = False,
):
  """Loss of Gaussians [B, Vc or 1, N] (one set per view time) rendered into a chunk's views.

  views: the chunk's "world_to_camera" [B, Vc, 4, 4], "intrinsics" [B, Vc, 4], "images"
  [B, Vc, H, W, 3] and, for the motion term, "moving" [B, Vc, H, W] (for the auxiliary loss
  on the objects, "objects" [B, Vc, H, W]; for the mask term, "masks" [B, Vc, H, W]); world_to_camera [B, V, 4, 4] / intrinsics
  [B, V, 4]: all the views, which the visibility term projects every time's Gaussians into;
  context_images: the input views [B, Vi, H, W, 3] behind an "input_mean" background, or None;
  auxiliary: a render of part of the Gaussians (the dynamic auxiliary one): no coverage term
  (`add_coverage`), and where the views carry "objects" the terms "objects_rgb" and
  "objects_alpha" that only this render is scored by.
  Returns `(loss, terms, render stats [B, Vc, 1])`.
  """
  from tokengs_jax import losses

  height, width = views["images"].shape[-3], views["images"].shape[-2]
  rendered = render_views(
    gaussians,
    views["world_to_camera"][:, :, None],
    views["intrinsics"][:, :, None],
    height,
    width,
    render_config,
    objective,
    context_images,
  )
  loss, terms = photometric_loss(rendered.rgb[:, :, 0], views["images"], loss_config, lpips_params)
  if "moving" in views:
    terms["motion"] = losses.motion_loss(
      rendered.rgb[:, :, 0], views["images"], views["moving"], loss_config.rgb_loss
    )
    loss = loss + loss_config.lambda_rgb * loss_config.lambda_motion * terms["motion"]
    terms["loss"] = loss
  if auxiliary and "objects" in views:
    objects = views["objects"]
    terms["objects_rgb"] = losses.motion_loss(
      rendered.rgb[:, :, 0], views["images"], objects, loss_config.rgb_loss
    )
    alpha = rendered.alpha[:, :, 0, ..., 0]
    # balanced: the objects are a small share of the pixels, and a mean over all of them is
    # least where the dynamic render is empty everywhere (measured: the Gaussians vanished)
    on_objects = jnp.sum(objects * jnp.square(1.0 - alpha)) / jnp.maximum(jnp.sum(objects), 1.0)
    background = 1.0 - objects
    off_objects = jnp.sum(background * jnp.square(alpha)) / jnp.maximum(jnp.sum(background), 1.0)
    terms["objects_alpha"] = on_objects + off_objects
  # official: the auxiliary loss is the whole loss on its render, the mask term included
  loss, terms = add_mask(loss, terms, rendered.alpha[:, :, 0], views.get("masks"), loss_config)
  if not auxiliary:
    loss, terms = add_coverage(loss, terms, rendered.alpha[:, :, 0], loss_config)
  # the Gaussians of each time against every view: [B, Vc or 1]
  loss, terms = add_visibility(
    loss,
    terms,
    gaussians.means,
    world_to_camera[:, None],
    intrinsics[:, None],
    height,
    width,
    loss_config,
  )
  loss, terms = add_opacity(loss, terms, gaussians.opacities, loss_config)
  return loss, terms, rendered.stats


def _scored_with_dynamic_aux(
  scored: Callable, gaussians: Gaussians, views: dict, num_static_gaussians, step, loss_config
):
  """`scored(gaussians, views)` with `render_diagnostics`, plus the dynamic auxiliary loss.

  The auxiliary loss (`losses.add_dynamic_aux`, and "dyn_aux_psnr") scores the Gaussians
  [B, Vc or 1, num_static_gaussians:] alone (with `loss_config.dyn_aux_on_motion`, on the views'
  moving pixels only; with `dyn_aux_on_objects`, on their object pixels, its alpha against
  them); it is on when `num_static_gaussians` is set and
  `loss_config.lambda_dyn_aux > 0`. Its render only runs while its weight at `step`
  (`losses.dynamic_aux_weight`) is positive: once the schedule has decayed to 0 the second render
  is skipped, as official.
  """
  from tokengs_jax import losses

  loss, terms, stats = scored(gaussians, views)
  terms.update(render_diagnostics(stats))
  if num_static_gaussians is None or not loss_config.lambda_dyn_aux > 0:
    return loss, terms
  _, dynamic = gaussians.static_and_dynamic(num_static_gaussians)

  def dynamic_loss():
    loss, terms, _ = scored(dynamic, views, auxiliary=True)
    if loss_config.dyn_aux_on_motion:
      if "motion" not in terms:
        raise ValueError("dyn_aux_on_motion needs the views' moving pixels (`moving`)")
      # the dynamic Gaussians answer for the moving pixels only; the rest is the static ones'
      loss = loss_config.lambda_rgb * terms["motion"] + loss_config.lambda_vis * terms["visibility"]
    elif loss_config.dyn_aux_on_objects:
      # the objects' colours where the segmentation shows them, and nothing elsewhere
      loss = (
        loss_config.lambda_rgb * terms["objects_rgb"]
        + terms["objects_alpha"]
        + loss_config.lambda_vis * terms["visibility"]
      )
    return loss, terms["psnr"]

  zero = jnp.zeros((), jnp.float32)
  aux_weight = losses.dynamic_aux_weight(step, loss_config)
  dyn_loss, dyn_psnr = jax.lax.cond(aux_weight > 0, dynamic_loss, lambda: (zero, zero))
  loss, terms = losses.add_dynamic_aux(loss, terms, dyn_loss, step, loss_config)
  terms["dyn_aux_psnr"] = dyn_psnr
  return loss, terms


def supervised_views(batch: dict, objective: ObjectiveConfig) -> dict:
  """The batch whose `target_*` views the model losses score: the targets, followed by the input
  views with `objective.use_input_supervision` (official `images_all`, `cam_view_all`, ...) and
  by the input views again with `objective.cross_view_renders` (their other-view renders:
  `cross_view_flags`); otherwise the batch itself.

  Targets first, so that `decode_times="first"` still decodes at the first target's time, as the
  official code does with input supervision; the inputs' true depths are unknown (0).
  """
  repeats = int(objective.use_input_supervision) + int(objective.cross_view_renders)
  if not repeats:
    return batch
  for name in ("target_objects", "target_masks", "target_flows"):
    if name in batch:
      raise ValueError(
        f"the input views carry no per-pixel truth: {name} with input supervision or "
        "cross-view renders"
      )
  views = dict(batch)
  for name in ("images", "c2w", "intrinsics", "times"):
    if f"target_{name}" in batch:
      views[f"target_{name}"] = jnp.concatenate(
        [batch[f"target_{name}"]] + [batch[f"context_{name}"]] * repeats, axis=1
      )
  if "target_depths" in batch:
    depths = batch["target_depths"]
    num_inputs = batch["context_images"].shape[1] * repeats
    unknown = jnp.zeros((depths.shape[0], num_inputs, *depths.shape[2:]), depths.dtype)
    views["target_depths"] = jnp.concatenate([depths, unknown], axis=1)
  return views


def supervision_targets(batch: dict, loss_config) -> tuple[jax.Array, jax.Array | None]:
  """(the target images the loss scores [B, V, H, W, 3], their foreground masks [B, V, H, W] or
  None). Where the batch carries `target_masks` the targets' background is white, as the official
  loss composites a masked target (`losses.composite_on_white`); `loss_config.lambda_mask > 0`
  without them raises ValueError here, before the model runs."""
  from tokengs_jax import losses

  masks = batch.get("target_masks")
  if masks is None:
    if loss_config.lambda_mask > 0:
      raise ValueError("lambda_mask > 0 needs the batch's foreground masks (`target_masks`)")
    return batch["target_images"], None
  return losses.composite_on_white(batch["target_images"], masks), masks


def static_model_loss(
  params,
  batch: dict,
  *,
  model_config,
  loss_config,
  render_config,
  objective: ObjectiveConfig,
  lpips_params=None,
  reconstruct: Callable[..., Gaussians] | None = None,
):
  """Static models: context views -> `reconstruct` -> `supervision_loss` on the targets (and
  the inputs with `objective.use_input_supervision`: `supervised_views`).

  reconstruct: `(params, images [B, V, H, W, 3], c2w [B, V, 4, 4], intrinsics [B, V, 4], *,
    config, viewer_c2w [B, T, 4, 4] or None, own_view [T] bool or None) -> Gaussians` of the
    model (None: `model.reconstruct`); another model with its signature (the pixel-aligned
    baseline) is scored by the same objective.
  """
  from tokengs_jax import model
  from tokengs_jax.camera import invert_rigid

  reconstruct = model.reconstruct if reconstruct is None else reconstruct
  batch = supervised_views(batch, objective)
  images, masks = supervision_targets(batch, loss_config)
  gaussians = reconstruct(
    params,
    batch["context_images"],
    batch["context_c2w"],
    batch["context_intrinsics"],
    config=model_config,
    viewer_c2w=batch["target_c2w"] if model_config.viewer_dependent else None,
    own_view=cross_view_flags(
      objective, model_config, batch["target_c2w"].shape[1], batch["context_c2w"].shape[1]
    ),
  )
  return supervision_loss(
    gaussians,
    images,
    invert_rigid(batch["target_c2w"]),
    batch["target_intrinsics"],
    loss_config,
    render_config,
    objective,
    lpips_params,
    depths=batch.get("target_depths"),
    context_images=batch["context_images"],
    masks=masks,
  )


def dynamic_model_loss(
  params,
  batch: dict,
  step: jax.Array | int,
  *,
  model_config,
  loss_config,
  render_config,
  objective: ObjectiveConfig,
  lpips_params=None,
):
  """Time-conditioned models: context views and `batch["context_times"]` -> `encode_views` once
  -> `model.decode_at_times` at `batch["target_times"]` -> `time_conditioned_loss`, plus the
  dynamic auxiliary loss (weight scheduled by `step`) when the model has static and dynamic tokens
  and `loss_config.lambda_dyn_aux > 0`, as official, and the motion term
  (`loss_config.lambda_motion > 0`: the targets' `losses.moving_pixels`). With
  `objective.use_input_supervision` the input views are scored too (`supervised_views`)."""
  from tokengs_jax import losses, model
  from tokengs_jax.camera import invert_rigid

  if objective.cross_view_renders:
    check_cross_view(model_config)
  batch = supervised_views(batch, objective)
  images, masks = supervision_targets(batch, loss_config)
  with_aux = (
    loss_config.lambda_dyn_aux > 0
    and model_config.num_dynamic_gs_tokens > 0
    and model_config.num_gs_tokens > 0
  )
  encoded = model.encode_views(
    params,
    batch["context_images"],
    batch["context_c2w"],
    batch["context_intrinsics"],
    model_config,
    times=batch["context_times"],
  )
  moving = None
  if loss_config.lambda_motion > 0:
    moving = losses.moving_pixels(
      batch["target_images"].astype(jnp.float32),
      batch["target_c2w"],
      batch["context_images"].astype(jnp.float32),
      batch["context_c2w"],
      loss_config.motion_threshold,
    )
  return time_conditioned_loss(
    lambda times, world_to_camera: model.decode_at_times(
      params, encoded, model_config, times, viewer_c2w=invert_rigid(world_to_camera)
    ),
    batch["target_times"],
    images,
    invert_rigid(batch["target_c2w"]),
    batch["target_intrinsics"],
    loss_config,
    render_config,
    objective,
    lpips_params,
    num_static_gaussians=model_config.num_static_gaussians if with_aux else None,
    step=step,
    context_images=batch["context_images"],
    moving=moving,
    objects=batch.get("target_objects"),
    masks=masks,
    flows=batch.get("target_flows"),
  )


def tokengs_loss_fn(
  model_config,
  loss_config=None,
  render_config=None,
  objective: ObjectiveConfig = ObjectiveConfig(),
  lpips_params=None,
):
  """The TokenGS training loss `(params, batch, key, step) -> (loss, terms)` for `train_step`.

  `static_model_loss`, or `dynamic_model_loss` for time-conditioned models
  (`model_config.time_embedding`). `step` ([] int, the train step passes `state.step`) drives
  the dynamic auxiliary weight's schedule; static models ignore it, as they do the key (the
  network is deterministic; augmentation belongs to the data pipeline).

  Args:
    model_config: `tokengs_jax.model.ModelConfig` (its `dtype` is the network's compute dtype).
    loss_config: `tokengs_jax.losses.LossConfig` (default: official weights).
    render_config: `tokengs_jax.splatting.RenderConfig` (default: its defaults).
    objective: view chunking, background, near/far, decode_times.
    lpips_params: VGG weights when `loss_config.lambda_lpips > 0`.

  Returns:
    The loss function (see `supervision_loss` / `time_conditioned_loss` for the terms).
  """
  from tokengs_jax import losses, splatting

  settings = {
    "model_config": model_config,
    "loss_config": losses.LossConfig() if loss_config is None else loss_config,
    "render_config": splatting.RenderConfig() if render_config is None else render_config,
    "objective": objective,
    "lpips_params": lpips_params,
  }

  def loss_fn(params, batch, key, step):
    del key
    if model_config.time_embedding:
      return dynamic_model_loss(params, batch, step, **settings)
    return static_model_loss(params, batch, **settings)

  return loss_fn
