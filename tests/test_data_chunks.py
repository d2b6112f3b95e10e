"""Chunk reader/writer: the torch-written fixture, round trips, unsafe pickles and bad input."""

import concurrent.futures
import json
import os
import pickle
import re
import zipfile

import numpy as np
import pytest
from conftest import reference_fixture

from tokengs_jax.data import (
  BoundedSamplerConfig,
  ChunkedSceneSource,
  ExampleConfig,
  InputPipeline,
  chunks,
)
from tokengs_jax.data.chunks import ChunkError, UnsafeChunkError, read_chunk, write_chunk


def _scene(key="s0", frames=3, height=12, width=20, seed=0):
  rng = np.random.default_rng(seed)
  angles = rng.uniform(-0.3, 0.3, (frames, 3))
  c2w = np.tile(np.eye(4), (frames, 1, 1))
  for f, (_, b, c) in enumerate(angles):
    rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    c2w[f, :3, :3] = rz @ ry
    c2w[f, :3, 3] = rng.normal(size=3)
  intrinsics = np.tile([width * 0.9, height * 1.1, width / 2 + 0.3, height / 2 - 0.2], (frames, 1))
  ramp = np.linspace(0, 255, width, dtype=np.float32)
  images = np.zeros((frames, height, width, 3), np.uint8)
  images[..., 0] = ramp
  images[..., 1] = np.linspace(0, 255, height)[:, None]
  images[..., 2] = (np.arange(frames) * 40)[:, None, None]
  return {
    "key": key,
    "url": f"https://example.invalid/{key}",
    "c2w": c2w,
    "intrinsics": intrinsics,
    "images": images,
    "timestamps": np.arange(frames) * 1000,
  }


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


def test_lazy_frames_load_from_many_threads_past_the_open_file_cache(tmp_path, monkeypatch):
  """grain reads with threads: more chunk files than the cache holds, read concurrently, must
  neither race on the cache nor close an archive another thread is reading."""
  monkeypatch.setattr(chunks.archive, "_MAX_OPEN_ARCHIVES", 2)
  frames = []
  for number in range(6):
    scene = _scene(f"s{number}", seed=number)
    scene["images"] = [chunks.encode_jpeg(image) for image in scene["images"]]
    write_chunk(tmp_path / f"{number:06d}.torch", [scene])
    (lazy,) = read_chunk(tmp_path / f"{number:06d}.torch", images="lazy")
    frames += [(frame, scene["images"][i]) for i, frame in enumerate(lazy["images"])]

  def load_all(offset):
    return all(
      frames[(i + offset) % len(frames)][0].load().tobytes()
      == frames[(i + offset) % len(frames)][1]
      for i in range(len(frames) * 10)
    )

  with concurrent.futures.ThreadPoolExecutor(8) as pool:
    assert all(pool.map(load_all, range(8)))


def test_jpeg_bytes_are_stored_verbatim_and_lazy_frames_load(tmp_path):
  scene = _scene()
  scene["images"] = [chunks.encode_jpeg(image) for image in scene["images"]]
  write_chunk(tmp_path / "c.torch", [scene])
  (lazy,) = read_chunk(tmp_path / "c.torch", images="lazy")
  assert isinstance(lazy["images"][2], chunks.LazyTensor)
  assert lazy["images"][2].load().tobytes() == scene["images"][2]
  (raw,) = read_chunk(tmp_path / "c.torch", images="bytes")
  assert [f.tobytes() for f in raw["images"]] == scene["images"]


def test_tensor_archive_dtypes_and_containers(tmp_path):
  obj = {
    "f64": np.arange(6.0).reshape(2, 3),
    "b": np.array([True, False]),
    "i8": np.arange(-3, 3, dtype=np.int8),
    "t": np.arange(12, dtype=np.int32).reshape(3, 4).T,
    "e": np.zeros((0, 2), np.float32),
    "n": [None, 1.5, -7, 2**40, 70000, (1, "a"), ()],
  }
  chunks.save_tensor_archive(tmp_path / "m.torch", obj)
  back = chunks.load_tensor_archive(tmp_path / "m.torch")
  for key in ("f64", "b", "i8", "t", "e"):
    assert back[key].dtype == obj[key].dtype
    np.testing.assert_array_equal(back[key], obj[key])
  assert back["n"] == obj["n"]


class _Exploit:
  def __init__(self, marker):
    self.marker = marker

  def __reduce__(self):
    return (os.system, (f"touch {self.marker}",))


def _zip_with_pickle(path, payload: bytes):
  with zipfile.ZipFile(path, "w") as archive:
    archive.writestr("evil/data.pkl", payload)
    archive.writestr("evil/version", "3\n")


def test_malicious_pickle_is_refused_and_never_runs(tmp_path):
  marker = tmp_path / "pwned"
  path = tmp_path / "evil.torch"
  _zip_with_pickle(path, pickle.dumps([{"key": "x", "cameras": _Exploit(marker)}], protocol=2))
  with pytest.raises(UnsafeChunkError, match=r"evil\.torch.*posix\.system|evil\.torch.*os\.system"):
    read_chunk(path)
  assert not marker.exists()


def test_forged_tensor_geometry_is_refused(tmp_path):
  path = tmp_path / "forged.torch"
  chunks.save_tensor_archive(path, [np.arange(4, dtype=np.float32)])
  with zipfile.ZipFile(path) as archive:
    records = {n: archive.read(n) for n in archive.namelist()}
  name = "forged/data.pkl"
  forged = records[name].replace(b"K\x00(K\x04t", b"K\x00(M\x00\x10t")  # size (4,) -> (4096,)
  assert forged != records[name]
  records[name] = forged
  with zipfile.ZipFile(path, "w") as archive:
    for record, data in records.items():
      archive.writestr(record, data)
  with pytest.raises(ChunkError, match="forged.torch.*reaches element"):
    chunks.load_tensor_archive(path)


@pytest.mark.parametrize("content", [b"", b"not a zip at all", None])
def test_truncated_or_non_chunk_file(tmp_path, content):
  path = tmp_path / "bad.torch"
  if content is None:  # a real chunk cut in half
    write_chunk(path, [_scene()])
    content = path.read_bytes()[: path.stat().st_size // 2]
  path.write_bytes(content)
  with pytest.raises(ChunkError, match="bad.torch"):
    read_chunk(path)


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
