"""The frozen courtyards (`synthetic.courtyards`): frozen, open to the sky, drawing only held-out
photographs."""

import numpy as np
from synthetic_scenes import photo_names as _photo_names

from tokengs_jax.data.synthetic import courtyards, held_out, photos
from tokengs_jax.data.synthetic.raytrace import render


def test_courtyards_are_frozen_open_and_draw_only_held_out_photos():
  config = held_out.COURTYARD_DATASET
  a = held_out._render_held_out_scene("courtyards", courtyards.FROZEN_SEED, 0, 12, 16, 3, config)
  b = held_out._render_held_out_scene("courtyards", courtyards.FROZEN_SEED, 0, 12, 16, 3, config)
  np.testing.assert_array_equal(a["images"], b["images"])
  assert a["key"] == f"courtyard{courtyards.FROZEN_SEED}_000000"
  used, open_sky = set(), 0
  for i in range(8):
    scene, c2w = courtyards.sample_courtyard(np.random.default_rng(i), 13)
    used |= _photo_names(scene)
    assert len(scene.planes) == 1  # the ground; the facades are finite slabs, with no ceiling
    # A sideways track: travel is across the first view direction.
    travel = c2w[-1, :3, 3] - c2w[0, :3, 3]
    assert abs(np.dot(travel, c2w[0, :3, 2])) < 0.5 * np.linalg.norm(travel)
    up = np.eye(4)
    up[:3, 3] = c2w[0, :3, 3]
    up[:3, :3] = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # looking straight up
    open_sky += (render(scene, up, np.array([8.0, 8.0, 8.0, 8.0]), 16, 16).depth == 0).mean() > 0.5
  assert used and used <= set(photos.HELD_OUT_PHOTOS)
  assert open_sky == 8
