"""The vetted unpickler (`chunks.unpickler`): a malicious pickle is refused and never runs."""

import os
import pickle
import zipfile

import pytest

from tokengs_jax.data.chunks import UnsafeChunkError, read_chunk


class _Exploit:
  def __init__(self, marker):
    self.marker = marker

  def __reduce__(self):
    return (os.system, (f"touch {self.marker}",))


def _zip_with_pickle(path, payload: bytes):
  with zipfile.ZipFile(path, "w") as archive:
    archive.writestr("evil/data.pkl", payload)
    archive.writestr("evil/version", "3\n")


def test_malicious_pickle_is_refused_and_never_runs(tmp_path):
  marker = tmp_path / "pwned"
  path = tmp_path / "evil.torch"
  _zip_with_pickle(path, pickle.dumps([{"key": "x", "cameras": _Exploit(marker)}], protocol=2))
  with pytest.raises(UnsafeChunkError, match=r"evil\.torch.*posix\.system|evil\.torch.*os\.system"):
    read_chunk(path)
  assert not marker.exists()
