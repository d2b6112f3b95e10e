"""The input pipeline (`tokengs_jax.data.pipeline`) on generated chunks: batches, translation
scale, resumable and sharded streams, bad scenes, evaluation views, times, the "pointmap" scale
on Kubric and the synthetic dataset preset."""

import dataclasses
import json

import numpy as np
import pytest

from tokengs_jax.data import (
  DATASET_PRESETS,
  BadExampleError,
  BoundedSamplerConfig,
  ChunkedSceneSource,
  ExampleConfig,
  InputPipeline,
  MissingIndexEntryError,
  chunks,
  kubric,
  make_example,
  write_chunk,
)
from tokengs_jax.data.synthetic import generate

SMALL_SAMPLER = BoundedSamplerConfig(2, 3, 2, 6, 0, 0, 2, 6)
SMALL = ExampleConfig((16, 24), SMALL_SAMPLER, 0.25)


def _scene(key, frames=10, seed=0, height=20, width=32):
  rng = np.random.default_rng(seed)
  c2w = np.tile(np.eye(4), (frames, 1, 1))
  c2w[:, :3, 3] = np.cumsum(rng.normal(scale=0.1, size=(frames, 3)), axis=0) + rng.normal(size=3)
  intrinsics = np.tile([30.0, 30.0, width / 2, height / 2], (frames, 1))
  images = rng.integers(0, 255, (frames, height, width, 3), dtype=np.uint8)
  return {"key": key, "c2w": c2w, "intrinsics": intrinsics, "images": images}


def _write_dataset(root, scenes_per_chunk):
  root.mkdir(parents=True, exist_ok=True)
  index = {}
  for number, scenes in enumerate(scenes_per_chunk):
    name = f"{number:06d}.torch"
    write_chunk(root / name, scenes)
    index.update({scene["key"]: name for scene in scenes})
  (root / "index.json").write_text(json.dumps(index))
  return root


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
  root = tmp_path_factory.mktemp("re10k") / "train"
  return _write_dataset(
    root, [[_scene(f"k{c}{s}", seed=10 * c + s) for s in range(3)] for c in range(2)]
  )


# ---- pipeline


def _pipeline(source, config=SMALL, **kwargs):
  kwargs = {"batch_size": 2, "seed": 0, "shard_index": 0, "shard_count": 1, **kwargs}
  return InputPipeline(source, config, **kwargs)


def test_batches_have_fixed_shapes_and_normalised_cameras(dataset):
  source = ChunkedSceneSource(dataset)
  assert len(source) == 6
  batches = [b for _, b in zip(range(4), _pipeline(source))]
  for batch in batches:
    assert batch["context_images"].shape == (2, 2, 16, 24, 3)
    assert batch["target_images"].shape == (2, 3, 16, 24, 3)
    assert batch["context_c2w"].shape == (2, 2, 4, 4) and batch["target_intrinsics"].shape == (
      2,
      3,
      4,
    )
    assert batch["context_images"].dtype == np.float32
    assert 0.0 <= batch["context_images"].min() and batch["context_images"].max() <= 1.0
    np.testing.assert_allclose(
      batch["context_c2w"][:, 0], np.broadcast_to(np.eye(4), (2, 4, 4)), atol=1e-6
    )
    assert batch["scene_index"].dtype == np.int64


def test_translation_scale_is_applied(dataset):
  source = ChunkedSceneSource(dataset)
  record = source[0]
  from tokengs_jax.data import make_example

  views = (np.array([0, 4]), np.array([2, 3, 5]))
  config = ExampleConfig((20, 32), SMALL_SAMPLER, 0.25, random_flip=False)
  example = make_example(record, config, np.random.default_rng(0), views=views)
  raw = np.linalg.inv(record["c2w"][0]) @ record["c2w"][4]
  np.testing.assert_allclose(example["context_c2w"][1, :3, 3], 0.25 * raw[:3, 3], atol=1e-5)
  np.testing.assert_allclose(example["context_intrinsics"], record["intrinsics"][[0, 4]], atol=1e-5)


