"""Trace-time checks of the views a TokenGS entry point is given (shapes, dtypes, cameras).

Shapes and dtypes are static under `jax.jit`, so these checks run once per trace and cost nothing
at run time. Values are checked only where they are concrete (a call outside `jit`, read on the
host): images, poses and intrinsics must be finite (one NaN pixel would make every Gaussian NaN)
and focal lengths positive. Traced values (under jit, vmap, grad) do not exist yet and are not
checked. uint8 images are accepted and scaled by `normalize_images` (which checks that float
images are in [0, 1] where concrete).

Shape errors are `ValueError`, dtype errors `TypeError`; every message names the argument, the
expected layout and what was given.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from tokengs_jax.camera import check_camera_values
from tokengs_jax.model.configs import ModelConfig


def _shape_error(name: str, expected: str, array) -> ValueError:
  return ValueError(f"{name} must be {expected}, got shape {tuple(np.shape(array))}")


def _check_floating(name: str, array) -> None:
  if not jnp.issubdtype(jnp.result_type(array), jnp.floating):
    raise TypeError(f"{name} must be floating point, got {jnp.result_type(array)}")


def check_times(name: str, times, expected: tuple[int | None, ...], layout: str) -> None:
  """times: float of shape `expected` (None: any size on that axis); `layout` names the axes."""
  shape = np.shape(times)
  if len(shape) != len(expected) or any(
    e is not None and n != e for n, e in zip(shape, expected, strict=True)
  ):
    raise _shape_error(name, f"{layout} = {expected}", times)
  _check_floating(name, times)


def _check_finite_images(images) -> None:
  """images [B, V, H, W, 3]: a NaN / inf in a concrete float image names its view."""
  if isinstance(images, jax.core.Tracer) or jnp.result_type(images) == jnp.uint8:
    return
  bad = ~np.all(np.isfinite(np.asarray(images)), axis=(2, 3, 4))  # [B, V]
  if np.any(bad):
    view = np.argwhere(bad)[0].tolist()
    raise ValueError(f"images of view {view} (index into [B, V]) are not finite (NaN or inf)")


def check_views(images, c2w, intrinsics, config: ModelConfig, times=None) -> None:
  """Raises if the views cannot be encoded by a network of this config.

  Args:
    images: [B, V, H, W, 3] RGB, float in [0, 1] or uint8; H, W divisible by the patch size.
    c2w: [B, V, 4, 4] float camera-to-world.
    intrinsics: [B, V, 4] float fx, fy, cx, cy in pixels.
    config: the architecture.
    times: [B, V] input-view times (required iff `config.time_embedding`).

  Raises:
    ValueError: a shape, a missing/unexpected `times`, or, where concrete, a NaN / inf in the
      images, c2w or intrinsics or a non-positive focal length (naming the view [b, v]).
    TypeError: a dtype.
  """
  if np.ndim(images) != 5 or np.shape(images)[-1] != 3:
    raise _shape_error("images", "[B, V, H, W, 3]", images)
  batch, views, height, width, _ = np.shape(images)
  dtype = jnp.result_type(images)
  if dtype != jnp.uint8 and not jnp.issubdtype(dtype, jnp.floating):
    raise TypeError(f"images must be floating point in [0, 1] or uint8, got {dtype}")
  p = config.patch_size
  if height % p or width % p:
    raise ValueError(f"image size {height}x{width} must be divisible by the patch size {p}")
  if np.shape(c2w) != (batch, views, 4, 4):
    raise _shape_error("c2w", f"[B, V, 4, 4] = {(batch, views, 4, 4)}", c2w)
  _check_floating("c2w", c2w)
  if np.shape(intrinsics) != (batch, views, 4):
    raise _shape_error(
      "intrinsics", f"[B, V, 4] = {(batch, views, 4)} (fx, fy, cx, cy)", intrinsics
    )
  _check_floating("intrinsics", intrinsics)
  _check_finite_images(images)
  check_camera_values(c2w, intrinsics, pose_name="c2w", camera="view", layout="[B, V]")
  if config.time_embedding:
    if times is None:
      raise ValueError("this model has time embeddings: pass the input-view times [B, V]")
    check_times("times", times, (batch, views), "[B, V]")
  elif times is not None:
    raise ValueError("times given for a model without time embedding")
