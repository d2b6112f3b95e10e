"""Chunk files in the pixelSplat/MVSplat/DepthSplat layout, read and written without torch.

A chunk (`NNNNNN.torch`) is what `torch.save` writes for a list of scene dicts:
`key` str, `url` str, `timestamps` int64 [F], `cameras` float32 [F, 18] (fx/W, fy/H, cx/W, cy/H, two
unused, then the row-major 3x4 world-to-camera) and `images`, a list of uint8 1-D tensors holding
JPEG bytes. On disk that is a zip archive `<stem>/data.pkl` (a protocol-2 pickle whose tensors point
at raw little-endian storages `<stem>/data/<key>` through persistent ids) plus version records.

Reading never executes pickled code (`unpickler`: only the globals and opcodes a plain tensor
pickle needs, rebuilt as numpy); writing emits the same pickle opcodes `torch.save` emits
(`writer`), so `torch.load(path)` (weights_only or not) reads our files unchanged.

Modules: `archive` (bounded zip record reading, `ChunkError`), `storage` (typed storages and
`LazyTensor`), `unpickler` (`load_tensor_archive`), `writer` (`save_tensor_archive`), `scenes`
(chunk <-> scene records, JPEG helpers), `images` (bounded image decoding, which the DL3DV and
Kubric readers share).
"""

from tokengs_jax.data.chunks.archive import ChunkError, check_regular_file, open_zip, read_member
from tokengs_jax.data.chunks.scenes import (
  cameras_to_poses,
  decode_jpeg,
  encode_jpeg,
  jpeg_size,
  poses_to_cameras,
  read_chunk,
  scan_chunk,
  write_chunk,
)
from tokengs_jax.data.chunks.storage import LazyTensor
from tokengs_jax.data.chunks.unpickler import UnsafeChunkError, load_tensor_archive
from tokengs_jax.data.chunks.writer import save_tensor_archive

__all__ = [
  "ChunkError",
  "UnsafeChunkError",
  "check_regular_file",
  "open_zip",
  "read_member",
  "scan_chunk",
  "load_tensor_archive",
  "save_tensor_archive",
  "LazyTensor",
  "read_chunk",
  "write_chunk",
  "decode_jpeg",
  "encode_jpeg",
  "jpeg_size",
  "cameras_to_poses",
  "poses_to_cameras",
]
