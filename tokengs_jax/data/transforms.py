"""Per-example transforms on numpy arrays (they run in the input workers, so no JAX here).

Camera conventions as `tokengs_jax.camera`: OpenCV axes, `c2w [..., 4, 4]`, intrinsics
(fx, fy, cx, cy) in pixels with pixel (i, j) centred at (j + 0.5, i + 0.5). Every transform keeps
the projection of a world point consistent with the image it returns.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from PIL import Image

__all__ = [
  "rigid_inverse",
  "resize_and_center_crop",
  "resize_and_center_crop_depth",
  "resize_and_center_crop_mask",
  "flip_horizontal",
  "normalize_cameras",
  "translation_scale",
  "normalize_times",
]

_REFLECT_X = np.diag([-1.0, 1.0, 1.0, 1.0])


def rigid_inverse(pose: np.ndarray) -> np.ndarray:
  """Inverse of rigid transforms, computed in float64.  pose: [..., 4, 4] -> [..., 4, 4].

  The numpy twin of `tokengs_jax.camera.invert_rigid`, kept because it runs on the host inside
  the grain input workers: those must not import or dispatch to JAX (a forked process must not
  touch the parent's JAX runtime, and a per-example 4x4 op would pay dispatch costs), and the
  camera normalisation wants float64 while JAX runs in float32 unless x64 is enabled globally.
  """
  pose = np.asarray(pose, np.float64)
  rot_t = np.swapaxes(pose[..., :3, :3], -1, -2)
  inverse = np.zeros_like(pose)
  inverse[..., :3, :3] = rot_t
  inverse[..., :3, 3] = -np.einsum("...ij,...j->...i", rot_t, pose[..., :3, 3])
  inverse[..., 3, 3] = 1.0
  return inverse


def resize_and_center_crop(
  images: np.ndarray, intrinsics: np.ndarray, shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
  """pixelSplat's crop shim: scale so the image covers `shape`, then crop the centre.

  The scale is the larger of h_out/H and w_out/W; the scaled size is rounded, and the intrinsics
  use the exact per-axis factor of that rounded size and the crop offset (pixelSplat keeps
  normalised intrinsics and ignores both, which is exact only for a centred principal point).

  images: uint8 [V, H, W, 3], intrinsics: [V, 4] pixels -> (uint8 [V, h_out, w_out, 3], [V, 4]).
  """
  height, width = images.shape[1:3]
  images, (h_scaled, w_scaled), (row, col) = _scale_and_crop(images, shape, Image.LANCZOS)
  factor_x, factor_y = w_scaled / width, h_scaled / height
  intrinsics = np.asarray(intrinsics, np.float64) * np.array(
    [factor_x, factor_y, factor_x, factor_y]
  )
  intrinsics = intrinsics - np.array([0.0, 0.0, col, row])
  return np.ascontiguousarray(images), intrinsics.astype(np.float32)


def _scale_and_crop(stack: np.ndarray, shape: tuple[int, int], resample):
  """The geometry of `resize_and_center_crop` on a stack of PIL-readable images [V, H, W(, C)].

  -> (the cropped stack, the scaled size (h, w), the crop offset (row, col)).
  """
  height, width = stack.shape[1:3]
  h_out, w_out = shape
  scale = max(h_out / height, w_out / width)
  h_scaled, w_scaled = max(h_out, round(height * scale)), max(w_out, round(width * scale))
  if (h_scaled, w_scaled) != (height, width):
    stack = np.stack(
      [np.asarray(Image.fromarray(image).resize((w_scaled, h_scaled), resample)) for image in stack]
    )
  row, col = (h_scaled - h_out) // 2, (w_scaled - w_out) // 2
  return stack[:, row : row + h_out, col : col + w_out], (h_scaled, w_scaled), (row, col)


def resize_and_center_crop_depth(depths: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
  """Depth maps through the same scale and crop as `resize_and_center_crop` gives the images.

  Bilinear, so a pixel on a depth edge gets a blend of both sides (as its colour does); a 0
  ("nothing hit") blended with a surface is marked 0 again, so invalid stays invalid.

  depths: [V, H, W] -> float32 [V, h_out, w_out].
  """
  depths = np.asarray(depths, np.float32)
  valid = (depths > 0).astype(np.float32)
  scaled, _, _ = _scale_and_crop(depths, shape, Image.BILINEAR)
  coverage, _, _ = _scale_and_crop(valid, shape, Image.BILINEAR)
  return np.where(coverage > 0.999, scaled, 0.0).astype(np.float32)


def resize_and_center_crop_values(values: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
  """Per-pixel quantities (any sign) through the same scale and crop as `resize_and_center_crop`
  gives the images, bilinear.  values: [V, H, W] -> float32 [V, h_out, w_out]."""
  scaled, _, _ = _scale_and_crop(np.asarray(values, np.float32), shape, Image.BILINEAR)
  return scaled.astype(np.float32)


def resize_and_center_crop_mask(masks: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
  """Boolean masks through the same scale and crop as `resize_and_center_crop` gives the images:
  an output pixel is set where the bilinear resize of the mask (antialiased when shrinking) is at
  least 1/2.

  masks: bool [V, H, W] -> bool [V, h_out, w_out].
  """
  scaled, _, _ = _scale_and_crop(np.asarray(masks, np.float32), shape, Image.BILINEAR)
  return scaled >= 0.5


def flip_horizontal(images: np.ndarray, c2w: np.ndarray, intrinsics: np.ndarray):
  """Mirror images left-right and the world in x, so every projection stays consistent.

  The world and camera x axes are both negated (c2w -> R c2w R, R = diag(-1, 1, 1, 1), as
  pixelSplat's augmentation) and cx -> W - cx: a world point (x, y, z) seen at pixel (u, v)
  becomes (-x, y, z) seen at (W - u, v).

  images: [..., V, H, W, C], c2w: [..., V, 4, 4], intrinsics: [..., V, 4]
  -> the same shapes.
  """
  width = images.shape[-2]
  flipped = np.ascontiguousarray(images[..., ::-1, :])
  c2w = (_REFLECT_X @ np.asarray(c2w, np.float64) @ _REFLECT_X).astype(np.float32)
  intrinsics = np.array(intrinsics, np.float32)
  intrinsics[..., 2] = width - intrinsics[..., 2]
  return flipped, c2w, intrinsics


def _mean_camera(c2w: np.ndarray) -> np.ndarray:
  """Average pose of c2w [V, 4, 4] as official `mean_cam`: mean position, Gram-Schmidt of the mean
  forward (z) and down (y) axes, right = down x forward. -> [4, 4]."""
  forward = c2w[:, :3, 2].mean(0)
  forward = forward / np.linalg.norm(forward)
  down = c2w[:, :3, 1].mean(0)
  down = down - down.dot(forward) * forward
  down = down / np.linalg.norm(down)
  mean = np.eye(4)
  mean[:3, 0] = np.cross(down, forward)
  mean[:3, 1] = down
  mean[:3, 2] = forward
  mean[:3, 3] = c2w[:, :3, 3].mean(0)
  return mean


def normalize_cameras(
  c2w: np.ndarray, num_context: int, method: Literal["first_cam", "mean_cam"] = "first_cam"
) -> np.ndarray:
  """Expresses all cameras relative to a reference built from the first `num_context` views.

  `first_cam`: the first context camera becomes the identity; `mean_cam`: the average context
  camera does (official TokenGS `_normalize_camera_mean_cam`).

  c2w: [V, 4, 4] with the context views first -> [V, 4, 4] float32.
  """
  c2w = np.asarray(c2w, np.float64)
  if method == "first_cam":
    reference = c2w[0]
  elif method == "mean_cam":
    reference = _mean_camera(c2w[:num_context])
  else:
    raise ValueError(f"unknown camera normalisation {method!r}")
  return (rigid_inverse(reference) @ c2w).astype(np.float32)


def translation_scale(
  c2w: np.ndarray,
  num_context: int,
  base_scale: float,
  method: Literal["constant", "distance", "bound"] = "constant",
) -> float:
  """Factor for the camera translations, as official `camera_scale_method`.

  `constant`: `base_scale` (RE10K 0.25, DL3DV 0.15, Kubric 0.1, making mean depth about 1);
  `distance`: `base_scale` / the largest context-camera distance to the first camera;
  `bound`: `base_scale` / the largest absolute context-camera coordinate.
  c2w: [V, 4, 4], already normalised.
  """
  positions = np.asarray(c2w, np.float64)[:num_context, :3, 3]
  if method == "constant":
    return float(base_scale)
  if method == "distance":
    return float(base_scale / max(np.linalg.norm(positions - positions[:1], axis=-1).max(), 1e-6))
  if method == "bound":
    return float(base_scale / max(np.abs(positions).max(), 1e-6))
  raise ValueError(f"unknown camera scale method {method!r}")


def normalize_times(times: np.ndarray) -> np.ndarray:
  """An example's frame times min-max normalised to [0, 1] (official TokenGS).

  All times equal (an example from one instant, e.g. a static or single-frame clip): all 0, not
  the official 0 / 0 = NaN.  times: [V] -> [V] float32.
  """
  times = np.asarray(times, np.float64)
  span = times.max() - times.min()
  return ((times - times.min()) / span if span > 0 else np.zeros_like(times)).astype(np.float32)
