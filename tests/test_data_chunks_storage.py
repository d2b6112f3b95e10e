"""Tensor storages (`chunks.storage`): a tensor view forged past its storage is refused."""

import zipfile

import numpy as np
import pytest

from tokengs_jax.data import chunks
from tokengs_jax.data.chunks import ChunkError


def test_forged_tensor_geometry_is_refused(tmp_path):
  path = tmp_path / "forged.torch"
  chunks.save_tensor_archive(path, [np.arange(4, dtype=np.float32)])
  with zipfile.ZipFile(path) as archive:
    records = {n: archive.read(n) for n in archive.namelist()}
  name = "forged/data.pkl"
  forged = records[name].replace(b"K\x00(K\x04t", b"K\x00(M\x00\x10t")  # size (4,) -> (4096,)
  assert forged != records[name]
  records[name] = forged
  with zipfile.ZipFile(path, "w") as archive:
    for record, data in records.items():
      archive.writestr(record, data)
  with pytest.raises(ChunkError, match="forged.torch.*reaches element"):
    chunks.load_tensor_archive(path)
