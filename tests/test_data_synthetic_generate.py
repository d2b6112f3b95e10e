"""The dataset writers (`synthetic.generate`): deterministic scenes, chunk files that read back
with their cameras and batch through the pipeline, true depths recorded beside the chunks."""

import json

import numpy as np
from synthetic_scenes import H, W

from tokengs_jax.data import read_chunk
from tokengs_jax.data.synthetic import generate
from tokengs_jax.data.synthetic.generate import (
  Re10kLikeConfig,
  generate_re10k_like,
  render_re10k_like_scene,
)


def test_re10k_like_scene_is_deterministic_by_seed():
  config = Re10kLikeConfig(supersample=1)
  a = render_re10k_like_scene(5, "train", 2, 12, 16, 3, config)
  b = render_re10k_like_scene(5, "train", 2, 12, 16, 3, config)
  c = render_re10k_like_scene(5, "train", 3, 12, 16, 3, config)
  for field in ("c2w", "intrinsics", "images", "depths"):
    np.testing.assert_array_equal(a[field], b[field])
  assert not np.array_equal(a["c2w"], c["c2w"])
  assert (a["depths"] > 0).all()  # a closed room: every ray hits something


def test_generated_chunks_read_back_with_the_same_cameras(tmp_path):
  config = Re10kLikeConfig(supersample=1, scenes_per_chunk=2)
  index = generate_re10k_like(
    tmp_path, num_train=3, num_test=1, height=H, width=W, frames=4, seed=9, config=config
  )
  assert sorted((tmp_path / "train").iterdir()) == [
    tmp_path / "train" / n
    for n in ("000000.depth.npz", "000000.torch", "000001.depth.npz", "000001.torch", "index.json")
  ]
  assert json.loads((tmp_path / "train" / "index.json").read_text()) == index["train"]
  assert len(index["train"]) == 3 and len(index["test"]) == 1
  scenes_read = read_chunk(tmp_path / "train" / "000001.torch")
  assert [s["key"] for s in scenes_read] == ["synthetic9_train_000002"]
  expected = render_re10k_like_scene(9, "train", 2, H, W, 4, config)
  got = scenes_read[0]
  np.testing.assert_allclose(got["c2w"], expected["c2w"], atol=2e-5)
  np.testing.assert_allclose(got["intrinsics"], expected["intrinsics"], rtol=1e-5)
  assert got["images"].shape == (4, H, W, 3)
  assert np.abs(got["images"].astype(float) - expected["images"]).mean() < 4.0  # JPEG q95


def test_generated_dataset_batches_through_the_chunked_source_and_pipeline(tmp_path):
  from tokengs_jax.data.chunked import ChunkedSceneSource
  from tokengs_jax.data.pipeline import ExampleConfig, InputPipeline
  from tokengs_jax.data.sampler import BoundedSamplerConfig

  generate_re10k_like(
    tmp_path,
    num_train=2,
    num_test=0,
    height=H,
    width=W,
    frames=8,
    seed=1,
    config=Re10kLikeConfig(supersample=1),
  )
  source = ChunkedSceneSource(tmp_path / "train")
  assert len(source) == 2
  # Synthetic clips are short (each frame moves further than an RE10K frame): a scaled-down sampler.
  config = ExampleConfig(image_shape=(16, 16), sampler=BoundedSamplerConfig(2, 3, 3, 7, 0, 0, 3, 7))
  pipeline = InputPipeline(
    source, config, batch_size=2, seed=0, num_epochs=1, shard_index=0, shard_count=1
  )
  batch = next(iter(pipeline))
  assert batch["context_images"].shape == (2, 2, 16, 16, 3) and batch["target_c2w"].shape == (
    2,
    3,
    4,
    4,
  )
  assert np.isfinite(batch["context_c2w"]).all() and 0.0 <= batch["context_images"].min() <= 1.0


def test_splits_record_true_depths_beside_their_chunks(tmp_path):
  generate.generate_re10k_like(
    tmp_path, 2, 2, 12, 16, frames=4, config=generate.Re10kLikeConfig(supersample=1)
  )
  assert list((tmp_path / "train").glob("*.depth.npz"))  # every split: the depth loss reads them
  chunk = tmp_path / "test" / "000000.torch"
  scene = generate.render_re10k_like_scene(
    0, "test", 1, 12, 16, 4, generate.Re10kLikeConfig(supersample=1)
  )
  depths = generate.read_true_depths(chunk, scene["key"])
  np.testing.assert_allclose(depths, scene["depths"], rtol=1e-3)  # stored as float16
  assert generate.read_true_depths(chunk, "no such scene") is None
  assert generate.read_true_depths(tmp_path / "train" / "000000.torch", scene["key"]) is None
  (tmp_path / "test" / "000000.depth.npz").unlink()  # real data: no depth recorded
  assert generate.read_true_depths(chunk, scene["key"]) is None
