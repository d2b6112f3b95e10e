"""Writing `torch.save` archives without torch: the protocol-2 pickle opcodes torch.save emits.

Only the few types a chunk holds (dict/list/tuple/str/int/float/bool/None and numpy arrays, as
tensors), with each storage a 64-byte-aligned stored record, so `torch.load(path)` (weights_only
or not) reads our files unchanged.
"""

from __future__ import annotations

import hashlib
import io
import os
import pathlib
import struct
import zipfile
from typing import Mapping

import numpy as np

from tokengs_jax.data.chunks.storage import _STORAGE_NAMES

_ALIGNMENT = 64  # torch aligns every record's payload to 64 bytes (enables mmap loading)


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
