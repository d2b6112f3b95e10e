"""Chunk files <-> scene records (`chunks.scenes`): the torch-written fixture, round trips, lazy
and raw frames, and bad cameras or frames refused naming file, scene and frame."""

import json
import re

import numpy as np
import pytest
from chunk_scenes import chunk_scene as _scene
from conftest import reference_fixture

from tokengs_jax.data import (
  BoundedSamplerConfig,
  ChunkedSceneSource,
  ExampleConfig,
  InputPipeline,
  chunks,
)
from tokengs_jax.data.chunks import ChunkError, read_chunk, write_chunk


def test_reads_torch_written_fixture_with_true_cameras():
  truth = np.load(reference_fixture("re10k_tiny", "test", "truth.npz"))
  scenes = read_chunk(reference_fixture("re10k_tiny", "test", "000000.torch"))
  assert [s["key"] for s in scenes] == list(truth["keys"])
  for scene, c2w, intrinsics in zip(scenes, truth["c2w"], truth["intrinsics"]):
    np.testing.assert_allclose(scene["c2w"], c2w, atol=2e-6)
    np.testing.assert_allclose(scene["intrinsics"], intrinsics, rtol=1e-6, atol=1e-5)
    assert scene["images"].shape == (6, 36, 64, 3) and scene["images"].dtype == np.uint8
    # gradient images: red ramps along x, green along y (JPEG-lossy)
    assert scene["images"][0, :, -1, 0].mean() > scene["images"][0, :, 0, 0].mean() + 150
    assert scene["images"][0, -1, :, 1].mean() > scene["images"][0, 0, :, 1].mean() + 150
  index = json.loads((reference_fixture("re10k_tiny", "test", "index.json")).read_text())
  assert set(index) == {s["key"] for s in scenes}


def test_write_read_round_trip(tmp_path):
  scenes = [_scene("a", seed=1), _scene("b", frames=4, seed=2)]
  write_chunk(tmp_path / "000000.torch", scenes)
  loaded = read_chunk(tmp_path / "000000.torch")
  for scene, back in zip(scenes, loaded):
    assert back["key"] == scene["key"] and back["url"] == scene["url"]
    np.testing.assert_array_equal(back["timestamps"], scene["timestamps"])
    np.testing.assert_allclose(back["c2w"], scene["c2w"], atol=1e-6)
    np.testing.assert_allclose(back["intrinsics"], scene["intrinsics"], rtol=1e-6)
    assert np.abs(back["images"].astype(int) - scene["images"]).max() <= 8  # JPEG quality 95


def test_jpeg_bytes_are_stored_verbatim_and_lazy_frames_load(tmp_path):
  scene = _scene()
  scene["images"] = [chunks.encode_jpeg(image) for image in scene["images"]]
  write_chunk(tmp_path / "c.torch", [scene])
  (lazy,) = read_chunk(tmp_path / "c.torch", images="lazy")
  assert isinstance(lazy["images"][2], chunks.LazyTensor)
  assert lazy["images"][2].load().tobytes() == scene["images"][2]
  (raw,) = read_chunk(tmp_path / "c.torch", images="bytes")
  assert [f.tobytes() for f in raw["images"]] == scene["images"]


def _rewrite_record(tmp_path, mutate):
  """Writes a chunk via the raw record layer after `mutate(record)`."""
  record = chunks.scenes._scene_to_record(_scene("sceneX"), 95)
  mutate(record)
  path = tmp_path / "000001.torch"
  chunks.save_tensor_archive(path, [record])
  return path


def test_wrong_camera_row_length_names_file_and_scene(tmp_path):
  path = _rewrite_record(tmp_path, lambda r: r.update(cameras=r["cameras"][:, :17].copy()))
  with pytest.raises(
    ChunkError,
    match=r"000001\.torch scene 'sceneX': 'cameras' must be a tensor \[3, 18\], got \[3, 17\]",
  ):
    read_chunk(path)


def test_nan_pose_names_file_scene_and_frame(tmp_path):
  def poison(record):
    record["cameras"][1, 9] = np.nan

  path = _rewrite_record(tmp_path, poison)
  with pytest.raises(ChunkError, match=r"scene 'sceneX'.*NaN/inf.*frames \[1\]"):
    read_chunk(path)


def test_corrupt_jpeg_names_file_scene_and_frame(tmp_path):
  def corrupt(record):
    record["images"][2] = np.frombuffer(b"\xff\xd8garbage" * 10, np.uint8)

  path = _rewrite_record(tmp_path, corrupt)
  with pytest.raises(ChunkError, match=r"000001\.torch scene 'sceneX' frame 2"):
    read_chunk(path)
  (lazy,) = read_chunk(path, images="lazy")  # lazy reading defers the failure to the decode
  with pytest.raises(ChunkError, match="frame 2"):
    chunks.decode_jpeg(lazy["images"][2].load(), where=f"{path} scene 'sceneX' frame 2")


def test_a_frame_of_another_size_is_a_rejection_naming_scene_and_frame(tmp_path):
  frames = [chunks.encode_jpeg(image) for image in _scene(height=12, width=20)["images"]]
  frames[2] = chunks.encode_jpeg(_scene(height=16, width=16)["images"][2])
  write_chunk(tmp_path / "000000.torch", [_scene("good"), {**_scene("odd"), "images": frames}])
  message = r"000000\.torch scene 'odd' frame 2: 16x16 pixels, frame 0 is 12x20"
  for images in ("bytes", "decode"):  # every frame's bytes are read: refused when scanned
    with pytest.raises(ChunkError, match=message):
      read_chunk(tmp_path / "000000.torch", images=images)
  source = ChunkedSceneSource(tmp_path, skip_bad=True)  # lazy: refused when the frame is read
  with pytest.raises(ChunkError, match=message):
    source[source.keys.index("odd")]["images"][2].load()
  pipeline = InputPipeline(
    source,
    ExampleConfig((8, 8), BoundedSamplerConfig(2, 1, 2, 2, 0, 0, 2, 2), 0.25),
    batch_size=1,
    shard_index=0,
    shard_count=1,
    num_epochs=1,
    shuffle=False,
    skip_bad=True,
    select_views=lambda record, rng, step: (np.array([0, 2]), np.array([1])),
  )
  assert [int(b["scene_index"][0]) for b in pipeline] == [source.keys.index("good")]
  assert dict(pipeline.rejections.counts) == {"ChunkError": 1}
  assert re.search(message, pipeline.rejections.messages[-1])
