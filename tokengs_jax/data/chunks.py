"""Chunk files in the pixelSplat/MVSplat/DepthSplat layout, read and written without torch.

A chunk (`NNNNNN.torch`) is what `torch.save` writes for a list of scene dicts:
`key` str, `url` str, `timestamps` int64 [F], `cameras` float32 [F, 18] (fx/W, fy/H, cx/W, cy/H, two
unused, then the row-major 3x4 world-to-camera) and `images`, a list of uint8 1-D tensors holding
JPEG bytes. On disk that is a zip archive `<stem>/data.pkl` (a protocol-2 pickle whose tensors point
at raw little-endian storages `<stem>/data/<key>` through persistent ids) plus version records.

Reading never executes pickled code: `_TensorUnpickler.find_class` resolves only the few globals a
plain tensor pickle needs (the tensor rebuild function, typed storages, `OrderedDict`) to our own
numpy re-implementations, and refuses anything else naming the file. Writing emits the same pickle
opcodes `torch.save` emits, so `torch.load(path)` (weights_only or not) reads our files unchanged.
"""

from __future__ import annotations

import collections
import dataclasses
import hashlib
import io
import math
import os
import pathlib
import pickle
import stat
import struct
import zipfile
import zlib
from typing import Any, Iterable, Literal, Mapping

import ml_dtypes
import numpy as np
from PIL import Image

from tokengs_jax.data.transforms import rigid_inverse

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

CAMERA_ROW_LENGTH = 18

# torch typed-storage class name <-> numpy dtype (the names torch.save writes into the pickle)
_STORAGE_DTYPES = {
  "DoubleStorage": np.dtype(np.float64),
  "FloatStorage": np.dtype(np.float32),
  "HalfStorage": np.dtype(np.float16),
  "BFloat16Storage": np.dtype(ml_dtypes.bfloat16),
  "LongStorage": np.dtype(np.int64),
  "IntStorage": np.dtype(np.int32),
  "ShortStorage": np.dtype(np.int16),
  "CharStorage": np.dtype(np.int8),
  "ByteStorage": np.dtype(np.uint8),
  "BoolStorage": np.dtype(np.bool_),
}
_STORAGE_NAMES = {dtype: name for name, dtype in _STORAGE_DTYPES.items()}
_ALIGNMENT = 64  # torch aligns every record's payload to 64 bytes (enables mmap loading)


class ChunkError(ValueError):
  """A chunk file (or one scene in it) is malformed; the message names the file and scene."""


class UnsafeChunkError(ChunkError):
  """The pickle inside a chunk asks for a global that a plain tensor file never needs."""


# ----------------------------------------------------------------------------------------------
# Reading

# Allocation bounds, checked against a record's declared size before any byte is read: a forged
# archive cannot make the reader inflate more than this (torch stores records uncompressed, so a
# real chunk's records are bounded by the file itself).
MAX_PICKLE_BYTES = 256 << 20
MAX_INFLATED_RECORD_BYTES = 256 << 20


def check_regular_file(path: str | os.PathLike, *, where: str = "") -> None:
  """Raises `ChunkError` unless `path` is an existing regular file (after symlinks).

  Opening a FIFO blocks and /dev/zero never ends: data files must be plain files.
  """
  try:
    mode = os.stat(path).st_mode
  except OSError as error:
    raise ChunkError(f"{where or path}: cannot open ({error.strerror or error})") from error
  if not stat.S_ISREG(mode):
    raise ChunkError(
      f"{where or path}: not a regular file (a data file may not be a device, FIFO, "
      "socket or directory)"
    )


def open_zip(path: str | os.PathLike) -> zipfile.ZipFile:
  """Opens a zip archive; every way a file can fail to be one is a `ChunkError` naming it."""
  check_regular_file(path)
  try:
    return zipfile.ZipFile(path)
  except (
    zipfile.BadZipFile,
    zipfile.LargeZipFile,
    OSError,
    EOFError,
    ValueError,
    struct.error,
    OverflowError,
  ) as error:  # what zipfile raises on a malformed central directory
    raise ChunkError(
      f"{path}: not a readable zip archive ({type(error).__name__}: {error})"
    ) from error


