"""The exact target renders of evaluation: `render_targets` renders Gaussians at cameras as the
training objective supervises them (its background, near / far), to host arrays (`Rendered`).

The single render of evaluation (scores, grids, fly-throughs, studies); `tokengs_jax.evaluation`
re-exports both names.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from tokengs_jax import splatting
from tokengs_jax.camera import invert_rigid
from tokengs_jax.gaussians import Gaussians
from tokengs_jax.objective import ObjectiveConfig, render_settings


@dataclasses.dataclass(frozen=True)
class Rendered:
  """Host arrays of rendered views: rgb [..., V, H, W, 3], depth and alpha [..., V, H, W, 1]."""

  rgb: np.ndarray
  depth: np.ndarray
  alpha: np.ndarray


def render_targets(
  gaussians: Gaussians,
  c2w,
  intrinsics,
  *,
  height: int,
  width: int,
  render_config: splatting.RenderConfig | None = None,
  objective: ObjectiveConfig = ObjectiveConfig(),
  context_images=None,
  compact: bool = False,
) -> Rendered:
  """Renders cameras as training supervises them (the objective's background, near / far, eps2d).

  The single render of evaluation (scores, grids, fly-throughs, studies): exact by construction
  (`splatting.render_exact` re-renders any camera whose intersection budget overflowed).

  Args:
    gaussians: batch shape [B] (seen by every camera) or [B, V] (set v seen by camera v only).
    c2w: [B, V, 4, 4] camera-to-world.
    intrinsics: [B, V, 4] in pixels.
    height, width: image size.
    render_config: renderer settings (default `RenderConfig()`; its eps2d is the objective's).
    objective: background, near / far and eps2d (default: the official grey background).
    context_images: [B, Vi, H, W, 3] the input views, behind an "input_mean" background.
    compact: first move out the Gaussians no camera can draw (`splatting.compaction`; the same
      images, exactly). Off by default: on the shipped defaults it does not pay
      (docs/benchmarks.md, "Skipping what a scene does not need").
  """
  render_config = splatting.RenderConfig() if render_config is None else render_config
  gaussians = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), gaussians)
  world_to_camera = invert_rigid(jnp.asarray(c2w, jnp.float32))
  intrinsics = jnp.asarray(intrinsics, jnp.float32)
  per_view = len(gaussians.batch_shape) == world_to_camera.ndim - 2
  if per_view:  # each set seen by its own camera: a batch [B, V] of single-camera renders
    world_to_camera, intrinsics = world_to_camera[..., None, :, :], intrinsics[..., None, :]
  settings = render_settings(objective, context_images, world_to_camera, render_config)
  if compact:
    gaussians = splatting.compaction.compact_for_cameras(
      gaussians,
      world_to_camera,
      intrinsics,
      height=height,
      width=width,
      near=settings["near"],
      far=settings["far"],
      config=settings["config"],
    )
  result = splatting.render_exact(
    gaussians, world_to_camera, intrinsics, height=height, width=width, **settings
  )
  views = [np.asarray(x) for x in (result.rgb, result.depth, result.alpha)]
  if per_view:
    views = [x[..., 0, :, :, :] for x in views]
  return Rendered(*views)