def test_checkpoint_restores_the_exact_stream(dataset):
  pipeline = _pipeline(ChunkedSceneSource(dataset))
  iterator = pipeline.iterator()
  for _ in range(3):
    next(iterator)
  state = iterator.get_state()
  expected = [next(iterator) for _ in range(3)]
  restored = pipeline.iterator()
  restored.set_state(state)
  for batch in expected:
    got = next(restored)
    for key in batch:
      np.testing.assert_array_equal(got[key], batch[key])


def test_shards_are_disjoint_and_cover_the_source(dataset):
  source = ChunkedSceneSource(dataset)
  seen = []
  for shard in range(2):
    pipeline = _pipeline(source, batch_size=1, shard_index=shard, shard_count=2, num_epochs=1)
    seen.append({int(b["scene_index"][0]) for b in pipeline})
  assert seen[0].isdisjoint(seen[1]) and seen[0] | seen[1] == set(range(6))


def test_bad_scenes_raise_naming_file_and_scene_or_are_skipped_and_counted(tmp_path):
  good = [_scene(f"g{i}", seed=i) for i in range(3)]
  short = _scene("short", frames=2)
  root = _write_dataset(tmp_path / "bad", [good + [short]])
  record = chunks.scenes._scene_to_record(_scene("corrupt"), 95)
  for frame in range(1, 10):  # frame 0 stays readable: the scan reads the image size from it
    record["images"][frame] = np.frombuffer(b"\xff\xd8\xff\xe0 not a jpeg", np.uint8)
  chunks.save_tensor_archive(root / "000001.torch", [record])
  source = ChunkedSceneSource(root)
  assert len(source) == 5
  sampler = BoundedSamplerConfig(2, 3, 3, 9, 0, 0, 3, 9)
  strict = _pipeline(
    source, ExampleConfig((16, 16), sampler, 0.25), shuffle=False, num_epochs=1, batch_size=1
  )
  with pytest.raises(BadExampleError, match=r"000000\.torch scene 'short'.*2 frames"):
    list(strict)
  lenient = _pipeline(
    source,
    ExampleConfig((16, 16), sampler, 0.25),
    shuffle=False,
    num_epochs=1,
    batch_size=1,
    skip_bad=True,
  )
  keys = [int(b["scene_index"][0]) for b in lenient]
  assert len(keys) == 3
  assert lenient.rejections.total() == 2
  assert any("000001.torch scene 'corrupt' frame" in m for m in lenient.rejections.messages)


def test_nan_pose_chunk_is_refused_at_scan(tmp_path):
  record = chunks.scenes._scene_to_record(_scene("nan"), 95)
  record["cameras"][3, 7] = np.inf
  root = tmp_path / "nan"
  root.mkdir()
  chunks.save_tensor_archive(root / "000000.torch", [record])
  with pytest.raises(chunks.ChunkError, match=r"000000\.torch scene 'nan'.*NaN/inf"):
    ChunkedSceneSource(root)


def test_missing_index_entry_and_evaluation_views(dataset, tmp_path):
  with pytest.raises(MissingIndexEntryError, match="'nope'"):
    ChunkedSceneSource(dataset, keys=["k01", "nope"])
  source = ChunkedSceneSource(dataset, keys=["k12", "k01", "nope"], skip_bad=True)
  assert [e.key for e in source.entries] == ["k12", "k01"] and source.rejections.counts[
    "missing_index_entry"
  ] == 1
  index = {"k12": ((0, 8), (2, 4)), "k01": ((1, 9), (3, 5))}
  pipeline = _pipeline(
    source,
    ExampleConfig((20, 32), SMALL_SAMPLER, 0.25, random_flip=False),
    evaluation_index=index,
    shuffle=False,
    num_epochs=1,
    batch_size=1,
  )
  batches = list(pipeline)
  assert [int(b["scene_index"][0]) for b in batches] == [0, 1]
  record = source[1]
  raw = np.linalg.inv(record["c2w"][1]) @ record["c2w"][5]
  np.testing.assert_allclose(batches[1]["target_c2w"][0, 1, :3, 3], 0.25 * raw[:3, 3], atol=1e-5)