def read_member(
  archive: zipfile.ZipFile,
  name: str,
  *,
  where: str,
  expected_bytes: int | None = None,
  max_bytes: int = MAX_INFLATED_RECORD_BYTES,
) -> bytes:
  """One member of an open archive, its size checked before it is read.

  Args:
    archive: an open zip archive.
    name: the member's name.
    where: file (and scene) for the error message.
    expected_bytes: the exact size the member must have (a tensor storage), if known.
    max_bytes: refuse a compressed member that declares more (a "zip bomb").

  Raises `ChunkError` for a missing, oversized, truncated, encrypted or corrupt member.
  """
  try:
    info = archive.getinfo(name)
  except KeyError:
    raise ChunkError(f"{where}: record '{name}' is missing") from None
  if expected_bytes is not None and info.file_size != expected_bytes:
    raise ChunkError(
      f"{where}: record '{name}' declares {info.file_size} bytes, expected {expected_bytes}"
    )
  if info.compress_type != zipfile.ZIP_STORED and info.file_size > max_bytes:
    raise ChunkError(
      f"{where}: compressed record '{name}' would inflate to {info.file_size} bytes "
      f"(limit {max_bytes})"
    )
  try:
    data = archive.read(info)
  except (
    zipfile.BadZipFile,
    OSError,
    EOFError,
    zlib.error,
    NotImplementedError,
    RuntimeError,
  ) as error:  # RuntimeError: zipfile's "encrypted, password required"
    raise ChunkError(
      f"{where}: cannot read record '{name}' ({type(error).__name__}: {error})"
    ) from error
  if len(data) != info.file_size:
    raise ChunkError(f"{where}: record '{name}' holds {len(data)} bytes, declares {info.file_size}")
  return data


@dataclasses.dataclass(frozen=True, slots=True)
class _StorageType:
  """Stand-in for `torch.<X>Storage` inside the pickle: only carries the element dtype.

  Shared by every read, so immutable (and the unpickler refuses BUILD, which would set state).
  """

  dtype: np.dtype


@dataclasses.dataclass(frozen=True)
class _StorageRecord:
  """A storage not read yet (lazy loading): where its bytes are and what they hold."""

  path: str
  record: str
  dtype: np.dtype
  numel: int
  byteorder: str

  def read(self, archive: zipfile.ZipFile) -> np.ndarray:
    dtype = self.dtype.newbyteorder("<" if self.byteorder == "little" else ">")
    raw = read_member(
      archive, self.record, where=self.path, expected_bytes=self.numel * dtype.itemsize
    )
    return np.frombuffer(raw, dtype).astype(self.dtype, copy=False)


def _is_index(value) -> bool:
  return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _check_geometry(numel: int, offset, size, stride) -> None:
  """Rejects a size/stride/offset that would read outside a storage of `numel` elements, or that
  would make a view with more elements than its storage (a stride-0 view could ask for any
  amount of memory)."""
  if not (
    isinstance(size, tuple)
    and isinstance(stride, tuple)
    and _is_index(offset)
    and all(map(_is_index, size + stride))
  ):
    raise pickle.UnpicklingError(
      f"bad tensor geometry offset={offset!r} size={size!r} stride={stride!r}"
    )
  if len(size) != len(stride):
    raise pickle.UnpicklingError(f"tensor size {size} and stride {stride} differ in rank")
  if all(size):
    last = offset + sum((n - 1) * s for n, s in zip(size, stride))
    if last >= numel:
      raise pickle.UnpicklingError(f"tensor reaches element {last} of a storage of {numel}")
    if math.prod(size) > numel:
      raise pickle.UnpicklingError(
        f"tensor of {math.prod(size)} elements views a storage of {numel}"
      )


