"""RE10K and DL3DV scenes stored as pixelSplat chunks, as a random-access source.

A stage directory (`root/{train,test}`) holds `NNNNNN.torch` chunks and `index.json` (scene key ->
chunk file name). The source lists every scene once (reading only each chunk's pickle and camera
tensors) and, per item, returns a scene record whose frames are `LazyTensor`s: a sample reads and
decodes only the JPEGs of the views it uses.

A scene record (the contract the pipeline consumes, shared with the other sources):
  `key` str, `source` str (file, for messages), `c2w` [F, 4, 4], `intrinsics` [F, 4] (pixels of the
  stored frames), `height`, `width`, `images` (a length-F sequence of uint8 [H, W, 3] arrays, JPEG
  bytes or `LazyTensor`s of JPEG bytes), optionally `times` [F] float (dynamic scenes).
"""

from __future__ import annotations

import collections
import dataclasses
import json
import os
import pathlib
from typing import Iterable

from tokengs_jax.data.chunks import ChunkError, read_chunk
from tokengs_jax.data.sampler import MissingIndexEntryError

__all__ = ["ChunkedSceneSource", "SceneEntry"]


@dataclasses.dataclass(frozen=True)
class SceneEntry:
  key: str
  chunk: str
  position: int
  num_frames: int


class ChunkedSceneSource:
  """Random-access (grain `RandomAccessDataSource`) source of chunked scenes.

  Args:
    root: a stage directory holding `*.torch` chunks and `index.json`.
    keys: only these scenes, in this order (e.g. the keys of an evaluation index); the index finds
      their chunks, so the other chunks are never opened.
    skip_bad: drop (and count in `skipped`) unreadable chunks, malformed scenes and keys missing
      from the index, instead of raising.
    min_frames: scenes with fewer frames are dropped and counted (pixelSplat skips them too).
  """

  def __init__(self, root: str | os.PathLike, *, keys: Iterable[str] | None = None,
               skip_bad: bool = False, min_frames: int = 1):
    self.root = pathlib.Path(root)
    self.skip_bad = skip_bad
    self.skipped: collections.Counter = collections.Counter()
    self.skip_messages: list[str] = []
    index_path = self.root / "index.json"
    index = json.loads(index_path.read_text()) if index_path.exists() else None
    if keys is None:
      chunk_paths = sorted(self.root.glob("*.torch"))
      wanted = None
    else:
      wanted = list(keys)
      if index is None:
        raise FileNotFoundError(f"{index_path}: needed to find scenes by key")
      present = []
      for key in wanted:
        if key in index:
          present.append(key)
        else:
          self._bad("missing_index_entry", MissingIndexEntryError(
              f"{index_path}: scene '{key}' has no entry"))
      wanted = present
      chunk_paths = sorted({self.root / index[key] for key in wanted})
    by_key = {}
    for chunk_path in chunk_paths:
      try:
        scenes = read_chunk(chunk_path, images="lazy")
      except (ChunkError, FileNotFoundError) as error:
        self._bad("bad_chunk", error)
        continue
      for position, scene in enumerate(scenes):
        if len(scene["images"]) < min_frames:
          self.skipped["too_few_frames"] += 1
          continue
        by_key[scene["key"]] = SceneEntry(scene["key"], str(chunk_path), position, len(scene["images"]))
    if wanted is None:
      self.entries = list(by_key.values())
    else:
      self.entries = []
      for key in wanted:
        if key in by_key:
          self.entries.append(by_key[key])
        else:
          self._bad("missing_scene", ChunkError(f"{self.root / index[key]}: scene '{key}' listed "
                                                "in index.json is not in its chunk"))
    self._cache: collections.OrderedDict = collections.OrderedDict()

  def _bad(self, reason: str, error: Exception) -> None:
    if not self.skip_bad:
      raise error
    self.skipped[reason] += 1
    self.skip_messages.append(str(error))

  def __len__(self) -> int:
    return len(self.entries)

  def __getitem__(self, index: int) -> dict:
    entry = self.entries[index]
    scenes = self._chunk(entry.chunk)
    return {**scenes[entry.position], "source": entry.chunk}

  def _chunk(self, path: str) -> list[dict]:
    """A per-process LRU of parsed chunks (cameras + lazy frame references, no pixels)."""
    key = (os.getpid(), path)
    if key not in self._cache:
      self._cache[key] = read_chunk(path, images="lazy")
      while len(self._cache) > 16:
        self._cache.popitem(last=False)
    self._cache.move_to_end(key)
    return self._cache[key]

  def __getstate__(self):  # workers rebuild their own cache
    return {**self.__dict__, "_cache": collections.OrderedDict()}
