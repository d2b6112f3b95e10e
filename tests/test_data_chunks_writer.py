"""The torch-free archive writer (`chunks.writer`): every dtype and container a chunk holds reads
back unchanged."""

import numpy as np

from tokengs_jax.data import chunks


def test_tensor_archive_dtypes_and_containers(tmp_path):
  obj = {
    "f64": np.arange(6.0).reshape(2, 3),
    "b": np.array([True, False]),
    "i8": np.arange(-3, 3, dtype=np.int8),
    "t": np.arange(12, dtype=np.int32).reshape(3, 4).T,
    "e": np.zeros((0, 2), np.float32),
    "n": [None, 1.5, -7, 2**40, 70000, (1, "a"), ()],
  }
  chunks.save_tensor_archive(tmp_path / "m.torch", obj)
  back = chunks.load_tensor_archive(tmp_path / "m.torch")
  for key in ("f64", "b", "i8", "t", "e"):
    assert back[key].dtype == obj[key].dtype
    np.testing.assert_array_equal(back[key], obj[key])
  assert back["n"] == obj["n"]