def _view(storage: np.ndarray, offset: int, size: tuple, stride: tuple) -> np.ndarray:
  if not all(size):
    return np.zeros(size, storage.dtype)
  view = np.lib.stride_tricks.as_strided(
    storage[offset:], shape=size, strides=[s * storage.itemsize for s in stride]
  )
  return np.array(view)  # own the memory: the storage buffer may be shared by other tensors


@dataclasses.dataclass(frozen=True)
class LazyTensor:
  """A tensor of a chunk whose bytes are read only by `load()` (e.g. the one JPEG a sample needs).

  Picklable (it holds the file path, not an open file), so it can travel to input workers.
  `load()` raises `ChunkError` naming the file for anything wrong with the bytes.
  """

  storage: _StorageRecord
  offset: int
  shape: tuple
  stride: tuple

  @property
  def dtype(self) -> np.dtype:
    return self.storage.dtype

  def load(self) -> np.ndarray:
    storage = self.storage.read(_open_archive(self.storage.path))
    return _view(storage, self.offset, self.shape, self.stride)


_ARCHIVES: collections.OrderedDict = collections.OrderedDict()
_MAX_OPEN_ARCHIVES = 8


def _open_archive(path: str) -> zipfile.ZipFile:
  """A per-process cache of open chunk files (keyed by pid: a forked worker must not share the
  parent's file offset)."""
  key = (os.getpid(), path)
  if key not in _ARCHIVES:
    _ARCHIVES[key] = open_zip(path)
    while len(_ARCHIVES) > _MAX_OPEN_ARCHIVES:
      _ARCHIVES.popitem(last=False)[1].close()
  _ARCHIVES.move_to_end(key)
  return _ARCHIVES[key]


def _rebuild_tensor(
  storage, storage_offset, size, stride, requires_grad=False, backward_hooks=None, metadata=None
):
  """numpy version of `torch._utils._rebuild_tensor_v2`; bounds-checked so a forged size/stride
  cannot read outside its storage."""
  del requires_grad, backward_hooks, metadata  # autograd state has no numpy meaning
  if isinstance(storage, _StorageRecord):
    _check_geometry(storage.numel, storage_offset, size, stride)
    return LazyTensor(storage, storage_offset, tuple(size), tuple(stride))
  if not isinstance(storage, np.ndarray):
    raise pickle.UnpicklingError("tensor rebuilt from something that is not a storage")
  _check_geometry(storage.size, storage_offset, size, stride)
  return _view(storage, storage_offset, tuple(size), tuple(stride))


# Opcodes a tensor pickle never needs: BUILD sets state on an object (on one of our shared globals
# it would change them for the whole process), the others instantiate or look up objects outside
# `find_class`'s control. PERSID is the text form; torch writes BINPERSID.
_REFUSED_OPCODES = {
  op[0]: name
  for op, name in [
    (pickle.BUILD, "BUILD"),
    (pickle.INST, "INST"),
    (pickle.OBJ, "OBJ"),
    (pickle.NEWOBJ, "NEWOBJ"),
    (pickle.NEWOBJ_EX, "NEWOBJ_EX"),
    (pickle.EXT1, "EXT1"),
    (pickle.EXT2, "EXT2"),
    (pickle.EXT4, "EXT4"),
    (pickle.PERSID, "PERSID"),
  ]
}
# What the pure-Python pickle machine raises when the opcode stream itself is malformed (stack
# underflow, truncated argument, wrong container type for an opcode).
_MALFORMED_STREAM = (
  IndexError,
  KeyError,
  TypeError,
  AttributeError,
  ValueError,
  struct.error,
  EOFError,
  OverflowError,
)


def _guarded(handler):
  """An opcode handler whose malformed-stream failures become `UnpicklingError`."""

  def run(unpickler):
    try:
      handler(unpickler)
    except ChunkError:
      raise
    except _MALFORMED_STREAM as error:
      raise pickle.UnpicklingError(f"malformed pickle ({type(error).__name__}: {error})") from error

  return run


