"""Official weights saved by torch (`torch.save(model.state_dict())`: `.pth`, `.pt`), read without
torch and without executing anything in the file.

A torch file is a zip archive of a pickle plus raw storages, the format of the pixelSplat chunks,
so the vetted chunk unpickler (`tokengs_jax.data.chunks.unpickler`) reads it: only the tensor
globals, every opcode vetted, bounded records and opcode count. One addition: a module's
`state_dict()` is an `OrderedDict` carrying a `_metadata` attribute (each submodule's version),
which `torch.save` pickles as a BUILD opcode on the dict, and the chunk unpickler refuses BUILD.
Here BUILD is allowed for exactly that: on an `OrderedDict`, setting nothing but `_metadata`, whose
value is dropped (module versions mean nothing to our params, and no state is ever set).
"""

from __future__ import annotations

import collections
import os
import pickle

import numpy as np

from tokengs_jax.data.chunks import ChunkError, UnsafeChunkError, open_zip, read_member
from tokengs_jax.data.chunks.archive import MAX_PICKLE_BYTES
from tokengs_jax.data.chunks.unpickler import _guarded, _TensorUnpickler


def _load_state_dict_metadata(unpickler):
  """BUILD, restricted to a state dict's `_metadata`, which is discarded."""
  stack = unpickler.stack
  state = stack.pop()
  if not (
    type(stack[-1]) is collections.OrderedDict
    and isinstance(state, dict)
    and set(state) == {"_metadata"}
  ):
    raise UnsafeChunkError(
      f"{unpickler.path}: refusing pickle opcode BUILD on {type(stack[-1]).__name__}: a torch "
      "state dict only sets an OrderedDict's _metadata"
    )


class _StateDictUnpickler(_TensorUnpickler):
  dispatch = {**_TensorUnpickler.dispatch, pickle.BUILD[0]: _guarded(_load_state_dict_metadata)}


def _byteorder(archive, prefix: str, path: str) -> str:
  if f"{prefix}byteorder" not in archive.namelist():
    return "little"  # files from torch before 2.1 have no record and are little-endian
  record = read_member(archive, f"{prefix}byteorder", where=path, max_bytes=16)
  byteorder = record.decode("ascii", "replace").strip()
  if byteorder not in ("little", "big"):
    raise ChunkError(f"{path}: unknown byteorder record {byteorder!r}")
  return byteorder


def read_torch_state_dict(path: str | os.PathLike) -> dict[str, np.ndarray]:
  """The tensors of a `torch.save`d state dict (name -> tensor mapping) as numpy arrays.

  Raises:
    ChunkError: (a ValueError) naming the file, for anything but a torch zip archive holding a
      mapping of names to tensors (missing, truncated, legacy non-zip format, oversized records,
      a malformed pickle, another top-level object).
    UnsafeChunkError: for a pickle asking for any global, opcode or call that a state dict never
      needs (it is never executed).
  """
  path = str(path)
  with open_zip(path) as archive:
    pickles = [n for n in archive.namelist() if n.endswith("/data.pkl") and n.count("/") == 1]
    if len(pickles) != 1:
      raise ChunkError(f"{path}: not a torch zip archive (no single '<name>/data.pkl' record)")
    prefix = pickles[0][: -len("data.pkl")]
    byteorder = _byteorder(archive, prefix, path)
    pickle_bytes = archive.getinfo(pickles[0]).file_size
    if pickle_bytes > MAX_PICKLE_BYTES:  # checked before a byte is read
      raise ChunkError(f"{path}: a pickle of {pickle_bytes} bytes exceeds {MAX_PICKLE_BYTES}")
    data = read_member(archive, pickles[0], where=path)
    try:
      loaded = _StateDictUnpickler(data, archive, prefix, path, byteorder, lazy=False).load()
    except pickle.UnpicklingError as error:
      raise ChunkError(f"{path}: not a readable torch file ({error})") from error
  if not (
    isinstance(loaded, dict)
    and all(isinstance(k, str) and isinstance(v, np.ndarray) for k, v in loaded.items())
  ):
    keys = f" with keys {list(loaded)[:5]}" if isinstance(loaded, dict) else ""
    raise ChunkError(
      f"{path}: holds a {type(loaded).__name__}{keys}, not a state dict (a mapping of names to "
      "tensors, what the official loaders read)"
    )
  return dict(loaded)
