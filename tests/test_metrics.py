"""Evaluation metrics against skimage, the `lpips` package's numbers and hand values."""

import pathlib
import pickle

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from skimage.metrics import structural_similarity

from tokengs_jax import lpips as lpips_lib
from tokengs_jax import metrics

DATA = pathlib.Path(__file__).parent / "data"


def _skimage_ssim(pred, target):
  return structural_similarity(
    pred,
    target,
    win_size=11,
    gaussian_weights=True,
    sigma=1.5,
    use_sample_covariance=True,
    data_range=1.0,
    channel_axis=-1,
  )


@pytest.mark.parametrize("shape", [(24, 31, 3), (11, 11, 3), (40, 17, 3)])
def test_ssim_matches_skimage(shape):
  rng = np.random.default_rng(sum(shape))
  target = rng.uniform(0, 1, shape).astype(np.float32)
  # A correlated prediction (SSIM well away from 0) and one with values outside [0, 1].
  preds = [
    np.clip(target + rng.normal(0, 0.1, shape), 0, 1).astype(np.float32),
    (target * 1.3 - 0.1).astype(np.float32),
  ]
  for pred in preds:
    np.testing.assert_allclose(metrics.ssim(pred, target), _skimage_ssim(pred, target), atol=1e-5)


def test_ssim_constant_and_identical_images():
  flat_a = np.full((16, 16, 3), 0.3, np.float32)
  flat_b = np.full((16, 16, 3), 0.7, np.float32)
  np.testing.assert_allclose(metrics.ssim(flat_a, flat_b), _skimage_ssim(flat_a, flat_b), atol=1e-5)
  np.testing.assert_allclose(metrics.ssim(flat_b, flat_b), 1.0, atol=1e-6)


def test_ssim_batches_and_jits():
  rng = np.random.default_rng(3)
  pred = rng.uniform(0, 1, (2, 3, 20, 22, 3)).astype(np.float32)
  target = rng.uniform(0, 1, (2, 3, 20, 22, 3)).astype(np.float32)
  batched = jax.jit(metrics.ssim)(pred, target)
  assert batched.shape == (2, 3)
  expected = [[_skimage_ssim(pred[i, j], target[i, j]) for j in range(3)] for i in range(2)]
  np.testing.assert_allclose(batched, expected, atol=1e-5)


def test_ssim_rejects_images_smaller_than_the_window():
  with pytest.raises(ValueError, match="11x11"):
    metrics.ssim(np.zeros((10, 20, 3)), np.zeros((10, 20, 3)))


def test_psnr_hand_values_clipping_and_cap():
  target = np.full((2, 8, 8, 3), 0.5, np.float32)
  pred = target + np.array([0.1, -0.01], np.float32)[:, None, None, None]
  np.testing.assert_allclose(jax.jit(metrics.psnr)(pred, target), [20.0, 40.0], rtol=1e-4)
  # Values beyond [0, 1] are clipped first: 1.7 vs 1.0 are the same pixel.
  over = np.full((8, 8, 3), 1.7, np.float32)
  white = np.ones((8, 8, 3), np.float32)
  np.testing.assert_allclose(metrics.psnr(over, white), metrics.PSNR_CAP_DB)
  # Identical images give the documented cap, not inf.
  assert float(metrics.psnr(target[0], target[0])) == pytest.approx(metrics.PSNR_CAP_DB)


def test_lpips_matches_reference_package_numbers():
  ref = np.load(DATA / "lpips_reference.npz")
  pred = ref["pred"].astype(np.float32) / 255.0
  target = ref["target"].astype(np.float32) / 255.0
  np.testing.assert_allclose(metrics.lpips(pred, target), ref["lpips"], atol=1e-5)
  assert ref["lpips"][1] == 0.0  # the identical pair
  # Leading dimensions are kept, also under an outer jit (shape only: no second compile).
  grid = jax.eval_shape(
    jax.jit(metrics.lpips),
    pred[:4].reshape(2, 2, *pred.shape[1:]),
    target[:4].reshape(2, 2, *pred.shape[1:]),
  )
  assert grid.shape == (2, 2)


