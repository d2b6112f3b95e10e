"""pixelSplat/MVSplat's RE10K example filters: maximum field of view and minimum context baseline."""

import math

import numpy as np
import pytest

from tokengs_jax.data import (
  BadExampleError,
  BoundedSamplerConfig,
  ExampleConfig,
  InputPipeline,
  make_example,
)
from tokengs_jax.data.pipeline import field_of_view

HEIGHT, WIDTH = 20, 32
SAMPLER = BoundedSamplerConfig(2, 3, 2, 6, 0, 0, 2, 6)
OFF = ExampleConfig((16, 24), SAMPLER, 0.25)
VIEWS = (np.array([0, 4]), np.array([1, 2, 3]))


def _record(key="scene", frames=10, seed=0, fx=30.0, fy=30.0):
  rng = np.random.default_rng(seed)
  c2w = np.tile(np.eye(4), (frames, 1, 1))
  c2w[:, :3, 3] = np.cumsum(rng.normal(scale=0.1, size=(frames, 3)), axis=0) + rng.normal(size=3)
  intrinsics = np.tile([fx, fy, WIDTH / 2, HEIGHT / 2], (frames, 1))
  images = rng.integers(0, 255, (frames, HEIGHT, WIDTH, 3), dtype=np.uint8)
  return {
    "key": key,
    "c2w": c2w,
    "intrinsics": intrinsics,
    "images": images,
    "height": HEIGHT,
    "width": WIDTH,
  }


def _on(**kwargs):
  return ExampleConfig((16, 24), SAMPLER, 0.25, **kwargs)


def _build(record, config, views=VIEWS):
  return make_example(record, config, np.random.default_rng(0), views=views)


def _assert_kept_as_is(record, config, views=VIEWS):
  """A scene the filters let through gives the example it gives with them off, and the record is
  left as it was (the next epoch reads it again). Returns the example."""
  before = {key: np.array(value, copy=True) for key, value in record.items() if key != "key"}
  kept = _build(record, config, views)
  for key, value in before.items():
    np.testing.assert_array_equal(record[key], value, err_msg=f"record[{key!r}] changed")
  plain = _build(record, OFF, views)
  assert kept.keys() == plain.keys()
  for key in plain:
    np.testing.assert_array_equal(kept[key], plain[key], err_msg=key)
  return kept


def _focal_for_fov(fov_degrees, size):
  return (size / 2) / math.tan(math.radians(fov_degrees) / 2)


def test_field_of_view_matches_pixelsplat_get_fov():
  # pixelSplat: normalised K (fx/W, fy/H, cx/W, cy/H); angle between K^-1 (0, .5, 1) and
  # K^-1 (1, .5, 1), and between K^-1 (.5, 0, 1) and K^-1 (.5, 1, 1). Off-centre principal point.
  intrinsics = np.array([[25.0, 40.0, 13.0, 12.5], [12.0, 9.0, 16.0, 10.0]])
  got = field_of_view(intrinsics, HEIGHT, WIDTH)
  for row, (fx, fy, cx, cy) in enumerate(intrinsics):
    inverse = np.linalg.inv([[fx / WIDTH, 0, cx / WIDTH], [0, fy / HEIGHT, cy / HEIGHT], [0, 0, 1]])

    def angle(a, b):
      a, b = inverse @ a, inverse @ b
      return math.degrees(math.acos(a @ b / np.linalg.norm(a) / np.linalg.norm(b)))

    expected = [angle([0, 0.5, 1], [1, 0.5, 1]), angle([0.5, 0, 1], [0.5, 1, 1])]
    np.testing.assert_allclose(got[row], expected, rtol=1e-12)
  np.testing.assert_allclose(
    field_of_view([[16.0, 10.0, 16.0, 10.0]], HEIGHT, WIDTH), [[90.0, 90.0]]
  )


@pytest.mark.parametrize("axis", ["horizontal", "vertical"])
def test_wide_field_of_view_is_rejected_only_above_the_limit(axis):
  def record(relative):  # the other axis stays narrow
    if axis == "horizontal":
      return _record(fx=_focal_for_fov(100.0, WIDTH) * relative, fy=60.0)
    return _record(fx=60.0, fy=_focal_for_fov(100.0, HEIGHT) * relative)

  just_wider, just_narrower = record(1 - 1e-6), record(1 + 1e-6)
  with pytest.raises(BadExampleError, match=rf"scene 'scene'.*{axis} field of view 100\.000\d deg"):
    _build(just_wider, _on(max_fov_degrees=100.0))
  _assert_kept_as_is(just_narrower, _on(max_fov_degrees=100.0))
  assert OFF.max_fov_degrees is None and _build(just_wider, OFF)  # off by default
  _assert_kept_as_is(just_wider, _on(max_fov_degrees=101.0))


