"""Random scene layouts (`synthetic.scenes`): a room's walking camera stays clear of its objects."""

import numpy as np

from tokengs_jax.data.synthetic import scenes


def test_room_scene_camera_stays_clear_of_objects_and_inside_the_room():
  scene, c2w = scenes.sample_room_scene(np.random.default_rng(11), 24)
  walls = {tuple(np.round(p.normal)): p for p in scene.planes}
  half_w, half_d = walls[(-1.0, 0.0, 0.0)].point[0], walls[(0.0, 0.0, -1.0)].point[2]
  assert (np.abs(c2w[:, 0, 3]) < half_w).all() and (np.abs(c2w[:, 2, 3]) < half_d).all()
  for obj in scene.objects:
    gap = np.linalg.norm(c2w[:, [0, 2], 3] - np.asarray(obj.center)[[0, 2]], axis=-1)
    assert gap.min() > scenes.RoomConfig().clearance
