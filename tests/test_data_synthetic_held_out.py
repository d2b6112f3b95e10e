"""The held-out static test families' writers (`synthetic.held_out`): the gallery family
(out-of-distribution test set) reads back through the evaluation index, deterministic and unlike
the rooms."""

import numpy as np
from synthetic_scenes import H, W

from tokengs_jax.data.synthetic import scenes


def test_gallery_set_reads_back_through_the_evaluation_index(tmp_path):
  from tokengs_jax.data import ChunkedSceneSource, evaluation_views, load_evaluation_index
  from tokengs_jax.data.synthetic.held_out import GalleryDatasetConfig, generate_galleries

  config = GalleryDatasetConfig(supersample=1, scenes_per_chunk=2)
  written = generate_galleries(
    tmp_path, num_scenes=3, height=H, width=W, frames=9, seed=4, config=config
  )
  assert sorted(p.name for p in (tmp_path / "test").iterdir()) == [
    "000000.depth.npz",  # true depth maps, for the evaluation's geometry scores
    "000000.torch",
    "000001.depth.npz",
    "000001.torch",
    "index.json",
  ]
  index = load_evaluation_index(tmp_path / "eval_index.json")
  assert list(index) == list(written) == ["gallery4_000000", "gallery4_000001", "gallery4_000002"]
  source = ChunkedSceneSource(tmp_path / "test", keys=list(index))
  for position, key in enumerate(index):
    record = source[position]
    assert record["key"] == key and len(record["images"]) == 9
    context, target = evaluation_views(index, key, 9)
    np.testing.assert_array_equal(context, [0, 8])
    np.testing.assert_array_equal(target, [2, 4, 6])  # strictly between the inputs
    assert not set(target.tolist()) & set(context.tolist())


def test_gallery_scene_is_deterministic_and_unlike_the_rooms():
  from tokengs_jax.data.synthetic.held_out import GalleryDatasetConfig, render_gallery_scene

  config = GalleryDatasetConfig(supersample=1)
  a = render_gallery_scene(3, 1, 12, 16, 3, config)
  b = render_gallery_scene(3, 1, 12, 16, 3, config)
  for field in ("c2w", "intrinsics", "images", "depths"):
    np.testing.assert_array_equal(a[field], b[field])
  assert not np.array_equal(a["c2w"], render_gallery_scene(3, 2, 12, 16, 3, config)["c2w"])
  assert (a["depths"] > 0).all()  # a closed room

  rooms_kinds, gallery_kinds, wall_counts = set(), set(), set()
  for i in range(6):
    room, _ = scenes.sample_room_scene(np.random.default_rng(i), 12)
    gallery, orbit = scenes.sample_gallery_scene(np.random.default_rng(i), 12)
    rooms_kinds |= {p.texture.kind for p in room.primitives}
    gallery_kinds |= {p.texture.kind for p in gallery.primitives}
    wall_counts.add(len(gallery.planes) - 2)
    # Rooms have 4 axis-aligned walls and a high white light; galleries 5-8 walls, a low tinted one.
    assert len(room.planes) == 6 and len(gallery.planes) >= 7
    assert gallery.light_direction[1] < 0.8 * np.linalg.norm(gallery.light_direction)
    assert gallery.light_color != (1.0, 1.0, 1.0)
    # An inward orbit moves across its view direction (a walk mostly moves along it).
    travel = np.diff(orbit[:, [0, 2], 3], axis=0)
    look = orbit[:-1, [0, 2], 2]
    along = np.abs(np.einsum("fi,fi->f", travel, look)) / (
      np.linalg.norm(travel, axis=-1) * np.linalg.norm(look, axis=-1)
    )
    assert np.median(along) < 0.5
  assert rooms_kinds.isdisjoint(gallery_kinds)
  assert len(wall_counts) > 1