def test_lpips_gradient_is_finite_for_flat_and_identical_images():
  params = lpips_lib.load_vgg_params()
  # Black images make whole VGG feature maps zero: the channel norm's sqrt must not give NaN.
  pred = jnp.zeros((2, 16, 16, 3))
  target = jnp.stack([jnp.zeros((16, 16, 3)), jnp.full((16, 16, 3), 0.5)])
  loss = lambda weights, p: jnp.sum(lpips_lib.lpips_distance(weights, p, target))
  grad = jax.jit(jax.grad(loss, argnums=1))(params, pred)  # weights as an argument: fast compile
  assert np.isfinite(np.asarray(grad)).all()


def test_weights_loader_refuses_foreign_pickles(tmp_path, monkeypatch):
  path = tmp_path / "evil.ckpt"
  path.write_bytes(pickle.dumps({"VGG16_0": print}))  # any non-numpy global must be refused
  with pytest.raises(pickle.UnpicklingError, match="refusing"):
    lpips_lib.load_vgg_params(str(path))
  monkeypatch.setenv(lpips_lib.WEIGHTS_ENV, str(path))
  assert lpips_lib.default_weights_path() == path


def test_mean_over_scenes_averages_scenes_equally():
  # Scene 0 has 3 targets, scene 1 has 1: per-scene means 2 and 10, overall 6 (not 4).
  assert metrics.mean_over_scenes([np.array([1.0, 2.0, 3.0]), np.array([10.0])]) == 6.0
  with pytest.raises(ValueError):
    metrics.mean_over_scenes([])


def test_holes_count_pixels_the_render_leaves_uncovered():
  alpha = np.ones((2, 4, 4, 1))
  alpha[0, :2] = 0.49  # half the first view shows the background
  alpha[1, 0, 0] = 0.5  # exactly the threshold counts as covered
  np.testing.assert_allclose(metrics.holes(alpha), [0.5, 0.0])


def test_depth_errors_absrel_and_delta_over_known_pixels():
  truth = np.full((1, 2, 2), 2.0)
  truth[0, 1, 1] = 0.0  # unknown: not scored
  depth = np.array([[[2.0], [2.4]], [[1.0], [99.0]]])[None]  # exact, +20%, half, (unknown)
  scores = metrics.depth_errors(depth, truth)
  np.testing.assert_allclose(scores["depth_absrel"], [(0.0 + 0.2 + 0.5) / 3])
  np.testing.assert_allclose(scores["depth_delta1"], [2 / 3])  # 1.2 < 1.25; a factor 2 is not
  empty = metrics.depth_errors(np.zeros((1, 2, 2, 1)), np.full((1, 2, 2), 3.0))
  np.testing.assert_allclose(empty["depth_absrel"], [1.0])  # a hole is a full error
  np.testing.assert_allclose(empty["depth_delta1"], [0.0])


def test_masked_psnr_scores_only_the_masked_pixels():
  rng = np.random.default_rng(5)
  target = rng.uniform(0.0, 0.9, size=(2, 8, 8, 3)).astype(np.float32)
  pred = target.copy()
  mask = np.zeros((2, 8, 8), bool)
  mask[0, 2:4, 1:5] = True
  pred[0, 2:4, 1:5] += 0.1  # error 0.1 on every masked value: MSE 0.01 -> 20 dB
  pred[0, 6:] = 1.0 - target[0, 6:]  # large errors outside the mask do not count
  values = np.asarray(jax.jit(metrics.masked_psnr)(pred, target, mask))
  assert values[0] == pytest.approx(20.0, abs=1e-3)
  assert np.isnan(values[1])  # empty mask: nothing to score
  full = np.ones((2, 8, 8), bool)
  np.testing.assert_allclose(metrics.masked_psnr(pred, target, full), metrics.psnr(pred, target))
  # clipped to [0, 1] and capped as psnr
  assert float(metrics.masked_psnr(target[1] + 5.0, np.ones_like(target[1]), full[1])) == 100.0


# ----------------------------------------------------------------------------------------------
# Foreground (official masked) metrics: soft masks, empty masks, an all-ones mask