def _refused(code: int):
  def refuse(unpickler):
    raise UnsafeChunkError(
      f"{unpickler.path}: refusing pickle opcode "
      f"{_REFUSED_OPCODES.get(code, hex(code))}: a chunk only rebuilds tensors"
    )

  return refuse


def _load_reduce(unpickler):
  """REDUCE, restricted to the two callables a tensor pickle uses, arguments checked first."""
  stack = unpickler.stack
  if len(stack) < 2 or not isinstance(stack[-1], tuple):
    raise pickle.UnpicklingError("REDUCE without a callable and an argument tuple")
  args = stack.pop()
  func = stack[-1]
  if func is collections.OrderedDict and not args:
    stack[-1] = collections.OrderedDict()
  elif func is _rebuild_tensor and 4 <= len(args) <= 7:
    stack[-1] = _rebuild_tensor(*args)
  else:
    raise UnsafeChunkError(
      f"{unpickler.path}: refusing to call {func!r} with {len(args)} arguments"
    )


def _load_binpersid(unpickler):
  if not unpickler.stack:
    raise pickle.UnpicklingError("BINPERSID on an empty stack")
  unpickler.append(unpickler.persistent_load(unpickler.stack.pop()))


class _TensorUnpickler(pickle._Unpickler):  # noqa: SLF001 - the Python one lets us vet each opcode
  """Unpickler that can only build tensors (numpy arrays), storages and plain containers.

  The pure-Python unpickler (not the C one) so that every opcode is vetted: refused opcodes and
  callables raise `UnsafeChunkError`; a malformed stream raises `pickle.UnpicklingError`. Nothing
  in the file is ever executed. (A chunk's pickle is small: the tensors' bytes are other records.)
  """

  _GLOBALS = {
    ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor,
    ("collections", "OrderedDict"): collections.OrderedDict,
    **{("torch", name): _StorageType(dtype) for name, dtype in _STORAGE_DTYPES.items()},
  }
  dispatch = {code: _refused(code) for code in range(256)}
  dispatch.update(
    {
      code: _guarded(handler)
      for code, handler in pickle._Unpickler.dispatch.items()
      if code not in _REFUSED_OPCODES
    }
  )
  dispatch[pickle.REDUCE[0]] = _load_reduce
  dispatch[pickle.BINPERSID[0]] = _load_binpersid

  def __init__(
    self, data: bytes, archive: zipfile.ZipFile, prefix: str, path: str, byteorder: str, lazy: bool
  ):
    super().__init__(io.BytesIO(data))
    self._archive = archive
    self._prefix = prefix
    self.path = path
    self._byteorder = byteorder
    self._lazy = lazy
    self._storages: dict[str, Any] = {}

  def load(self):
    try:
      return super().load()
    except EOFError as error:  # the stream ended before STOP
      raise pickle.UnpicklingError("truncated pickle (no STOP opcode)") from error

  def find_class(self, module: str, name: str):
    try:
      return self._GLOBALS[(module, name)]
    except (KeyError, TypeError):
      raise UnsafeChunkError(
        f"{self.path}: refusing to load global '{module}.{name}': a chunk may only contain "
        "tensors, storages and plain containers"
      ) from None

  def persistent_load(self, pid):
    if not (
      isinstance(pid, tuple)
      and len(pid) == 5
      and pid[0] == "storage"
      and isinstance(pid[1], _StorageType)
      and isinstance(pid[2], str)
      and _is_index(pid[4])
    ):
      raise UnsafeChunkError(f"{self.path}: unexpected persistent id {pid!r}")
    _, storage_type, key, _location, numel = pid
    if key not in self._storages:
      record = _StorageRecord(
        self.path, f"{self._prefix}data/{key}", storage_type.dtype, numel, self._byteorder
      )
      self._storages[key] = record if self._lazy else record.read(self._archive)
    return self._storages[key]


