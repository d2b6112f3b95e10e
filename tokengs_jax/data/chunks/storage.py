"""Torch storage records: the typed storages a tensor pickle points at, and tensors viewing them.

A tensor in a `torch.save` archive is a (storage, offset, size, stride) view of a raw
little-endian storage record `<stem>/data/<key>`. This module maps torch's storage classes to numpy
dtypes, reads a storage record (now or, for a `LazyTensor`, on `load()`), and rebuilds a tensor
from it, bounds-checked so a forged size/stride cannot read outside its storage.
"""

from __future__ import annotations

import dataclasses
import math
import pickle
import zipfile

import ml_dtypes
import numpy as np

from tokengs_jax.data.chunks.archive import _open_archive, read_member

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