def test_dynamic_records_get_normalised_times():
  scene = _scene("dyn", frames=8)
  record = {**scene, "times": np.arange(8) * 0.5 + 3.0, "height": 20, "width": 32}
  pipeline = _pipeline(
    [record],
    batch_size=1,
    num_epochs=1,
    shuffle=False,
    select_views=lambda rec, rng, step: (np.array([0, 2]), np.array([1, 3, 6])),
  )
  (batch,) = list(pipeline)
  np.testing.assert_allclose(batch["context_times"][0], [0.0, 2 / 6])
  np.testing.assert_allclose(batch["target_times"][0], [1 / 6, 0.5, 1.0])


@pytest.mark.slow
def test_worker_processes_give_the_same_batches(dataset):
  source = ChunkedSceneSource(dataset)
  inline = [b for _, b in zip(range(3), _pipeline(source))]
  workers = [b for _, b in zip(range(3), _pipeline(source, num_workers=2))]
  for a, b in zip(inline, workers):
    for key in a:
      np.testing.assert_array_equal(a[key], b[key])


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


# ---- the synthetic dataset preset (the generator's 32-frame walks)


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


def test_pointmap_trim_drops_outlier_depths_as_pointmap_scale_does():
  """`ExampleConfig.pointmap_trim_lo / _hi` (official `pointmap_trim_lo / _hi`) reach the
  pipeline's "pointmap" scale: on depth maps with a few far outliers the trimmed scale differs
  from the untrimmed one and is `pointmap_scale(trim=...)` of the normalised context cameras."""
  from tokengs_jax.data.transforms import normalize_cameras

  rng = np.random.default_rng(0)
  size, frames = 8, 4
  c2w = np.tile(np.eye(4), (frames, 1, 1))
  c2w[:, :3, 3] = rng.normal(scale=0.3, size=(frames, 3))
  intrinsics = np.tile([8.0, 8.0, size / 2, size / 2], (frames, 1))
  depths = rng.uniform(1.5, 2.5, (frames, size, size)).astype(np.float32)
  depths[:, 0, :3] = 500.0  # a few far outliers (sky hits) in every view
  record = {
    "key": "outliers",
    "c2w": c2w,
    "intrinsics": intrinsics,
    "images": rng.integers(0, 255, (frames, size, size, 3), dtype=np.uint8),
    "depths": depths,
    "height": size,
    "width": size,
  }
  views = (np.array([0, 1]), np.array([2, 3]))
  base = dataclasses.replace(
    DATASET_PRESETS["kubric"], image_shape=(size, size), random_flip=False, deterministic=True
  )
  assert (base.pointmap_trim_lo, base.pointmap_trim_hi) == (0.0, 1.0)  # official: no trim
  normalised = normalize_cameras(c2w[np.concatenate(views)], 2, base.normalization)

  def scaled(trim):
    config = dataclasses.replace(base, pointmap_trim_lo=trim[0], pointmap_trim_hi=trim[1])
    example = make_example(record, config, np.random.default_rng(0), views=views)
    scale = 1.0 / kubric.pointmap_scale(depths[views[0]], normalised[:2], intrinsics[:2], trim)
    expected = normalised[:, :3, 3] * scale
    got = np.concatenate([example["context_c2w"], example["target_c2w"]])[:, :3, 3]
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-7)
    return scale

  untrimmed, trimmed = scaled((0.0, 1.0)), scaled((0.05, 0.9))
  # the outliers (3 of 64 points per view) inflate the mean distance ~20x; trimming them away
  # brings the scale back near 1 / (mean depth 2)
  assert trimmed > 5 * untrimmed and trimmed == pytest.approx(0.5, rel=0.3)
  assert scaled((0.0, 0.9)) == pytest.approx(trimmed, rel=0.05)
  for lo, hi in ((0.5, 0.5), (-0.1, 1.0), (0.0, 1.5), (0.9, 0.1)):
    with pytest.raises(ValueError, match="pointmap_trim_lo"):
      dataclasses.replace(base, pointmap_trim_lo=lo, pointmap_trim_hi=hi)
    with pytest.raises(ValueError, match="pointmap_trim_lo"):  # the official: silently no trim
      kubric.pointmap_scale(depths[:1], normalised[:1], intrinsics[:1], (lo, hi))
