"""List-format DL3DV evaluation index, the pipeline's "pointmap" scale on Kubric, the synthetic
sampler and dataset presets, and the host-side rigid inverse."""

import dataclasses
import json

import jax.numpy as jnp
import numpy as np
import pytest

from tokengs_jax import camera
from tokengs_jax.data import (
  DATASET_PRESETS,
  SAMPLER_PRESETS,
  BadExampleError,
  ChunkedSceneSource,
  InputPipeline,
  NotEnoughFramesError,
  context_gap_bounds,
  evaluation_views,
  kubric,
  load_evaluation_index,
  make_example,
  sample_bounded,
  transforms,
)
from tokengs_jax.data.synthetic import generate

HASH_A = "032dee9fb0a8bc1b90871dc5fe950080d0bcd3caf166447f44e60ca50ac04ec7"
HASH_B = "0569e83fdc248a51fc0ab082ce5e2baff15755c53c207f545e6d02d91f01d166"


# ---- evaluation indexes


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


# ---- Kubric through the generic pipeline with the official "pointmap" scale

H, W, FRAMES, CAMERAS = 12, 16, 8, 3


@pytest.fixture(scope="module")
def kubric_root(tmp_path_factory):
  root = tmp_path_factory.mktemp("kubric")
  config = dataclasses.replace(generate.KubricLikeConfig(), supersample=1)
  generate.generate_kubric_like(root, 1, H, W, FRAMES, CAMERAS, seed=3, config=config)
  return root


def test_pointmap_batches_and_a_record_without_depths(kubric_root):
  config = dataclasses.replace(DATASET_PRESETS["kubric"], image_shape=(8, 8))
  select = kubric.kubric_view_selector(3, 2, min_gap=2, max_gap=6)
  pipeline = InputPipeline(
    kubric.KubricSceneSource(kubric_root, ("v0",), num_cameras=CAMERAS),
    config,
    batch_size=2,
    seed=0,
    shard_index=0,
    shard_count=1,
    select_views=select,
  )
  batch = next(iter(pipeline))
  assert batch["context_c2w"].shape == (2, 3, 4, 4) and batch["target_times"].shape == (2, 2)
  record = {
    k: v
    for k, v in kubric.KubricSceneSource(kubric_root, ("v0",), num_cameras=CAMERAS)[0].items()
    if k != "depths"
  }
  with pytest.raises(BadExampleError, match="scene_000000.*needs depth maps"):
    make_example(
      record, config, np.random.default_rng(0), views=select(record, np.random.default_rng(0), 0)
    )


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


def test_synthetic_dataset_preset_batches_generated_walks(tmp_path):
  config = dataclasses.replace(generate.Re10kLikeConfig(), supersample=1)
  generate.generate_re10k_like(tmp_path, 2, 0, 16, 16, 32, seed=1, config=config)
  preset = dataclasses.replace(DATASET_PRESETS["synthetic"], image_shape=(16, 16))
  pipeline = InputPipeline(
    ChunkedSceneSource(tmp_path / "train"),
    preset,
    batch_size=2,
    seed=0,
    shard_index=0,
    shard_count=1,
  )
  batch = next(iter(pipeline))
  assert batch["context_images"].shape == (2, 2, 16, 16, 3) and batch["target_images"].shape == (
    2,
    4,
    16,
    16,
    3,
  )
  assert not pipeline.rejections


# ---- host-side rigid inverse


def test_rigid_inverse_matches_the_jax_camera_inverse():
  rng = np.random.default_rng(0)
  q, _ = np.linalg.qr(rng.normal(size=(5, 3, 3)))
  pose = np.tile(np.eye(4), (5, 1, 1))
  pose[:, :3, :3], pose[:, :3, 3] = q, rng.normal(size=(5, 3))
  host = transforms.rigid_inverse(pose)
  np.testing.assert_allclose(
    host, np.asarray(camera.invert_rigid(jnp.asarray(pose, jnp.float32))), atol=1e-5
  )
  np.testing.assert_allclose(host @ pose, np.broadcast_to(np.eye(4), pose.shape), atol=1e-12)
