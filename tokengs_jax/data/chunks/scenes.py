"""Chunk files <-> scene records: camera rows, scene validation, and the JPEG frames.

`read_chunk`/`scan_chunk` turn the scene dicts of a chunk (`key`, `url`, `timestamps`,
`cameras` [F, 18], `images` JPEG byte tensors) into validated scene records with camera-to-world
poses and pixel intrinsics; `write_chunk` does the inverse. A malformed scene is a `ChunkError`
naming the file and the scene.
"""

from __future__ import annotations

import dataclasses
import io
import os
from typing import Iterable, Literal, Mapping

import numpy as np
from PIL import Image

from tokengs_jax.data.chunks.archive import ChunkError
from tokengs_jax.data.chunks.images import check_frame_bytes, decode_image, image_size
from tokengs_jax.data.chunks.storage import LazyTensor
from tokengs_jax.data.chunks.unpickler import load_tensor_archive
from tokengs_jax.data.chunks.writer import save_tensor_archive
from tokengs_jax.data.transforms import rigid_inverse

CAMERA_ROW_LENGTH = 18
# Bounds on what a chunk decodes to, checked on the pickle's declared shapes before any tensor is
# read (a scene's cameras decode to ~400 bytes a frame): far above any real chunk (RE10K and DL3DV
# scenes have hundreds of frames, a chunk tens of scenes), far below what exhausts a host.
MAX_SCENE_FRAMES = 100_000
MAX_CHUNK_SCENES = 10_000


def jpeg_size(data: bytes | np.ndarray, *, where: str = "") -> tuple[int, int]:
  """(height, width) from a JPEG header without decoding the pixels; `ChunkError` naming `where`
  (file, scene, frame) for a corrupt header or one above `MAX_FRAME_PIXELS`."""
  return image_size(_as_bytes(data), where=where)


def decode_jpeg(data: bytes | np.ndarray, *, where: str = "") -> np.ndarray:
  """JPEG bytes -> uint8 [H, W, 3]; `ChunkError` naming `where` (file, scene, frame) for a corrupt
  image or one whose header declares more than `MAX_FRAME_PIXELS`."""
  return decode_image(_as_bytes(data), where=where, mode="RGB")


def encode_jpeg(image: np.ndarray, quality: int = 95) -> bytes:
  """uint8 [H, W, 3] -> JPEG bytes (4:4:4, no chroma subsampling: small synthetic images keep
  their colour edges)."""
  buffer = io.BytesIO()
  Image.fromarray(np.asarray(image, np.uint8), "RGB").save(
    buffer, format="JPEG", quality=quality, subsampling=0
  )
  return buffer.getvalue()


def _as_bytes(data: bytes | np.ndarray) -> bytes:
  return data.tobytes() if isinstance(data, np.ndarray) else bytes(data)


def cameras_to_poses(cameras: np.ndarray, height: int, width: int, *, where: str = ""):
  """Chunk camera rows -> (c2w [F, 4, 4] float32, intrinsics [F, 4] float32 in pixels).

  cameras: [F, 18] = fx/W, fy/H, cx/W, cy/H, two unused, row-major 3x4 world-to-camera.
  """
  cameras = np.asarray(cameras)
  if cameras.ndim != 2 or cameras.shape[1] != CAMERA_ROW_LENGTH:
    raise ChunkError(
      f"{where}: cameras must be [F, {CAMERA_ROW_LENGTH}], got {list(cameras.shape)}"
    )
  if not np.isfinite(cameras).all():
    bad = sorted(set(np.nonzero(~np.isfinite(cameras))[0].tolist()))
    raise ChunkError(f"{where}: NaN/inf in the cameras of frames {bad}")
  focal = cameras[:, :2]
  if (focal <= 0).any():
    bad = sorted(set(np.nonzero(focal <= 0)[0].tolist()))
    raise ChunkError(
      f"{where}: non-positive focal length (fx/W, fy/H) in the cameras of frames {bad}"
    )
  w2c = np.zeros((cameras.shape[0], 4, 4), np.float64)
  w2c[:, :3, :] = cameras[:, 6:].reshape(-1, 3, 4)
  w2c[:, 3, 3] = 1.0
  intrinsics = cameras[:, :4].astype(np.float64) * np.array([width, height, width, height])
  return rigid_inverse(w2c).astype(np.float32), intrinsics.astype(np.float32)


def poses_to_cameras(
  c2w: np.ndarray, intrinsics: np.ndarray, height: int, width: int
) -> np.ndarray:
  """Inverse of `cameras_to_poses`: -> cameras [F, 18] float32."""
  frames = c2w.shape[0]
  cameras = np.zeros((frames, CAMERA_ROW_LENGTH), np.float64)
  cameras[:, :4] = np.asarray(intrinsics, np.float64) / np.array([width, height, width, height])
  cameras[:, 6:] = rigid_inverse(c2w)[:, :3, :].reshape(frames, 12)
  return cameras.astype(np.float32)


