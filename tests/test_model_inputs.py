"""Input checks (`tokengs_jax.model.inputs`): reconstruct refuses bad images, cameras and times at
trace time with a message naming them, and accepts uint8 images and valid views."""

import jax
import numpy as np
import pytest
from scenes import FULL, MICRO, random_inputs

from tokengs_jax.model import encode_views, init_params, reconstruct


def _bad_views(change: str):
  """(config, images, c2w, intrinsics, times, target_times) valid but for `change`."""
  images, c2w, intrinsics = (np.asarray(x) for x in random_inputs(jax.random.key(5), 2, 3, 8, 8))
  config, times, target_times = MICRO, None, None
  if change == "images rank":
    images = images[0]
  elif change == "images channels":
    images = images[..., :2]
  elif change == "images dtype":
    images = (images * 255).astype(np.int32)
  elif change == "patch size":
    images = images[:, :, :6]
  elif change == "c2w shape":
    c2w = c2w[..., :3, :]
  elif change == "c2w dtype":
    c2w = c2w.astype(np.int32)
  elif change == "intrinsics shape":
    intrinsics = intrinsics[:, :2]
  elif change == "intrinsics dtype":
    intrinsics = intrinsics.astype(np.int32)
  elif change == "focal":
    intrinsics = intrinsics.copy()
    intrinsics[1, 2, 1] = 0.0
  elif change == "images nan":
    images = images.copy()
    images[1, 2, 3, 4, 0] = np.nan
  elif change == "c2w nan":
    c2w = c2w.copy()
    c2w[0, 1, 0, 3] = np.nan
  elif change == "cx inf":
    intrinsics = intrinsics.copy()
    intrinsics[1, 0, 2] = np.inf
  elif change == "times missing":
    config = FULL
  elif change == "times unexpected":
    times = np.zeros((2, 3), np.float32)
  elif change == "times shape":
    config, times = FULL, np.zeros((2, 2), np.float32)
  elif change == "times dtype":
    config, times = FULL, np.zeros((2, 3), np.int32)
  elif change == "target_times shape":
    config, times, target_times = FULL, np.zeros((2, 3), np.float32), np.zeros((2, 1), np.float32)
  return config, images, c2w, intrinsics, times, target_times


@pytest.mark.parametrize(
  "change, error, message",
  [
    ("images rank", ValueError, r"images must be \[B, V, H, W, 3\]"),
    ("images channels", ValueError, r"images must be \[B, V, H, W, 3\]"),
    ("images dtype", TypeError, "images must be floating point in \\[0, 1\\] or uint8"),
    ("patch size", ValueError, "divisible by the patch size 4"),
    ("c2w shape", ValueError, r"c2w must be \[B, V, 4, 4\] = \(2, 3, 4, 4\), got shape"),
    ("c2w dtype", TypeError, "c2w must be floating point"),
    ("intrinsics shape", ValueError, r"intrinsics must be \[B, V, 4\]"),
    ("intrinsics dtype", TypeError, "intrinsics must be floating point"),
    ("focal", ValueError, r"intrinsics of view \[1, 2\].*fx, fy must be > 0"),
    ("times missing", ValueError, "pass the input-view times"),
    ("times unexpected", ValueError, "without time embedding"),
    ("times shape", ValueError, r"times must be \[B, V\] = \(2, 3\), got shape \(2, 2\)"),
    ("times dtype", TypeError, "times must be floating point"),
    ("target_times shape", ValueError, r"target_times must be \[B\]"),
  ],
)
def test_reconstruct_rejects_bad_inputs_at_trace_time(change, error, message):
  config, images, c2w, intrinsics, times, target_times = _bad_views(change)
  params = jax.eval_shape(lambda: init_params(jax.random.key(0), config))
  trace = jax.eval_shape if change != "focal" else _call  # values: concrete only
  with pytest.raises(error, match=message):
    trace(
      lambda *a: reconstruct(*a, config=config, times=times, target_times=target_times),
      params,
      images,
      c2w,
      intrinsics,
    )


def _call(function, *args):
  return function(*args)


@pytest.mark.parametrize(
  "change, message",
  [
    ("images nan", r"images of view \[1, 2\] .*not finite"),
    ("c2w nan", r"c2w of view \[0, 1\] .*not finite"),
    ("cx inf", r"intrinsics of view \[1, 0\] .*not finite"),
  ],
)
def test_reconstruct_refuses_non_finite_concrete_views_naming_input_and_view(change, message):
  config, images, c2w, intrinsics, _, _ = _bad_views(change)
  params = jax.eval_shape(lambda: init_params(jax.random.key(0), config))
  run = lambda *a: reconstruct(*a, config=config)
  with pytest.raises(ValueError, match=message):
    run(params, images, c2w, intrinsics)
  with pytest.raises(ValueError, match=message):
    encode_views(params, images, c2w, intrinsics, config)
  # traced (inside jit) the values do not exist yet: nothing to check
  out = jax.eval_shape(run, params, images, c2w, intrinsics)
  assert out.means.shape == (2, config.num_gaussians, 3)


def test_reconstruct_accepts_uint8_images_and_valid_views():
  for change in ("none", "images uint8"):
    config, images, c2w, intrinsics, _, _ = _bad_views(change)
    if change == "images uint8":
      images = (images * 255).astype(np.uint8)
    params = jax.eval_shape(lambda: init_params(jax.random.key(0), config))
    out = jax.eval_shape(lambda *a: reconstruct(*a, config=config), params, images, c2w, intrinsics)
    assert out.means.shape == (2, config.num_gaussians, 3)
