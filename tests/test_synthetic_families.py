"""The issue-23 scene families: photo textures (`synthetic.photos`), the varied training rooms
(`synthetic.varied`), the frozen courtyards (`synthetic.courtyards`) and the true depth maps the
test sets record beside their chunks."""

import numpy as np
import pytest

from tokengs_jax.data.synthetic import courtyards, generate, held_out, photos, varied
from tokengs_jax.data.synthetic.raytrace import Plane, Scene, Texture, render, texture_color


def _photo_names(scene: Scene) -> set[str]:
  return {p.texture.image for p in scene.primitives if p.texture.kind == "photo"}


def test_photo_pools_are_disjoint_and_load_offline():
  assert not set(photos.TRAIN_PHOTOS) & set(photos.HELD_OUT_PHOTOS)
  for name in photos.TRAIN_PHOTOS + photos.HELD_OUT_PHOTOS:
    image = photos.photo(name)
    assert image.dtype == np.float32 and image.shape[2] == 3
    assert max(image.shape[:2]) <= photos.MAX_SIDE and 0.0 <= image.min() <= image.max() <= 1.0
  with pytest.raises(ValueError, match="unknown photograph"):
    photos.photo("../../etc/passwd")


def test_photo_texture_tiles_the_photograph_and_tints_grey_ones():
  with pytest.raises(ValueError, match="names its `image`"):
    Texture(kind="photo")
  with pytest.raises(ValueError, match="names its `image`"):
    Texture(kind="checker", image="brick.png")
  image = photos.photo("astronaut.png")
  height, width = image.shape[:2]
  plain = Texture(kind="photo", image="astronaut.png", frequency=1.0, seed=0)
  # Texel (row 10, column 20) of tile (0, 0) and of tile (2, -1): the photograph repeats.
  uv = np.array([[20.5 / width, 10.5 / height, 0.0], [2 + 20.5 / width, -1 + 10.5 / height, 0.0]])
  np.testing.assert_allclose(texture_color(plain, uv.astype(np.float32)), image[[10, 10], [20, 20]])
  # A box face addresses the photograph with its two in-face axes (face axis 0: local y, z).
  on_face = np.array([[0.3, 20.5 / width, 10.5 / height]], np.float32)
  np.testing.assert_allclose(texture_color(plain, on_face, np.array([0])), image[[10], [20]])
  tinted = Texture(
    kind="photo", image="brick.png", tint=True, color_a=(1.0, 0.0, 0.0), color_b=(0.0, 0.0, 1.0)
  )
  colours = texture_color(tinted, np.random.default_rng(0).uniform(0, 1, (256, 3)))
  assert np.allclose(colours[:, 1], 0.0) and np.allclose(colours.sum(-1), 1.0)  # red..blue mixes


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


def test_splits_record_true_depths_beside_their_chunks(tmp_path):
  generate.generate_re10k_like(
    tmp_path, 2, 2, 12, 16, frames=4, config=generate.Re10kLikeConfig(supersample=1)
  )
  assert list((tmp_path / "train").glob("*.depth.npz"))  # every split: the depth loss reads them
  chunk = tmp_path / "test" / "000000.torch"
  scene = generate.render_re10k_like_scene(
    0, "test", 1, 12, 16, 4, generate.Re10kLikeConfig(supersample=1)
  )
  depths = generate.read_true_depths(chunk, scene["key"])
  np.testing.assert_allclose(depths, scene["depths"], rtol=1e-3)  # stored as float16
  assert generate.read_true_depths(chunk, "no such scene") is None
  assert generate.read_true_depths(tmp_path / "train" / "000000.torch", scene["key"]) is None
  (tmp_path / "test" / "000000.depth.npz").unlink()  # real data: no depth recorded
  assert generate.read_true_depths(chunk, scene["key"]) is None


def test_a_plane_textured_with_a_photo_renders_the_photo():
  """The tracer end to end: a camera facing a photo-textured wall sees the photograph's texels."""
  wall = Plane(
    point=np.array([0.0, 0.0, 2.0]),
    normal=np.array([0.0, 0.0, -1.0]),
    tangent=np.array([1.0, 0.0, 0.0]),
    texture=Texture(kind="photo", image="coffee.png", frequency=0.25),
  )
  scene = Scene(planes=(wall,), ambient=1.0)
  image = render(scene, np.eye(4), np.array([16.0, 16.0, 8.0, 8.0]), 16, 16).rgb
  assert image.std() > 0.02  # texture detail, not a flat colour
  assert np.isin(
    np.round(image.reshape(-1, 3) * 255), np.round(photos.photo("coffee.png") * 255)
  ).all()
