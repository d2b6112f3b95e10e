"""Training objectives: the memory-lean mean over target views, and the TokenGS loss.

`mean_over_view_chunks` is the JAX form of the official "deferred back-propagation": the views are
processed `chunk_size` at a time in a `lax.scan` whose body is rematerialised, so the backward pass
recomputes one chunk's render at a time and peak memory holds one chunk's intermediates instead
of every view's. The gradient is that of the one-shot mean (up to float summation order).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp


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


@dataclasses.dataclass(frozen=True)
class ObjectiveConfig:
  """How the TokenGS objective renders its supervision views.

  Attributes:
    view_chunk_size: target views rendered (and differentiated) together; None: all at once.
    background: RGB behind the Gaussians (official `bg_color` default "grey" = 0.5).
    near, far: renderer depth culling (official znear / zfar).
  """

  view_chunk_size: int | None = None
  background: tuple[float, float, float] = (0.5, 0.5, 0.5)
  near: float = 0.025
  far: float = 125.0


def supervision_loss(gaussians, images, world_to_camera, intrinsics, loss_config, render_config,
                     objective: ObjectiveConfig = ObjectiveConfig(), lpips_params=None):
  """Loss of Gaussians against supervision views (training targets, or the inputs when tuning).

  The views are rendered in chunks of `objective.view_chunk_size` under remat and scored with
  `losses.render_loss` (RGB, SSIM, LPIPS terms) averaged over chunks; the visibility loss is taken
  over all views at once (its minimum over views does not split into chunks; it only projects
  centres, so it is cheap). Equals `losses.render_loss` on the one-shot render.

  Args:
    gaussians: `Gaussians` with batch shape [B] (rendered in float32).
    images: [B, V, H, W, 3] supervision images in [0, 1].
    world_to_camera: [B, V, 4, 4].
    intrinsics: [B, V, 4] in pixels.
    loss_config: `losses.LossConfig`.
    render_config: `splatting.RenderConfig`.
    objective: view chunking, background, near/far.
    lpips_params: VGG weights when `loss_config.lambda_lpips > 0`.

  Returns:
    `(loss, terms)`: the loss terms, "psnr", and render diagnostics ("render_overflow": fraction
    of renders whose tile budget overflowed, "visible": mean number of Gaussians drawn per view).
  """
  from tokengs_jax import losses, splatting  # the heavy areas only when this objective is used

  gaussians = jax.tree.map(lambda x: x.astype(jnp.float32), gaussians)
  height, width = images.shape[-3], images.shape[-2]
  world_to_camera = world_to_camera.astype(jnp.float32)
  intrinsics = intrinsics.astype(jnp.float32)
  photometric = dataclasses.replace(loss_config, lambda_vis=0.0)

  def chunk_loss(views):
    rendered = splatting.render(
        gaussians, views["world_to_camera"], views["intrinsics"], height=height, width=width,
        background=jnp.asarray(objective.background, jnp.float32), near=objective.near,
        far=objective.far, config=render_config)
    loss, terms = losses.render_loss(rendered.rgb, views["images"], photometric,
                                     lpips_params=lpips_params)
    terms["render_overflow"] = jnp.mean(rendered.stats.overflow.astype(jnp.float32))
    terms["visible"] = jnp.mean(rendered.stats.num_visible.astype(jnp.float32))
    return loss, terms

  loss, terms = mean_over_view_chunks(
      chunk_loss, {"world_to_camera": world_to_camera, "intrinsics": intrinsics,
                   "images": images.astype(jnp.float32)}, objective.view_chunk_size)
  if loss_config.lambda_vis > 0:
    terms["visibility"] = jnp.mean(losses.visibility_loss(
        gaussians.means, world_to_camera, intrinsics, height, width,
        threshold=loss_config.visibility_threshold, near=loss_config.near))
    loss = loss + loss_config.lambda_vis * terms["visibility"]
    terms["loss"] = loss
  return loss, terms


def tokengs_loss_fn(model_config, loss_config=None, render_config=None,
                    objective: ObjectiveConfig = ObjectiveConfig(), lpips_params=None):
  """The TokenGS training loss `(params, batch, key) -> (loss, terms)` for `train_step`.

  context views -> `model.reconstruct` -> Gaussians -> `supervision_loss` on the target views.

  Args:
    model_config: `tokengs_jax.model.ModelConfig` (its `dtype` is the network's compute dtype).
    loss_config: `tokengs_jax.losses.LossConfig` (default: official weights).
    render_config: `tokengs_jax.splatting.RenderConfig` (default: its defaults).
    objective: view chunking, background, near/far.
    lpips_params: VGG weights when `loss_config.lambda_lpips > 0`.

  Returns:
    The loss function (see `supervision_loss` for the terms).
  """
  from tokengs_jax import losses, model, splatting
  from tokengs_jax.camera import invert_rigid

  loss_config = losses.LossConfig() if loss_config is None else loss_config
  render_config = splatting.RenderConfig() if render_config is None else render_config
  if model_config.time_embedding:
    raise ValueError("tokengs_loss_fn covers static models; dynamic (time-conditioned) training "
                     "needs one decode per target time and is not implemented")

  def loss_fn(params, batch, key):
    del key  # the network is deterministic; augmentation belongs to the data pipeline
    gaussians = model.reconstruct(params, batch["context_images"], batch["context_c2w"],
                                  batch["context_intrinsics"], config=model_config)
    return supervision_loss(gaussians, batch["target_images"], invert_rigid(batch["target_c2w"]),
                            batch["target_intrinsics"], loss_config, render_config, objective,
                            lpips_params)

  return loss_fn