def _loaded(value):
  return value.load() if isinstance(value, LazyTensor) else value


def _check_frame_size(data, index: int, height: int, width: int, where: str) -> None:
  """`ChunkError` unless frame `index`'s JPEG header says `height` x `width` (frame 0's size: the
  intrinsics are in its pixels, and the frames of a view selection are stacked)."""
  size = jpeg_size(data, where=f"{where} frame {index}")
  if size != (height, width):
    raise ChunkError(
      f"{where} frame {index}: {size[0]}x{size[1]} pixels, frame 0 is {height}x{width}"
    )


@dataclasses.dataclass(frozen=True)
class LazyFrame(LazyTensor):
  """A lazy JPEG frame whose `load()` also checks its size against frame 0's: a lazy scan reads
  only frame 0, so a frame of another size is found when a sample reads it, as a `ChunkError`
  naming the file, scene and frame."""

  index: int
  height: int
  width: int
  where: str  # file and scene

  def load(self) -> np.ndarray:
    data = super().load()
    _check_frame_size(data, self.index, self.height, self.width, self.where)
    return data


def _checked_tensor(value, shape: tuple, integer: bool, what: str, where: str):
  """`value` if it is a tensor (loaded or lazy) of `shape` (and integer dtype if `integer`), checked
  before a byte of it is read: a forged shape cannot make the reader decode more."""
  if not (
    isinstance(value, (LazyTensor, np.ndarray))
    and tuple(value.shape) == shape
    and (not integer or np.issubdtype(value.dtype, np.integer))
  ):
    kind = "an integer tensor" if integer else "a tensor"
    found = (
      list(value.shape) if isinstance(value, (LazyTensor, np.ndarray)) else type(value).__name__
    )
    raise ChunkError(f"{where}: '{what}' must be {kind} {list(shape)}, got {found}")
  return value


def _checked_frames(record: Mapping, where: str) -> list:
  frames = record["images"]
  if not isinstance(frames, (list, tuple)) or not frames:
    raise ChunkError(f"{where}: 'images' must be a non-empty list of JPEG byte tensors")
  if len(frames) > MAX_SCENE_FRAMES:
    raise ChunkError(
      f"{where}: {len(frames)} frames, more than MAX_SCENE_FRAMES {MAX_SCENE_FRAMES}"
    )
  if not all(
    isinstance(frame, (LazyTensor, np.ndarray))
    and frame.dtype == np.uint8
    and len(frame.shape) == 1
    for frame in frames
  ):
    raise ChunkError(f"{where}: 'images' must hold uint8 1-D tensors of JPEG bytes")
  for index, frame in enumerate(frames):  # uint8: elements are bytes; `load` reads the storage
    stored = frame.storage.numel if isinstance(frame, LazyTensor) else frame.size
    check_frame_bytes(stored, where=f"{where} frame {index}")
  return list(frames)


def _scene_from_record(record, path: str, position: int, images_mode: str) -> dict:
  if not isinstance(record, Mapping) or not isinstance(record.get("key"), str):
    raise ChunkError(f"{path}: entry {position} is not a scene dict with a string 'key'")
  key = record["key"]
  where = f"{path} scene '{key}'"
  for field in ("cameras", "images"):
    if field not in record:
      raise ChunkError(f"{where}: missing field '{field}'")
  frames = _checked_frames(record, where)
  count = len(frames)
  cameras = _checked_tensor(record["cameras"], (count, CAMERA_ROW_LENGTH), False, "cameras", where)
  timestamps = _checked_tensor(
    record.get("timestamps", np.arange(count)), (count,), True, "timestamps", where
  )
  height, width = jpeg_size(_loaded(frames[0]), where=f"{where} frame 0")
  c2w, intrinsics = cameras_to_poses(_loaded(cameras), height, width, where=where)
  if images_mode == "lazy":
    frames = [  # `scan_chunk` loads the pickle lazily: every tensor is a `LazyTensor`
      LazyFrame(f.storage, f.offset, f.shape, f.stride, i, height, width, where)
      for i, f in enumerate(frames)
    ]
  else:
    frames = [_loaded(frame) for frame in frames]
    for index, frame in enumerate(frames):
      _check_frame_size(frame, index, height, width, where)
  if images_mode == "decode":
    frames = np.stack([decode_jpeg(f, where=f"{where} frame {i}") for i, f in enumerate(frames)])
  return {
    "key": key,
    "url": str(record.get("url", "")),
    "timestamps": _loaded(timestamps).astype(np.int64),
    "c2w": c2w,
    "intrinsics": intrinsics,
    "images": frames,
    "height": int(height),
    "width": int(width),
  }


