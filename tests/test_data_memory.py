"""Memory bounds on untrusted chunks (issue 28 part 9): what a chunk decodes to is bounded before
it is allocated, and a cached scan keeps no arrays of the scenes it rejected.

Allocations are measured with tracemalloc (numpy reports its buffers to it), which counts only
this process's Python and numpy allocations: deterministic, unlike the resident set size."""

import gc
import tracemalloc
import zipfile

import numpy as np
import pytest

from tokengs_jax.data import ChunkedSceneSource, chunks
from tokengs_jax.data.chunks import ChunkError

MiB = 1 << 20


def _scene(key, frames=3, size=8, seed=0):
  rng = np.random.default_rng(seed)
  c2w = np.tile(np.eye(4), (frames, 1, 1))
  c2w[:, :3, 3] = rng.normal(size=(frames, 3))
  return {
    "key": key,
    "c2w": c2w,
    "intrinsics": np.tile([10.0, 10.0, size / 2, size / 2], (frames, 1)),
    "images": rng.integers(0, 255, (frames, size, size, 3), dtype=np.uint8),
  }


def _record(key, **kwargs):
  return chunks.scenes._scene_to_record(_scene(key, **kwargs), 90)


def _deflate_storages(path):
  """Rewrites the chunk with its tensor records deflated: a large record in a small file."""
  with zipfile.ZipFile(path) as archive:
    records = {name: archive.read(name) for name in archive.namelist()}
  with zipfile.ZipFile(path, "w") as archive:
    for name, data in records.items():
      compress = zipfile.ZIP_DEFLATED if "/data/" in name else zipfile.ZIP_STORED
      archive.writestr(zipfile.ZipInfo(name), data, compress_type=compress)


def _peak_and_current(function):
  """(function's result or raised exception, peak bytes, bytes still held after gc)."""
  gc.collect()
  tracemalloc.start()
  try:
    result = function()
  except ChunkError as error:
    result = error
  gc.collect()
  current, peak = tracemalloc.get_traced_memory()
  tracemalloc.stop()
  return result, peak, current


def test_a_forged_camera_record_is_refused_before_it_is_read(tmp_path):
  # 3 frames, but a camera record of 64 MiB: [932067, 18] float32 (in a 230 KB file); reading
  # and converting it first took ~400 MB (1.7 GB from a 3.6 MB file at the 256 MiB record limit)
  record = _record("forged")
  record["cameras"] = np.zeros((64 * MiB // 72, 18), np.float32)
  record["cameras"][:, :2] = 1.0  # positive focal lengths: valid rows, only too many
  chunks.save_tensor_archive(tmp_path / "000000.torch", [_record("good"), record])
  _deflate_storages(tmp_path / "000000.torch")
  scenes, peak, _ = _peak_and_current(lambda: chunks.scan_chunk(tmp_path / "000000.torch"))
  assert peak < 8 * MiB
  assert scenes[0]["key"] == "good"
  assert "scene 'forged': 'cameras' must be a tensor [3, 18], got [932067, 18]" in str(scenes[1])


def test_a_scene_of_more_frames_than_the_bound_is_refused_before_its_cameras_are_read(
  tmp_path, monkeypatch
):
  monkeypatch.setattr(chunks.scenes, "MAX_SCENE_FRAMES", 4)
  chunks.save_tensor_archive(tmp_path / "000000.torch", [_record("long", frames=5)])
  (rejection,) = chunks.scan_chunk(tmp_path / "000000.torch")
  assert "scene 'long': 5 frames, more than MAX_SCENE_FRAMES 4" in str(rejection)


def test_pickle_decoding_is_bounded_by_an_opcode_budget(tmp_path, monkeypatch):
  # each 1-byte "]" makes a list: an 8 KB file of them (8 MiB inflated) took 9 GB and 86 s
  path = tmp_path / "lists.torch"
  with zipfile.ZipFile(path, "w") as archive:
    payload = b"\x80\x02](" + b"]" * 30_000 + b"e."
    archive.writestr(zipfile.ZipInfo("lists/data.pkl"), payload, zipfile.ZIP_DEFLATED)
  monkeypatch.setattr(chunks.unpickler, "MAX_PICKLE_OPCODES", 20_000)
  with pytest.raises(ChunkError, match=r"lists\.torch: the pickle runs more than .* 20000 opcodes"):
    chunks.scan_chunk(path)
  # within the budget, a list of more entries than a chunk holds scenes is refused as a whole
  # (one rejection per entry was ~1 KB each, a traceback with it)
  monkeypatch.setattr(chunks.unpickler, "MAX_PICKLE_OPCODES", 40_000)
  monkeypatch.setattr(chunks.scenes, "MAX_CHUNK_SCENES", 10_000)
  with pytest.raises(ChunkError, match=r"30000 entries, more than MAX_CHUNK_SCENES 10000"):
    chunks.scan_chunk(path)


def test_cached_rejections_hold_no_traceback_nor_the_arrays_of_their_scenes(tmp_path):
  # six scenes whose frame 0 is 4 MiB of garbage (deflated: a small file) next to a good one;
  # each rejection's traceback kept its frame's bytes resident (~50 MB after one read)
  records = [_record("good")] + [_record(f"bad{i}", seed=i) for i in range(6)]
  for record in records[1:]:
    record["images"][0] = np.frombuffer(b"not a JPEG" + bytes(4 * MiB), np.uint8)
  chunks.save_tensor_archive(tmp_path / "000000.torch", records)
  _deflate_storages(tmp_path / "000000.torch")

  def read_the_good_scene():
    source = ChunkedSceneSource(tmp_path, skip_bad=True)
    assert source.rejections.counts == {"bad_scene": 6}
    return source, source[0]

  (source, scene), _, held = _peak_and_current(read_the_good_scene)
  assert scene["key"] == "good"
  assert held < 2 * MiB
  (cached,) = source._cache.values()
  rejections = [entry for entry in cached if isinstance(entry, ChunkError)]
  assert [error.scene_key for error in rejections] == [f"bad{i}" for i in range(6)]
  for error in rejections:
    assert (error.__traceback__, error.__cause__, error.__context__) == (None, None, None)
    assert "frame 0: not a decodable image" in str(error)


def test_a_compressed_record_is_inflated_into_one_buffer(tmp_path):
  # zipfile's whole-member read concatenates its pieces: twice the record at a peak
  chunks.save_tensor_archive(tmp_path / "zeros.torch", np.zeros(16 * MiB, np.uint8))
  _deflate_storages(tmp_path / "zeros.torch")
  with zipfile.ZipFile(tmp_path / "zeros.torch") as archive:
    data, peak, _ = _peak_and_current(
      lambda: chunks.read_member(archive, "zeros/data/0", where="zeros.torch")
    )
  assert len(data) == 16 * MiB and not any(data[:: 1 << 16])
  assert peak < 1.3 * 16 * MiB
