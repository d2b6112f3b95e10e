"""Photographs as textures (`synthetic.photos`): disjoint training and held-out pools, read
offline, names checked."""

import numpy as np
import pytest

from tokengs_jax.data.synthetic import photos


def test_photo_pools_are_disjoint_and_load_offline():
  assert not set(photos.TRAIN_PHOTOS) & set(photos.HELD_OUT_PHOTOS)
  for name in photos.TRAIN_PHOTOS + photos.HELD_OUT_PHOTOS:
    image = photos.photo(name)
    assert image.dtype == np.float32 and image.shape[2] == 3
    assert max(image.shape[:2]) <= photos.MAX_SIDE and 0.0 <= image.min() <= image.max() <= 1.0
  with pytest.raises(ValueError, match="unknown photograph"):
    photos.photo("../../etc/passwd")
