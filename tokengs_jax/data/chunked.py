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

from tokengs_jax.data.chunks import ChunkError, check_regular_file, scan_chunk
from tokengs_jax.data.rejections import Rejections
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
    skip_bad: drop unreadable chunks, malformed scenes (one scene at a time: a chunk's good scenes
      are kept), keys missing from the index and index entries that are not regular files inside
      `root`, instead of raising. Each is counted and logged in `rejections`.
    min_frames: scenes with fewer frames are dropped, counted and logged (pixelSplat skips them too).

  Raises `ChunkError` for the first bad chunk, scene or index entry without `skip_bad`, and
  `MissingIndexEntryError` for a requested key the index does not list.
  """

  def __init__(
    self,
    root: str | os.PathLike,
    *,
    keys: Iterable[str] | None = None,
    skip_bad: bool = False,
    min_frames: int = 1,
  ):
    self.root = pathlib.Path(root)
    self.skip_bad = skip_bad
    self.rejections = Rejections(f"source {self.root}")
    if keys is None:
      chunk_paths = sorted(self.root.glob("*.torch"))
      wanted = None
    else:
      index = self._read_index()
      wanted, chunk_paths = [], set()
      for key in keys:
        if key not in index:
          self._bad(
            "missing_index_entry",
            MissingIndexEntryError(f"{self.root / 'index.json'}: scene '{key}' has no entry"),
          )
          continue
        try:
          chunk_paths.add(self._inside_root(index[key], f"scene '{key}'"))
        except ChunkError as error:
          self._bad("bad_index_entry", error)
          continue
        wanted.append(key)
      chunk_paths = sorted(chunk_paths)
    by_key, rejected, unreadable = {}, set(), set()  # rejected: keys of bad scenes
    for chunk_path in chunk_paths:
      try:
        self._inside_root(chunk_path.name, "chunk")  # a symlink may not lead out of the root
        scenes = scan_chunk(chunk_path)
      except ChunkError as error:
        unreadable.add(chunk_path)
        self._bad("bad_chunk", error)
        continue
      for position, scene in enumerate(scenes):
        if isinstance(scene, ChunkError):
          rejected.add(scene.scene_key)
          self._bad("bad_scene", scene)
        elif len(scene["images"]) < min_frames:
          self._bad(
            "too_few_frames",
            ChunkError(
              f"{chunk_path} scene '{scene['key']}': {len(scene['images'])} frames, fewer than "
              f"min_frames {min_frames}"
            ),
            always_skip=True,
          )
        else:
          by_key[scene["key"]] = SceneEntry(
            scene["key"], str(chunk_path), position, len(scene["images"])
          )
    if wanted is None:
      self.entries = list(by_key.values())
    else:
      self.entries = [by_key[key] for key in wanted if key in by_key]
      for key in wanted:  # a key whose scene or chunk was rejected is counted already
        if key not in by_key and key not in rejected and self.root / index[key] not in unreadable:
          self._bad(
            "missing_scene",
            ChunkError(
              f"{self.root / index[key]}: scene '{key}' listed in index.json is not in its chunk"
            ),
          )
    self._cache: collections.OrderedDict = collections.OrderedDict()

  def _read_index(self) -> dict:
    path = self.root / "index.json"
    if not path.exists():
      raise FileNotFoundError(f"{path}: needed to find scenes by key")
    check_regular_file(path)
    try:
      index = json.loads(path.read_bytes())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
      raise ChunkError(f"{path}: not valid JSON ({error})") from error
    if not isinstance(index, dict):
      raise ChunkError(
        f"{path}: expected a scene key -> chunk file map, found {type(index).__name__}"
      )
    return index

  def _inside_root(self, name, what: str) -> pathlib.Path:
    """`root / name`, refused unless it stays inside the root once symlinks are resolved."""
    if not isinstance(name, str) or not name:
      raise ChunkError(f"{self.root / 'index.json'}: {what} has entry {name!r}, not a file name")
    path = self.root / name
    if not path.resolve().is_relative_to(self.root.resolve()):
      raise ChunkError(
        f"{self.root / 'index.json'}: {what} -> '{name}' resolves to "
        f"{path.resolve()}, outside the data root {self.root.resolve()}"
      )
    return path

  def _bad(self, reason: str, error: Exception, *, always_skip: bool = False) -> None:
    if not (self.skip_bad or always_skip):
      raise error
    self.rejections.add(reason, str(error))

  def __len__(self) -> int:
    return len(self.entries)

  @property
  def keys(self) -> list[str]:
    """The scene keys, in item order."""
    return [entry.key for entry in self.entries]

  def __getitem__(self, index: int) -> dict:
    entry = self.entries[index]
    scenes = self._chunk(entry.chunk)
    scene = scenes[entry.position] if entry.position < len(scenes) else None
    # the scan found this scene here: anything else means the file changed since
    if isinstance(scene, ChunkError):
      raise scene.detached()  # the cached one, raised, would keep this call's traceback
    if not isinstance(scene, dict) or scene["key"] != entry.key:
      raise ChunkError(
        f"{entry.chunk}: scene '{entry.key}' is no longer at position {entry.position}"
      )
    return {**scene, "source": entry.chunk}

  def _chunk(self, path: str) -> list:
    """A per-process LRU of scanned chunks (cameras + lazy frame references, no pixels)."""
    key = (os.getpid(), path)
    if key not in self._cache:
      self._cache[key] = scan_chunk(path)
      while len(self._cache) > 16:
        self._cache.popitem(last=False)
    self._cache.move_to_end(key)
    return self._cache[key]

  def __getstate__(self):  # workers rebuild their own cache
    return {**self.__dict__, "_cache": collections.OrderedDict()}
