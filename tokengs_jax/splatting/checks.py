"""Checks of `render`'s arguments and results: shapes at trace time, values where concrete.

Shapes, dtypes and sizes are static, so `check_shapes` runs once per trace and costs nothing at
run time. Values exist only outside jit: there `check_cameras` refuses cameras that cannot render
and `warn_if_overflowed` reports a cut buffer; under a transformation both are skipped (training
reads `stats.overflow` itself, and reading values there would stall every step on the host).
"""

from __future__ import annotations

import numbers
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from tokengs_jax.camera import check_camera_values
from tokengs_jax.gaussians import Gaussians


class RenderBudgetWarning(UserWarning):
  """A render outside jit whose (Gaussian, tile) buffer overflowed: some pixels are wrong."""


def check_cameras(world_to_camera, intrinsics) -> None:
  """Raises ValueError, naming the field and camera, for a concrete world_to_camera [..., V, 4, 4]
  or intrinsics [..., V, 4] with a NaN / inf or fx, fy <= 0 (traced ones are not read)."""
  check_camera_values(
    world_to_camera,
    intrinsics,
    pose_name="world_to_camera",
    camera="camera",
    layout="[..., V]",
    prefix="render: ",
  )


def warn_if_overflowed(stats) -> None:
  """Warns (RenderBudgetWarning) where a concrete render's buffer overflowed (`stats.overflow`).

  Reading the flag waits for the render: the call that asked for it is outside jit, and its
  images are about to be read anyway. A traced result (under jit, vmap, grad) is not read.
  """
  if isinstance(stats.overflow, jax.core.Tracer):
    return
  overflow = np.asarray(stats.overflow)
  if not np.any(overflow):
    return
  needed = int(np.max(np.asarray(stats.num_intersections)))
  warnings.warn(
    f"render: the (Gaussian, tile) buffer overflowed in {int(overflow.sum())} of "
    f"{overflow.size} camera(s): their images are wrong where the farthest Gaussians were cut "
    f"(needed up to {needed} pairs, buffer {int(np.max(np.asarray(stats.budget)))}). Call "
    "splatting.render_exact for exact images, or raise RenderConfig.max_intersections "
    f"(splatting.larger_budget(config, N, height, width, needed={needed})).",
    RenderBudgetWarning,
    stacklevel=3,
  )


def _positive_int(name: str, value) -> None:
  if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value <= 0:
    raise ValueError(f"render: {name} must be a positive int, got {value!r}")


def check_shapes(
  gaussians: Gaussians, world_to_camera, intrinsics, background, height, width
) -> tuple[int, ...]:
  """Trace-time checks of `render`'s arguments; returns the broadcast batch shape [...].

  Intrinsics are (fx, fy, cx, cy) rows [..., V, 4]: a 3x3 K is refused here by its shape; a 4x4
  K has the shape of four views' rows and is refused by `check_cameras` where concrete.
  """
  _positive_int("height", height)
  _positive_int("width", width)
  scene_batch = gaussians.validate()
  w2c_shape, intr_shape = jnp.shape(world_to_camera), jnp.shape(intrinsics)
  for name, value in (("world_to_camera", world_to_camera), ("intrinsics", intrinsics)):
    dtype = jnp.result_type(value)
    if not (jnp.issubdtype(dtype, jnp.floating) or jnp.issubdtype(dtype, jnp.integer)):
      raise ValueError(f"render: {name} must be real numbers, got dtype {dtype}")
  if len(w2c_shape) < 3 or w2c_shape[-2:] != (4, 4):
    hint = " (one pose needs a view axis: world_to_camera[None])" if w2c_shape == (4, 4) else ""
    raise ValueError(f"render: world_to_camera must be [..., V, 4, 4], got shape {w2c_shape}{hint}")
  if len(intr_shape) < 2 or intr_shape[-1] != 4:
    hint = (
      " (a 3x3 K matrix? convert it with camera.intrinsics_from_matrix)"
      if intr_shape[-2:] == (3, 3)
      else ""
    )
    raise ValueError(
      f"render: intrinsics must be [..., V, 4] (fx, fy, cx, cy), got shape {intr_shape}{hint}"
    )
  if intr_shape[-2] != w2c_shape[-3]:
    raise ValueError(
      f"render: intrinsics {intr_shape} and world_to_camera {w2c_shape} disagree "
      f"on the number of views V"
    )
  try:
    batch = jnp.broadcast_shapes(scene_batch, w2c_shape[:-3], intr_shape[:-2])
  except ValueError:
    raise ValueError(
      f"render: batch shapes do not broadcast: gaussians {scene_batch}, "
      f"world_to_camera {w2c_shape[:-3]}, intrinsics {intr_shape[:-2]}"
    ) from None
  if background is not None:
    bg_shape = jnp.shape(background)
    try:
      if bg_shape[-1:] != (3,):
        raise ValueError
      jnp.broadcast_shapes(bg_shape, batch + (w2c_shape[-3], 3))
    except ValueError:
      raise ValueError(
        f"render: background must be None, [3] or [..., V, 3] for batch {batch} "
        f"and V = {w2c_shape[-3]}, got shape {bg_shape}"
      ) from None
  return batch