def test_masked_psnr_weights_soft_masks_by_their_values():
  target = np.full((1, 1, 3, 3), 0.5, np.float32)
  pred = target.copy()
  pred[0, 0, 0] += 0.2  # weight 0.5, squared error 0.04 in each channel
  pred[0, 0, 1] += 0.1  # weight 1, squared error 0.01
  pred[0, 0, 2] += 0.4  # weight 0: not scored
  mask = np.array([[[0.5, 1.0, 0.0]]], np.float32)
  # official masked_mean: sum(m e) / sum(m), over channels too: (0.5 * 0.12 + 0.03) / 4.5 = 0.02
  expected = -10.0 * np.log10(0.02)
  assert float(metrics.masked_psnr(pred, target, mask)[0]) == pytest.approx(expected, abs=1e-4)
  tiny = np.array([[[0.25, 0.0, 0.0]]], np.float32)  # a weight sum under 1 is still a mean
  expected = -10.0 * np.log10(0.04)
  assert float(metrics.masked_psnr(pred, target, tiny)[0]) == pytest.approx(expected, abs=1e-4)


def test_masked_ssim_is_skimage_on_the_masked_images():
  rng = np.random.default_rng(7)
  target = rng.uniform(0, 1, (2, 40, 36, 3)).astype(np.float32)
  pred = np.clip(target + rng.normal(0, 0.15, target.shape), 0, 1).astype(np.float32)
  mask = np.zeros((2, 40, 36), np.float32)
  mask[:, 8:20, 6:18] = 1.0
  mask[:, 8:20, 18] = 0.5  # a soft edge
  values = np.asarray(jax.jit(metrics.masked_ssim)(pred, target, mask))
  for i in range(2):
    m = mask[i, ..., None]
    np.testing.assert_allclose(values[i], _skimage_ssim(pred[i] * m, target[i] * m), atol=2e-5)
  # errors outside the mask (and its window) do not count
  outside = pred.copy()
  outside[:, 8:20, 6:19] = target[:, 8:20, 6:19]
  assert np.all(np.asarray(metrics.masked_ssim(outside, target, mask)) == pytest.approx(1.0))
  assert np.asarray(metrics.ssim(outside, target)).max() < 0.95


def test_masked_metrics_are_nan_for_an_empty_mask_and_unmasked_for_a_full_one():
  rng = np.random.default_rng(8)
  target = rng.uniform(0, 1, (2, 16, 16, 3)).astype(np.float32)
  pred = np.clip(target + rng.normal(0, 0.2, target.shape), 0, 1).astype(np.float32)
  mask = np.ones((2, 16, 16), np.float32)
  mask[1] = 0.0
  params = lpips_lib.load_vgg_params()
  scores = {
    "psnr": (metrics.masked_psnr(pred, target, mask), metrics.psnr(pred, target)),
    "ssim": (metrics.masked_ssim(pred, target, mask), metrics.ssim(pred, target)),
    "lpips": (
      metrics.masked_lpips(pred, target, mask, params),
      metrics.lpips(pred, target, params),
    ),
  }
  for name, (masked, unmasked) in scores.items():
    masked, unmasked = np.asarray(masked), np.asarray(unmasked)
    assert masked.shape == (2,), name
    np.testing.assert_allclose(masked[0], unmasked[0], rtol=1e-6, err_msg=name)
    assert np.isnan(masked[1]), name  # nothing to score


def test_masked_lpips_is_lpips_of_the_masked_images():
  rng = np.random.default_rng(9)
  target = rng.uniform(0, 1, (16, 16, 3)).astype(np.float32)
  pred = np.clip(target + rng.normal(0, 0.2, target.shape), 0, 1).astype(np.float32)
  mask = np.zeros((16, 16), np.float32)
  mask[2:9, 3:12] = 1.0
  params = lpips_lib.load_vgg_params()
  m = mask[..., None]
  masked = float(metrics.masked_lpips(pred, target, mask, params))
  assert masked == pytest.approx(float(metrics.lpips(pred * m, target * m, params)), rel=1e-6)
  # an error outside the mask is not seen
  outside = np.where(m > 0, pred, 1.0 - target)
  assert float(metrics.masked_lpips(outside, target, mask, params)) == pytest.approx(masked)
