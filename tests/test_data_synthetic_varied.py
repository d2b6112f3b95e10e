"""The varied training rooms (`synthetic.varied`): deterministic, varied, drawing only training
photographs."""

import numpy as np
from synthetic_scenes import photo_names as _photo_names

from tokengs_jax.data.synthetic import generate, photos, varied


def test_varied_rooms_are_deterministic_varied_and_draw_only_training_photos():
  config = generate.Re10kLikeConfig(supersample=1, room=varied.VariedRoomConfig())
  a = generate.render_re10k_like_scene(0, "train", 3, 12, 16, 4, config)
  b = generate.render_re10k_like_scene(0, "train", 3, 12, 16, 4, config)
  for field in ("c2w", "intrinsics", "images", "depths"):
    np.testing.assert_array_equal(a[field], b[field])
  used, kinds, counts, orbits = set(), set(), set(), 0
  for i in range(12):
    scene, c2w = varied.sample_varied_room(np.random.default_rng(i), 8)
    used |= _photo_names(scene)
    kinds |= {p.texture.kind for p in scene.primitives}
    counts.add(len(scene.objects))
    # An orbit looks at one point: its view axes converge; a walk's stay near parallel.
    forward = c2w[:, :3, 2]
    orbits += float(np.dot(forward[0], forward[-1])) < 0.999 and len(set(c2w[:, 1, 3])) == 1
    # The camera stays inside the room.
    half_x = max(abs(float(p.point[0])) for p in scene.planes[2:4])
    assert np.all(np.abs(c2w[:, 0, 3]) < half_x)
  assert used and used <= set(photos.TRAIN_PHOTOS)
  assert "photo" in kinds and kinds & {"checker", "stripes", "gradient", "noise"}
  assert not kinds & {"rings", "dots", "bricks"}  # the galleries' kinds stay held out
  assert len(counts) > 3