def load_tensor_archive(path: str | os.PathLike, *, lazy: bool = False) -> Any:
  """Loads a `torch.save` zip archive of tensors and plain containers as numpy, without torch.

  Returns the saved object with every tensor replaced by a numpy array, or with `lazy` by a
  `LazyTensor` (shape/dtype known, bytes read on `load()`). Raises `ChunkError` (naming the file)
  for anything that is not such an archive: missing, not a regular file, truncated, legacy
  non-zip format, missing or oversized records, a malformed pickle; and `UnsafeChunkError` for a
  pickle that asks for any global, opcode or call a plain tensor file never needs (it is never
  executed).
  """
  path = str(path)
  with open_zip(path) as archive:
    names = archive.namelist()
    pickles = [n for n in names if n.endswith("/data.pkl") and n.count("/") == 1]
    if len(pickles) != 1:
      raise ChunkError(f"{path}: not a torch zip archive (no single '<name>/data.pkl' record)")
    prefix = pickles[0][: -len("data.pkl")]
    byteorder = "little"
    if f"{prefix}byteorder" in names:
      byteorder = read_member(archive, f"{prefix}byteorder", where=path, max_bytes=16)
      byteorder = byteorder.decode("ascii", "replace").strip()
      if byteorder not in ("little", "big"):
        raise ChunkError(f"{path}: unknown byteorder record {byteorder!r}")
    if archive.getinfo(pickles[0]).file_size > MAX_PICKLE_BYTES:
      raise ChunkError(
        f"{path}: a pickle of {archive.getinfo(pickles[0]).file_size} bytes exceeds "
        f"{MAX_PICKLE_BYTES}"
      )
    data = read_member(archive, pickles[0], where=path)
    try:
      return _TensorUnpickler(data, archive, prefix, path, byteorder, lazy).load()
    except pickle.UnpicklingError as error:
      raise ChunkError(f"{path}: not a readable tensor chunk ({error})") from error


# ----------------------------------------------------------------------------------------------
# Writing: the protocol-2 opcodes torch.save emits, for the few types a chunk holds.


