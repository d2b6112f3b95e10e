"""`render`'s checks of concrete values (outside jit): camera values, K matrices passed as
intrinsics, and the warning of an overflowed buffer; inside jit none of them runs."""

import warnings

import jax
import numpy as np
import pytest

from tokengs_jax import camera
from tokengs_jax.gaussians import Gaussians
from tokengs_jax.splatting import RenderBudgetWarning, RenderConfig, render, render_exact

HEIGHT, WIDTH, NUM = 24, 32, 48
INTR = np.array([30.0, 30.0, 16.0, 12.0], np.float32)
TIGHT = RenderConfig(max_intersections=64, chunk_size=8)  # far fewer pairs than the scene needs


def _scene():
  """NUM translucent Gaussians in front of the identity camera, spread over the image."""
  rng = np.random.default_rng(0)
  return Gaussians(
    means=np.c_[rng.uniform(-1.0, 1.0, (NUM, 2)), rng.uniform(2.0, 4.0, NUM)].astype(np.float32),
    opacities=np.full(NUM, 0.3, np.float32),
    scales=np.full((NUM, 3), 0.3, np.float32),
    quats=np.tile(np.float32([1, 0, 0, 0]), (NUM, 1)),
    colors=rng.uniform(0, 1, (NUM, 3)).astype(np.float32),
  )


def _cameras(views=3):
  """Identity poses [views, 4, 4] and intrinsics [views, 4]."""
  return np.tile(np.eye(4, dtype=np.float32), (views, 1, 1)), np.tile(INTR, (views, 1))


def _render(w2c, intr, **kwargs):
  return render(_scene(), w2c, intr, height=HEIGHT, width=WIDTH, **kwargs)


def test_an_overflowed_render_outside_jit_warns_and_points_to_render_exact():
  w2c, intr = _cameras()
  with pytest.warns(RenderBudgetWarning, match=r"overflow.*render_exact.*max_intersections"):
    cut = _render(w2c, intr, config=TIGHT)
  assert bool(np.all(cut.stats.overflow))
  with warnings.catch_warnings():
    warnings.simplefilter("error")  # none of these may warn
    _render(w2c, intr)  # the default buffer holds the scene
    exact_out = render_exact(_scene(), w2c, intr, height=HEIGHT, width=WIDTH, config=TIGHT)
    inside = jax.jit(lambda g: _render_traced(g, w2c, intr))(_scene())
  assert not np.any(exact_out.stats.overflow) and bool(np.all(inside))


def _render_traced(gaussians, w2c, intr):
  return render(gaussians, w2c, intr, height=HEIGHT, width=WIDTH, config=TIGHT).stats.overflow


@pytest.mark.parametrize(
  "field, index, value, match",
  [
    ("world_to_camera", (1, 0, 3), np.nan, r"world_to_camera of camera \[1\].*not finite"),
    ("world_to_camera", (2, 2, 2), np.inf, r"world_to_camera of camera \[2\].*not finite"),
    ("intrinsics", (1, 0), np.nan, r"intrinsics of camera \[1\].*not finite"),
    ("intrinsics", (2, 2), np.inf, r"intrinsics of camera \[2\].*not finite"),
    ("intrinsics", (1, 0), 0.0, r"intrinsics of camera \[1\].*fx, fy must be > 0"),
    ("intrinsics", (0, 1), -30.0, r"intrinsics of camera \[0\].*fx, fy must be > 0"),
  ],
)
def test_render_refuses_a_bad_concrete_camera_naming_field_and_camera(field, index, value, match):
  cameras = dict(zip(("world_to_camera", "intrinsics"), _cameras(), strict=True))
  cameras[field][index] = value
  with pytest.raises(ValueError, match=match):
    _render(cameras["world_to_camera"], cameras["intrinsics"])
  with pytest.raises(ValueError, match=match):
    render_exact(_scene(), **cameras, height=HEIGHT, width=WIDTH)
  # traced, the values do not exist yet: the camera renders as before, unchecked
  assert np.all(np.isfinite(_traced_rgb(*cameras.values())))


@jax.jit
def _traced_rgb(w2c, intr):
  """`render` of traced cameras, compiled once for every case."""
  return _render(w2c, intr).rgb


def test_a_batched_camera_is_named_by_its_full_index():
  w2c, intr = _cameras()
  intr = np.stack([intr, intr])
  intr[1, 2, 3] = np.nan
  with pytest.raises(ValueError, match=r"intrinsics of camera \[1, 2\] \(index into \[\.\.\., V\]"):
    _render(w2c, intr)


def test_a_k_matrix_is_refused_as_intrinsics_and_converts_explicitly():
  k3 = camera.intrinsics_matrix(INTR)
  k4 = np.eye(4, dtype=np.float32)
  k4[:3, :3] = k3
  w2c, _ = _cameras(views=4)
  # a 4x4 K has the shape of four views' (fx, fy, cx, cy) rows: its zero focal lengths refuse it
  with pytest.raises(ValueError, match=r"4x4 K matrix.*intrinsics_from_matrix"):
    _render(w2c, k4)
  with pytest.raises(ValueError, match="3x3 K"):
    _render(w2c[:3], k3)
  np.testing.assert_array_equal(camera.intrinsics_from_matrix(k3), INTR)
  np.testing.assert_array_equal(camera.intrinsics_from_matrix(k4), INTR)
  np.testing.assert_array_equal(
    camera.intrinsics_from_matrix(np.stack([k4] * 4)), np.tile(INTR, (4, 1))
  )
  out = _render(w2c, camera.intrinsics_from_matrix(np.stack([k4] * 4)))
  assert out.rgb.shape == (4, HEIGHT, WIDTH, 3)
