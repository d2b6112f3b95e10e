"""How the objective renders: its settings (`ObjectiveConfig`) and the background behind every
render (`background_colours`), handed to the renderer as `render_settings`.

Training, tuning and evaluation read the same settings, so that a model is scored over the
background, near / far and low-pass filter it was supervised with.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np


@dataclasses.dataclass(frozen=True)
class ObjectiveConfig:
  """How the TokenGS objective renders its supervision views.

  Attributes:
    view_chunk_size: target views rendered (and differentiated) together; None: all at once.
      Time-conditioned models also decode per chunk, so this bounds the decoder's memory too.
    background: what is composited behind the Gaussians in every render of the objective
      (`background_colours`): an RGB (official `bg_color` default "grey" = 0.5), or
      "input_mean": each example's mean colour of its input (context) views, so that what no
      input view saw renders as the scene's average colour instead of a grey it may not have.
    near, far: renderer depth culling (official znear / zfar).
    decode_times: time-conditioned models only. "per_view": decode the Gaussians at every target
      view's own time; "first": decode once, at the first target view's time, and render every
      target view from it (the official `split_data` reads the target time from that one view;
      identical results, one decode instead of V, when all target views share a time, as the
      Kubric sampler's do).
    use_input_supervision: the model losses (`static_model_loss`, `dynamic_model_loss`) score
      the input views too, as further supervision views after the targets (official
      `use_input_supervision`, off by default; `model_loss.supervised_views`). Tuning, which
      supervises the input views anyway, and evaluation, which scores the targets, ignore it.
    cross_view_renders: static models whose colours are read from the input views with viewer
      weights (`ModelConfig.viewer_dependent`): each input view is also rendered with every
      Gaussian's colour read from the other views only (`own_view` False for that camera,
      `cross_view_flags`) and scored as one more supervision view, in training and token
      tuning. Such a render matches its view only where the Gaussians sit where the views
      agree, so it checks the geometry, which a render of the view's own colours, copied back
      pixel for pixel, hardly does (not in the paper; docs/generalisation.md, "Issue 23
      (session 28)"). The same decode colours both renders; each input view costs one more
      colour read and render. Evaluation, which scores the targets, ignores it.
    eps2d: the screen-space low-pass added to every splat's 2D covariance in the objective's
      renders; it replaces the `RenderConfig.eps2d` they are given (`render_settings`), so
      weights trained with a filter are tuned and scored with it. 0.3: gsplat's default, which
      the official weights were trained with.
  """

  view_chunk_size: int | None = None
  background: tuple[float, float, float] | Literal["input_mean"] = (0.5, 0.5, 0.5)
  near: float = 0.025
  far: float = 125.0
  decode_times: Literal["per_view", "first"] = "per_view"
  use_input_supervision: bool = False
  cross_view_renders: bool = False
  eps2d: float = 0.3

  def __post_init__(self):
    if not (math.isfinite(self.eps2d) and self.eps2d >= 0):
      raise ValueError(f"eps2d must be finite and >= 0, got {self.eps2d!r}")
    if self.decode_times not in ("per_view", "first"):
      raise ValueError(f"decode_times must be 'per_view' or 'first', got {self.decode_times!r}")
    rgb = not isinstance(self.background, str) and len(self.background) == 3
    if not (rgb or self.background == "input_mean"):
      raise ValueError(f"background must be an RGB or 'input_mean', got {self.background!r}")


def check_cross_view(model_config) -> None:
  """Refuses (ValueError) a model for the cross-view renders (`ObjectiveConfig.cross_view_renders`)
  that is time-conditioned (its input views would need the other views' colours at their own
  times) or whose colours do not depend on the camera (its renders of an input view would not
  change)."""
  if model_config.time_embedding:
    raise ValueError("cross_view_renders is for static models; this one is time-conditioned")
  if not model_config.viewer_dependent:
    raise ValueError(
      "cross_view_renders needs colours read from the input views with viewer weights "
      '(gaussian_colours="inputs", input_colour_weights="viewer")'
    )


def cross_view_flags(
  objective: ObjectiveConfig, model_config, num_views: int, num_inputs: int
) -> np.ndarray | None:
  """`model.reconstruct`'s `own_view` [num_views] for views whose last `num_inputs` are the input
  views rendered again (`model_loss.supervised_views`; tuning's inputs, then the inputs again):
  under `objective.cross_view_renders` False there, so a camera at an input view's centre takes
  its colours from the other views only (`check_cross_view` first); None without them."""
  if not objective.cross_view_renders:
    return None
  check_cross_view(model_config)
  return np.arange(num_views) < num_views - num_inputs


def background_colours(objective: ObjectiveConfig, context_images, world_to_camera) -> jax.Array:
  """What is composited behind the Gaussians in renders into views `world_to_camera`
  [B, ..., V, 4, 4] (`splatting.render`'s background).

  A fixed `objective.background`: that RGB [3]. "input_mean": the mean colour of each example's
  context views `context_images` [B, Vi, H, W, 3], as [B, 1, ..., 1, 3] (one colour behind every
  view of the example, whatever the view axes).
  """
  if objective.background != "input_mean":
    return jnp.asarray(objective.background, jnp.float32)
  if context_images is None:
    raise ValueError("the 'input_mean' background needs the context images")
  mean = jnp.mean(jnp.asarray(context_images, jnp.float32), axis=(1, 2, 3))  # [B, 3]
  return mean.reshape(mean.shape[:1] + (1,) * (jnp.ndim(world_to_camera) - 3) + (3,))


def render_settings(
  objective: ObjectiveConfig, context_images, world_to_camera, render_config
) -> dict:
  """The keyword arguments of `splatting.render` / `render_exact` that `objective` decides for
  renders into views `world_to_camera` [B, ..., V, 4, 4]: `background` (`background_colours`),
  the `near` / `far` culling and `config`: `render_config` (a `splatting.RenderConfig`) with the
  objective's `eps2d`. Training, tuning and evaluation all render through it, so a run is scored
  with the render settings it was trained with."""
  return dict(
    background=background_colours(objective, context_images, world_to_camera),
    near=objective.near,
    far=objective.far,
    config=dataclasses.replace(render_config, eps2d=objective.eps2d),
  )