class _PickleWriter:
  """Serialises dict/list/tuple/str/int/float/bool/None and numpy arrays as torch tensors."""

  def __init__(self):
    self.out = io.BytesIO()
    self.storages: list[bytes] = []

  def dump(self, obj) -> bytes:
    self.out.write(b"\x80\x02")  # PROTO 2 (torch's DEFAULT_PROTOCOL)
    self._save(obj)
    self.out.write(b".")  # STOP
    return self.out.getvalue()

  def _save(self, obj):
    write = self.out.write
    if obj is None:
      write(b"N")
    elif isinstance(obj, (bool, np.bool_)):
      write(b"\x88" if obj else b"\x89")
    elif isinstance(obj, (int, np.integer)):
      self._save_int(int(obj))
    elif isinstance(obj, (float, np.floating)):
      write(b"G" + struct.pack(">d", float(obj)))
    elif isinstance(obj, str):
      data = obj.encode("utf-8")
      write(b"X" + struct.pack("<I", len(data)) + data)
    elif isinstance(obj, np.ndarray):
      self._save_tensor(obj)
    elif isinstance(obj, (list, tuple)):
      self._save_sequence(obj)
    elif isinstance(obj, Mapping):
      write(b"}")
      if obj:
        write(b"(")
        for key, value in obj.items():
          self._save(key)
          self._save(value)
        write(b"u")  # SETITEMS
    else:
      raise TypeError(f"cannot write {type(obj).__name__} into a chunk")

  def _save_int(self, value: int):
    if 0 <= value < 1 << 8:
      self.out.write(b"K" + bytes([value]))
    elif 0 <= value < 1 << 16:
      self.out.write(b"M" + struct.pack("<H", value))
    elif -(1 << 31) <= value < 1 << 31:
      self.out.write(b"J" + struct.pack("<i", value))
    else:
      data = value.to_bytes((value.bit_length() + 8) // 8, "little", signed=True)
      self.out.write(b"\x8a" + bytes([len(data)]) + data)  # LONG1

  def _save_sequence(self, items, as_tuple=None):
    as_tuple = isinstance(items, tuple) if as_tuple is None else as_tuple
    if as_tuple and not items:
      self.out.write(b")")
      return
    self.out.write(b"(" if as_tuple else b"](")
    for item in items:
      self._save(item)
    self.out.write(b"t" if as_tuple else b"e")  # TUPLE / APPENDS

  def _save_tensor(self, array: np.ndarray):
    array = np.ascontiguousarray(array)
    array = array.astype(array.dtype.newbyteorder("<"), copy=False)
    if array.dtype not in _STORAGE_NAMES:
      raise TypeError(f"no torch storage for dtype {array.dtype}")
    key = str(len(self.storages))
    self.storages.append(array.tobytes())
    strides = tuple(s // array.itemsize for s in array.strides) if array.size else (1,) * array.ndim
    write = self.out.write
    write(b"ctorch._utils\n_rebuild_tensor_v2\n(")
    # persistent id ('storage', torch.<X>Storage, key, 'cpu', numel), then BINPERSID
    write(b"(")
    self._save("storage")
    write(f"ctorch\n{_STORAGE_NAMES[array.dtype]}\n".encode())
    self._save(key)
    self._save("cpu")
    self._save(int(array.size))
    write(b"tQ")
    self._save(0)  # storage offset
    self._save_sequence(tuple(int(n) for n in array.shape))
    self._save_sequence(strides)
    write(b"\x89")  # requires_grad=False
    write(b"ccollections\nOrderedDict\n)R")  # empty backward hooks
    write(b"tR")


def _aligned_zipinfo(archive: zipfile.ZipFile, name: str) -> zipfile.ZipInfo:
  """A stored (uncompressed) entry whose payload starts at a multiple of 64, as torch writes it."""
  info = zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0))
  info.compress_type = zipfile.ZIP_STORED
  header_end = archive.fp.tell() + 30 + len(name.encode()) + 4  # local header + 'FB' extra header
  padding = -header_end % _ALIGNMENT
  info.extra = struct.pack("<HH", 0x4246, padding) + b"Z" * padding
  return info


def save_tensor_archive(path: str | os.PathLike, obj) -> None:
  """Writes `obj` (containers of str/int/float/bool/None and numpy arrays) as `torch.save` would.

  The archive's top directory is the file stem, like torch's. Written to a temporary file and
  renamed, so a crash never leaves a truncated chunk under the final name.
  """
  path = pathlib.Path(path)
  writer = _PickleWriter()
  data_pkl = writer.dump(obj)
  stem = path.stem
  records = [
    (f"{stem}/data.pkl", data_pkl),
    (f"{stem}/.format_version", b"1"),
    (f"{stem}/.storage_alignment", str(_ALIGNMENT).encode()),
    (f"{stem}/byteorder", b"little"),
  ]
  records += [(f"{stem}/data/{i}", data) for i, data in enumerate(writer.storages)]
  # torch stores a random 40-digit id; a content hash keeps our files deterministic
  serial = str(int.from_bytes(hashlib.sha256(data_pkl).digest()[:16], "little")).zfill(40)[:40]
  records += [(f"{stem}/version", b"3\n"), (f"{stem}/.data/serialization_id", serial.encode())]
  tmp = path.with_name(path.name + ".tmp")
  with zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED) as archive:
    for name, data in records:
      archive.writestr(_aligned_zipinfo(archive, name), data)
  os.replace(tmp, path)


# ----------------------------------------------------------------------------------------------
# JPEG helpers


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


# ----------------------------------------------------------------------------------------------
# Chunk <-> scenes


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
