"""Zip archives (`chunks.archive`): a truncated or non-zip file is refused naming it, and lazy
frames load from many threads past the open-file cache."""

import concurrent.futures

import pytest
from chunk_scenes import chunk_scene as _scene

from tokengs_jax.data import chunks
from tokengs_jax.data.chunks import ChunkError, read_chunk, write_chunk


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


@pytest.mark.parametrize("content", [b"", b"not a zip at all", None])
def test_truncated_or_non_chunk_file(tmp_path, content):
  path = tmp_path / "bad.torch"
  if content is None:  # a real chunk cut in half
    write_chunk(path, [_scene()])
    content = path.read_bytes()[: path.stat().st_size // 2]
  path.write_bytes(content)
  with pytest.raises(ChunkError, match="bad.torch"):
    read_chunk(path)
