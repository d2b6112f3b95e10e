"""Chunk files <-> scene records: camera rows, scene validation, and the JPEG frames.

`read_chunk`/`scan_chunk` turn the scene dicts of a chunk (`key`, `url`, `timestamps`,
`cameras` [F, 18], `images` JPEG byte tensors) into validated scene records with camera-to-world
poses and pixel intrinsics; `write_chunk` does the inverse. A malformed scene is a `ChunkError`
naming the file and the scene.
"""

from __future__ import annotations

import io
import os
from typing import Iterable, Literal, Mapping

import numpy as np
from PIL import Image

from tokengs_jax.data.chunks.archive import ChunkError
from tokengs_jax.data.chunks.storage import LazyTensor
from tokengs_jax.data.chunks.unpickler import load_tensor_archive
from tokengs_jax.data.chunks.writer import save_tensor_archive
from tokengs_jax.data.transforms import rigid_inverse

CAMERA_ROW_LENGTH = 18


def jpeg_size(data: bytes | np.ndarray, *, where: str = "") -> tuple[int, int]:
  """(height, width) from a JPEG header without decoding the pixels."""
  try:
    with Image.open(io.BytesIO(_as_bytes(data))) as image:
      width, height = image.size
  except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as error:
    raise ChunkError(f"{where}: not a decodable image ({error})") from error
  return height, width


def decode_jpeg(data: bytes | np.ndarray, *, where: str = "") -> np.ndarray:
  """JPEG bytes -> uint8 [H, W, 3]; `where` (file, scene, frame) is named in the error."""
  try:
    with Image.open(io.BytesIO(_as_bytes(data))) as image:
      return np.asarray(image.convert("RGB"))
  except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as error:
    raise ChunkError(f"{where}: corrupt image ({error})") from error


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


def _scene_from_record(record, path: str, position: int, images_mode: str) -> dict:
  if not isinstance(record, Mapping) or not isinstance(record.get("key"), str):
    raise ChunkError(f"{path}: entry {position} is not a scene dict with a string 'key'")
  key = record["key"]
  where = f"{path} scene '{key}'"
  for field in ("cameras", "images"):
    if field not in record:
      raise ChunkError(f"{where}: missing field '{field}'")
  frames = record["images"]
  if not isinstance(frames, (list, tuple)) or not frames:
    raise ChunkError(f"{where}: 'images' must be a non-empty list of JPEG byte tensors")
  frames = list(frames)
  if not all(
    isinstance(frame, (LazyTensor, np.ndarray)) and frame.dtype == np.uint8 for frame in frames
  ):
    raise ChunkError(f"{where}: 'images' must hold uint8 tensors of JPEG bytes")
  if not isinstance(record["cameras"], (LazyTensor, np.ndarray)):
    raise ChunkError(f"{where}: 'cameras' must be a tensor")
  if images_mode != "lazy":
    frames = [_loaded(frame) for frame in frames]
  height, width = jpeg_size(_loaded(frames[0]), where=f"{where} frame 0")
  c2w, intrinsics = cameras_to_poses(_loaded(record["cameras"]), height, width, where=where)
  if len(frames) != c2w.shape[0]:
    raise ChunkError(f"{where}: {len(frames)} images but {c2w.shape[0]} camera rows")
  timestamps = _loaded(record.get("timestamps", np.arange(len(frames))))
  if not (
    isinstance(timestamps, np.ndarray)
    and timestamps.shape == (len(frames),)
    and np.issubdtype(timestamps.dtype, np.integer)
  ):
    raise ChunkError(f"{where}: 'timestamps' must be an integer tensor [{len(frames)}]")
  timestamps = timestamps.astype(np.int64)
  if images_mode == "decode":
    decoded = [decode_jpeg(f, where=f"{where} frame {i}") for i, f in enumerate(frames)]
    shapes = {d.shape for d in decoded}
    if len(shapes) != 1:
      raise ChunkError(f"{where}: frames differ in size {sorted(shapes)}")
    frames = np.stack(decoded)
  return {
    "key": key,
    "url": str(record.get("url", "")),
    "timestamps": timestamps,
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
  when it has one). Raises `ChunkError` when the file as a whole is unreadable.
  """
  path = str(path)
  content = load_tensor_archive(path, lazy=True)
  if not isinstance(content, list):
    raise ChunkError(f"{path}: a chunk holds a list of scenes, found {type(content).__name__}")
  scenes = []
  for position, record in enumerate(content):
    try:
      scenes.append(_scene_from_record(record, path, position, images))
    except ChunkError as error:
      key = record.get("key") if isinstance(record, Mapping) else None
      error.scene_key = key if isinstance(key, str) else None
      scenes.append(error)
  return scenes


def read_chunk(
  path: str | os.PathLike, *, images: Literal["decode", "bytes", "lazy"] = "decode"
) -> list[dict]:
  """Reads a pixelSplat-format chunk into scenes.

  Returns a list of dicts with `key` str, `url` str, `timestamps` int64 [F], `c2w` [F, 4, 4]
  float32 (camera-to-world, OpenCV), `intrinsics` [F, 4] float32 (fx, fy, cx, cy in pixels of the
  stored images), `height`, `width` and `images`: uint8 [F, H, W, 3] (`"decode"`), the F encoded
  JPEGs as uint8 1-D arrays (`"bytes"`), or F `LazyTensor`s whose `load()` reads one JPEG
  (`"lazy"`: reads only the pickle, the cameras and frame 0). Raises `ChunkError` naming the file
  and scene on any malformed content (`scan_chunk` keeps the good scenes of a chunk instead).
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
