"""View sampling and evaluation indexes (`tokengs_jax.data.sampler`): the bounded sampler and its
presets (the generator's 32-frame walks too), too few frames, and evaluation indexes in every
released format (keyed, DepthSplat's hash keys, the list format) with malformed ones named."""

import json

import numpy as np
import pytest

from tokengs_jax.data import (
  SAMPLER_PRESETS,
  BoundedSamplerConfig,
  MissingIndexEntryError,
  NotEnoughFramesError,
  context_gap_bounds,
  evaluation_views,
  load_evaluation_index,
  sample_bounded,
)

HASH_A = "032dee9fb0a8bc1b90871dc5fe950080d0bcd3caf166447f44e60ca50ac04ec7"
HASH_B = "0569e83fdc248a51fc0ab082ce5e2baff15755c53c207f545e6d02d91f01d166"


# ---- sampler


def test_bounded_sampler_respects_bounds():
  rng = np.random.default_rng(0)
  config = BoundedSamplerConfig(3, 5, 4, 9, 1, 0, 4, 9)
  for _ in range(200):
    context, target = sample_bounded(config, 30, rng)
    gap = context[-1] - context[0]
    assert 4 <= gap <= 9 and len(set(context.tolist())) == 3 and np.all(np.diff(context) > 0)
    assert (
      target.shape == (5,) and context[0] + 1 <= target.min() and target.max() <= context[-1] - 1
    )
    assert 0 <= context[0] and context[-1] < 30


def test_warm_up_schedule_and_presets():
  config = SAMPLER_PRESETS["pixelsplat_re10k"]
  assert context_gap_bounds(config, 0) == (25, 45)
  assert context_gap_bounds(config, 75_000) == (35, 118)
  assert context_gap_bounds(config, 10**6) == (45, 192)
  assert context_gap_bounds(SAMPLER_PRESETS["tokengs_dl3dv"], 0) == (10, 40)
  context, target = sample_bounded(config, 300, np.random.default_rng(0), deterministic=True)
  np.testing.assert_array_equal(context, [0, 192])
  np.testing.assert_array_equal(target, [0, 64, 128, 192])


def test_too_few_frames():
  with pytest.raises(NotEnoughFramesError, match="5 frames"):
    sample_bounded(BoundedSamplerConfig(2, 1, 6, 9, 0, 0, 6, 9), 5, np.random.default_rng(0))
  with pytest.raises(NotEnoughFramesError):
    sample_bounded(BoundedSamplerConfig(4, 1, 1, 9, 0, 0, 1, 9), 3, np.random.default_rng(0))


# ---- the synthetic presets (the generator's 32-frame walks)


def test_synthetic_32_frames_preset_fits_the_32_frame_walks():
  preset = SAMPLER_PRESETS["synthetic_32_frames"]
  rng = np.random.default_rng(0)
  for step in (0, preset.warm_up_steps // 2, 10 * preset.warm_up_steps):
    low, high = context_gap_bounds(preset, step)
    for _ in range(50):
      context, target = sample_bounded(preset, 32, rng, step=step)
      assert low <= context[-1] - context[0] <= high and context[-1] < 32
      assert context[0] <= target.min() and target.max() <= context[-1]
  context, _ = sample_bounded(preset, 32, rng, deterministic=True)
  assert context.tolist() == [0, preset.max_context_gap]


# ---- evaluation indexes


def test_evaluation_index(tmp_path):
  path = tmp_path / "evaluation_index.json"
  path.write_text(json.dumps({"a": {"context": [1, 9], "target": [3, 5, 7]}, "b": None}))
  index = load_evaluation_index(path)
  assert set(index) == {"a"}
  context, target = evaluation_views(index, "a", 10)
  np.testing.assert_array_equal(context, [1, 9])
  np.testing.assert_array_equal(target, [3, 5, 7])
  with pytest.raises(MissingIndexEntryError, match="'b'"):
    evaluation_views(index, "b", 10)
  with pytest.raises(NotEnoughFramesError, match="frame 9"):
    evaluation_views(index, "a", 8)


def test_depthsplat_dl3dv_index_with_hash_keys(tmp_path):
  path = tmp_path / "dl3dv_start_0_distance_50_ctx_6v_tgt_8v.json"  # the released entry shape
  path.write_text(
    json.dumps(
      {HASH_A: {"context": [0, 19, 29, 33, 39, 49], "target": [1, 6, 11, 16, 22, 27, 34, 40]}}
    )
  )
  context, target = evaluation_views(load_evaluation_index(path), HASH_A, 50)
  assert context.tolist() == [0, 19, 29, 33, 39, 49] and target.tolist() == [
    1,
    6,
    11,
    16,
    22,
    27,
    34,
    40,
  ]


def test_list_format_index_reads_the_chosen_context_and_targets_every_frame(tmp_path):
  path = tmp_path / "dl3dv_fold_8_kmeans_input_idx.json"
  path.write_text(
    json.dumps(
      [
        {
          "scene_name": HASH_A,
          "fold_8_kmeans_16_input": [1, 3, 5],
          "fold_8_kmeans_32_input": [1, 2, 3, 5],
        },
        {
          "scene_name": HASH_B,
          "fold_8_kmeans_16_input": [2, 4],
          "fold_8_kmeans_32_input": [2, 3, 4],
        },
      ]
    )
  )
  index = load_evaluation_index(path, num_context=16)
  assert list(index) == [HASH_A, HASH_B]
  context, target = evaluation_views(index, HASH_A, 7)
  assert context.tolist() == [1, 3, 5] and target.tolist() == list(range(7))
  assert evaluation_views(load_evaluation_index(path, num_context=32), HASH_B, 5)[0].tolist() == [
    2,
    3,
    4,
  ]
  with pytest.raises(NotEnoughFramesError, match="frame 5 of a 5-frame"):
    evaluation_views(index, HASH_A, 5)
  with pytest.raises(ValueError, match="needs num_context"):
    load_evaluation_index(path)
  with pytest.raises(ValueError, match=f"'{HASH_A}' has no 'fold_8_kmeans_8_input'"):
    load_evaluation_index(path, num_context=8)


@pytest.mark.parametrize(
  "content, message",
  [
    ([{"fold_8_kmeans_16_input": [1]}], "list entry 0 needs a 'scene_name'"),
    (
      [{"scene_name": "s", "fold_8_kmeans_16_input": [1, "2"]}],
      "'s' needs 'fold_8_kmeans_16_input' as a list",
    ),
    ({"s": {"context": [0, 1]}}, "'s' needs 'target'"),
    ({"s": [0, 1]}, "'s' needs 'context' and 'target'"),
    ("scenes", "found str"),
  ],
)
def test_malformed_indexes_name_file_and_scene(tmp_path, content, message):
  path = tmp_path / "index.json"
  path.write_text(json.dumps(content))
  with pytest.raises(ValueError, match=message) as error:
    load_evaluation_index(path, num_context=16)
  assert str(path) in str(error.value)