def test_field_of_view_is_tested_on_every_frame_of_the_scene():
  record = _record()
  record["intrinsics"][9, 0] = 5.0  # frame 9 is not among the chosen views
  with pytest.raises(BadExampleError, match="frame 9 exceeds max_fov_degrees 100.0"):
    _build(record, _on(max_fov_degrees=100.0))


def _coincident(distance, context=(0, 4)):
  record = _record()
  a, b = context
  record["c2w"][b, :3, 3] = record["c2w"][a, :3, 3] + np.array([0.6, 0.0, 0.8]) * distance
  return record


def test_nearly_coincident_context_cameras_are_rejected_only_below_epsilon():
  config = _on(min_context_baseline=1e-3)
  with pytest.raises(BadExampleError, match=r"scene 'scene': context baseline 0\.000999.*below"):
    _build(_coincident(1e-3 * (1 - 1e-6)), config)
  _assert_kept_as_is(_coincident(1e-3 * (1 + 1e-6)), config)
  coincident = _build(_coincident(0.0), OFF)  # off: the two cameras stay where they are
  np.testing.assert_allclose(coincident["context_c2w"][1, :3, 3], 0.0, atol=1e-9)
  # measured in raw record units, before normalisation and the 0.25 translation scale: kept,
  # although the example's context baseline is 0.25 x 2e-3, below the epsilon
  example = _assert_kept_as_is(_coincident(2e-3), config)
  centres = example["context_c2w"][:, :3, 3]
  np.testing.assert_allclose(np.linalg.norm(centres[1] - centres[0]), 0.25 * 2e-3, rtol=1e-5)


def test_baseline_is_not_checked_without_exactly_two_context_views():
  config = _on(min_context_baseline=1e-3)
  with pytest.raises(BadExampleError, match="context baseline"):  # two coincident views: out
    _build(_coincident(0.0), config)
  three = (np.array([0, 4, 6]), np.array([1, 2, 3]))  # the same pair plus a third: kept as is
  example = _build(_coincident(0.0), config, views=three)
  assert example["context_images"].shape[0] == 3
  np.testing.assert_array_equal(
    example["context_c2w"], _build(_coincident(0.0), OFF, views=three)["context_c2w"]
  )


def test_filters_leave_a_normal_example_bit_identical():
  record = _record(seed=3)
  on = _on(max_fov_degrees=100.0, min_context_baseline=1e-3)
  for views in (VIEWS, None):  # fixed views, and the bounded sampler with its random flip
    plain = make_example(record, OFF, np.random.default_rng(7), views=views)
    filtered = make_example(record, on, np.random.default_rng(7), views=views)
    assert plain.keys() == filtered.keys()
    for key in plain:
      assert plain[key].dtype == filtered[key].dtype
      np.testing.assert_array_equal(plain[key], filtered[key])


def test_pipeline_skips_and_counts_filtered_examples():
  good = [_record(f"good{i}", seed=i) for i in range(3)]
  wide = _record("wide", fx=5.0)
  still = _record("still")
  still["c2w"][:, :3, 3] = 1.5  # every pair of cameras coincides
  source = [good[0], wide, good[1], still, good[2]]
  config = _on(max_fov_degrees=100.0, min_context_baseline=1e-3)
  kwargs = {
    "batch_size": 1,
    "seed": 0,
    "shard_index": 0,
    "shard_count": 1,
    "shuffle": False,
    "num_epochs": 1,
  }
  with pytest.raises(BadExampleError, match="scene 'wide'"):
    list(InputPipeline(source, config, **kwargs))
  lenient = InputPipeline(source, config, skip_bad=True, **kwargs)
  assert [int(b["scene_index"][0]) for b in lenient] == [0, 2, 4]
  assert lenient.rejections.counts == {"BadExampleError": 2}
  assert any("scene 'wide'" in m and "field of view" in m for m in lenient.rejections.messages)
  assert any(
    "scene 'still'" in m and "context baseline 0 " in m for m in lenient.rejections.messages
  )
  assert len(list(InputPipeline(source, OFF, **kwargs))) == 5
