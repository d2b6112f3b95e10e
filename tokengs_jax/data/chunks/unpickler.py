"""The vetted unpickler: loads a `torch.save` archive's pickle without executing anything in it.

`_TensorUnpickler.find_class` resolves only the few globals a plain tensor pickle needs (the
tensor rebuild function, typed storages, `OrderedDict`) to our own numpy re-implementations, and
refuses anything else naming the file. Every opcode is vetted: those a tensor pickle never needs
are refused, REDUCE may only call the two callables a tensor pickle uses, and a malformed stream
becomes an `UnpicklingError` (hence a `ChunkError`).
"""

from __future__ import annotations

import collections
import io
import os
import pickle
import struct
import zipfile
from typing import Any

from tokengs_jax.data.chunks.archive import MAX_PICKLE_BYTES, ChunkError, open_zip, read_member
from tokengs_jax.data.chunks.storage import (
  _STORAGE_DTYPES,
  _is_index,
  _rebuild_tensor,
  _StorageRecord,
  _StorageType,
)


class UnsafeChunkError(ChunkError):
  """The pickle inside a chunk asks for a global that a plain tensor file never needs."""


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


# Each opcode allocates at most one object of bounded size (~100 bytes: an empty dict or list, a
# memo entry) besides strings, which the pickle's size bounds: so at most ~200 MB decoded from a
# pickle whose 1-byte opcodes each make a new list. A real chunk's pickle runs ~31 a tensor.
MAX_PICKLE_OPCODES = 2_000_000


def _guarded(handler):
  """An opcode handler that counts against the opcode budget and whose malformed-stream failures
  become `UnpicklingError`."""

  def run(unpickler):
    unpickler.opcodes_left -= 1
    if unpickler.opcodes_left < 0:
      raise ChunkError(
        f"{unpickler.path}: the pickle runs more than MAX_PICKLE_OPCODES {MAX_PICKLE_OPCODES} "
        "opcodes (a chunk's pickle runs ~31 a tensor)"
      )
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
  dispatch[pickle.REDUCE[0]] = _guarded(_load_reduce)
  dispatch[pickle.BINPERSID[0]] = _guarded(_load_binpersid)

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
    self.opcodes_left = MAX_PICKLE_OPCODES

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