def scan_chunk(
  path: str | os.PathLike, *, images: Literal["decode", "bytes", "lazy"] = "lazy"
) -> list[dict | ChunkError]:
  """Reads a pixelSplat-format chunk scene by scene: one bad scene costs only that scene.

  Returns, in file order, each scene (as `read_chunk`) or the `ChunkError` saying why that scene
  is unusable (NaN camera, corrupt frame 0, ...; its `scene_key` attribute holds the scene's key
  when it has one), detached from its traceback (`ChunkError.detached`), so a cached scan holds
  no arrays of its rejected scenes. Raises `ChunkError` when the file as a whole is unreadable,
  including one of more than `MAX_CHUNK_SCENES` entries.
  """
  path = str(path)
  content = load_tensor_archive(path, lazy=True)
  if not isinstance(content, list):
    raise ChunkError(f"{path}: a chunk holds a list of scenes, found {type(content).__name__}")
  if len(content) > MAX_CHUNK_SCENES:
    raise ChunkError(
      f"{path}: {len(content)} entries, more than MAX_CHUNK_SCENES {MAX_CHUNK_SCENES}"
    )
  scenes = []
  for position, record in enumerate(content):
    try:
      scenes.append(_scene_from_record(record, path, position, images))
    except ChunkError as error:
      key = record.get("key") if isinstance(record, Mapping) else None
      rejection = error.detached()
      rejection.scene_key = key if isinstance(key, str) else None
      scenes.append(rejection)
  return scenes


def read_chunk(
  path: str | os.PathLike, *, images: Literal["decode", "bytes", "lazy"] = "decode"
) -> list[dict]:
  """Reads a pixelSplat-format chunk into scenes.

  Returns a list of dicts with `key` str, `url` str, `timestamps` int64 [F], `c2w` [F, 4, 4]
  float32 (camera-to-world, OpenCV), `intrinsics` [F, 4] float32 (fx, fy, cx, cy in pixels of the
  stored images), `height`, `width` and `images`: uint8 [F, H, W, 3] (`"decode"`), the F encoded
  JPEGs as uint8 1-D arrays (`"bytes"`), or F `LazyFrame`s whose `load()` reads one JPEG
  (`"lazy"`: reads only the pickle, the cameras and frame 0). Every frame must have frame 0's
  size (checked when read: on `load()` for lazy frames). Raises `ChunkError` naming the file and
  scene (and frame) on any malformed content (`scan_chunk` keeps the good scenes of a chunk
  instead).
  """
  scenes = scan_chunk(path, images=images)
  for scene in scenes:
    if isinstance(scene, ChunkError):
      raise scene
  return scenes


def _scene_to_record(scene: Mapping, jpeg_quality: int) -> dict:
  key = scene["key"]
  c2w = np.asarray(scene["c2w"], np.float64)
  intrinsics = np.asarray(scene["intrinsics"], np.float64)
  frames = c2w.shape[0]
  if c2w.shape != (frames, 4, 4) or intrinsics.shape != (frames, 4):
    raise ValueError(
      f"scene '{key}': c2w must be [F, 4, 4] and intrinsics [F, 4], got "
      f"{list(c2w.shape)} and {list(intrinsics.shape)}"
    )
  images = scene["images"]
  if isinstance(images, np.ndarray):
    if images.dtype != np.uint8 or images.ndim != 4 or images.shape[-1] != 3:
      raise ValueError(
        f"scene '{key}': images must be uint8 [F, H, W, 3], got {images.dtype} {list(images.shape)}"
      )
    encoded = [encode_jpeg(image, jpeg_quality) for image in images]
  else:
    encoded = [_as_bytes(data) for data in images]
  if len(encoded) != frames:
    raise ValueError(f"scene '{key}': {len(encoded)} images for {frames} cameras")
  height, width = jpeg_size(encoded[0], where=f"scene '{key}' frame 0")
  timestamps = np.asarray(scene.get("timestamps", np.arange(frames)), np.int64)
  return {
    "url": str(scene.get("url", "")),
    "timestamps": timestamps,
    "cameras": poses_to_cameras(c2w, intrinsics, height, width),
    "images": [np.frombuffer(data, np.uint8) for data in encoded],
    "key": str(key),
  }


def write_chunk(
  path: str | os.PathLike, scenes: Iterable[Mapping], *, jpeg_quality: int = 95
) -> None:
  """Writes scenes as a pixelSplat-format chunk that `torch.load` and `read_chunk` both read.

  Each scene: `key` str, optional `url` str, optional `timestamps` int64 [F] (default 0..F-1),
  `c2w` [F, 4, 4] (camera-to-world, OpenCV), `intrinsics` [F, 4] (pixels), and `images` either
  uint8 [F, H, W, 3] (JPEG-encoded here at `jpeg_quality`) or a sequence of F JPEG byte strings.
  """
  save_tensor_archive(path, [_scene_to_record(scene, jpeg_quality) for scene in scenes])
