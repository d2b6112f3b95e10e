"""Bounded reading of zip archives: torch chunk files and DL3DV scene zips.

Every record's declared size is checked before a byte is read, every way a file can fail to be a
readable archive is a `ChunkError` naming it, and open archives are cached per process for the
lazy tensors that read one record at a time.
"""

from __future__ import annotations

import collections
import copy
import os
import stat
import struct
import threading
import zipfile
import zlib


class ChunkError(ValueError):
  """A chunk file (or one scene in it) is malformed; the message names the file and scene."""

  def detached(self) -> ChunkError:
    """A copy without traceback, cause or context, to keep (a cached rejection) or raise again:
    a traceback's frames hold the locals of every function it passed through, the arrays of the
    rejected scene among them. The message already names the cause."""
    return copy.copy(self)  # the type, args and attributes (`scene_key`); not the traceback


# Allocation bounds, checked against a record's declared size before any byte is read: a forged
# archive cannot make the reader inflate more than this (torch stores records uncompressed, so a
# real chunk's records are bounded by the file itself). A real chunk's pickle takes ~75 bytes and
# ~31 opcodes a tensor; what decoding it allocates is bounded by its opcodes (`unpickler`).
MAX_PICKLE_BYTES = 32 << 20
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
) -> bytearray:
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
  data = bytearray()
  try:
    with archive.open(info) as member:
      # grown in place: zipfile's whole-member read concatenates bytes objects, which holds
      # twice the record (510 MB at a peak for a 255 MiB record, 259 MB so)
      while piece := member.read(1 << 20):
        data += piece
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


_ARCHIVES: collections.OrderedDict = collections.OrderedDict()
_ARCHIVES_LOCK = threading.Lock()
_MAX_OPEN_ARCHIVES = 8


def _forget_archives_after_fork() -> None:
  # A forked worker must not share the parent's file offsets, nor inherit a lock another parent
  # thread held at the fork.
  global _ARCHIVES_LOCK
  _ARCHIVES.clear()
  _ARCHIVES_LOCK = threading.Lock()


os.register_at_fork(after_in_child=_forget_archives_after_fork)


def _open_archive(path: str) -> zipfile.ZipFile:
  """A per-process cache of open chunk files, safe under grain's reader threads.

  An archive pushed out of the cache is dropped, not closed: a thread that fetched it earlier may
  still be reading it, and the ZipFile closes itself once no thread holds it.
  """
  with _ARCHIVES_LOCK:
    archive = _ARCHIVES.get(path)
    if archive is None:
      archive = _ARCHIVES[path] = open_zip(path)
      while len(_ARCHIVES) > _MAX_OPEN_ARCHIVES:
        _ARCHIVES.popitem(last=False)
    _ARCHIVES.move_to_end(path)
    return archive
