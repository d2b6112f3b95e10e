"""The synthetic ray tracer against analytic values, camera paths, and chunk files it writes."""

import json

import jax.numpy as jnp
import numpy as np
import pytest

from tokengs_jax import camera
from tokengs_jax.data import read_chunk
from tokengs_jax.data.synthetic import cameras, raytrace, scenes
from tokengs_jax.data.synthetic.generate import (
  Re10kLikeConfig,
  generate_re10k_like,
  render_re10k_like_scene,
)

H, W = 24, 32
INTRINSICS = np.array([30.0, 28.0, 15.3, 12.7])  # fx != fy and an off-centre principal point


def _plane(point, normal, texture=raytrace.Texture(), tangent=(1.0, 0.0, 0.0)):
  return raytrace.Plane(
    point=np.asarray(point, float),
    normal=np.asarray(normal, float),
    tangent=np.asarray(tangent, float),
    texture=texture,
  )


def _pixel_dirs_cam():
  """Unnormalised camera-frame rays (x, y, 1) through pixel centres.  -> [H, W, 3]."""
  u = np.arange(W) + 0.5
  v = np.arange(H) + 0.5
  uu, vv = np.meshgrid(u, v)
  fx, fy, cx, cy = INTRINSICS
  return np.stack([(uu - cx) / fx, (vv - cy) / fy, np.ones_like(uu)], -1)


def test_fronto_parallel_plane_depth_is_its_distance():
  scene = raytrace.Scene(planes=(_plane((0, 0, 3.5), (0, 0, -1)),))
  out = raytrace.render(scene, np.eye(4), INTRINSICS, H, W)
  np.testing.assert_allclose(out.depth, 3.5, rtol=1e-5)
  assert (out.ids == 0).all()


def test_tilted_plane_depth_and_lambert_colour_match_analytic_values():
  normal = np.array([0.3, -0.2, -1.0])
  normal /= np.linalg.norm(normal)
  point = np.array([0.1, 0.2, 4.0])
  albedo = (0.8, 0.5, 0.25)
  light = np.array([0.2, -0.4, -1.0])
  scene = raytrace.Scene(
    planes=(_plane(point, normal, raytrace.Texture("solid", albedo)),),
    light_direction=tuple(light),
    ambient=0.3,
  )
  # Camera: rotated and translated, so the c2w path is exercised too.
  c2w = cameras.look_at(
    np.array([0.4, -0.3, -0.5]), np.array([0.2, 0.1, 4.0]), up=np.array([0, -1.0, 0])
  )
  out = raytrace.render(scene, c2w, INTRINSICS, H, W)

  dirs_cam = _pixel_dirs_cam()
  normal_cam = c2w[:3, :3].T @ normal
  point_cam = c2w[:3, :3].T @ (point - c2w[:3, 3])
  # plane n.X = n.p in camera frame, X = z * (x, y, 1)  =>  z = n.p / n.(x, y, 1)
  np.testing.assert_allclose(
    out.depth, (normal_cam @ point_cam) / (dirs_cam @ normal_cam), rtol=1e-4
  )
  facing = normal * np.sign(normal @ (c2w[:3, 3] - point))  # the side the camera sees
  lambert = max(0.0, float(facing @ (light / np.linalg.norm(light))))
  assert lambert > 0.5
  expected = np.asarray(albedo) * (0.3 + 0.7 * lambert)
  np.testing.assert_allclose(out.rgb, np.broadcast_to(expected, out.rgb.shape), atol=1e-5)


def test_checker_colour_follows_the_analytic_hit_point():
  texture = raytrace.Texture("checker", (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), frequency=2.0)
  scene = raytrace.Scene(planes=(_plane((0, 0, 2.0), (0, 0, -1), texture),), ambient=1.0)
  out = raytrace.render(scene, np.eye(4), INTRINSICS, H, W)
  hits = _pixel_dirs_cam() * 2.0  # hit points on z = 2
  # plane local axes: u along x, v along n x t = (0,0,-1) x (1,0,0) = (0,-1,0)
  parity = (np.floor(2.0 * hits[..., 0]) + np.floor(-2.0 * hits[..., 1])) % 2
  np.testing.assert_array_equal(out.rgb[..., 2] > 0.5, parity == 1)
  np.testing.assert_array_equal(out.rgb[..., 0] > 0.5, parity == 0)


def test_sphere_silhouette_is_where_project_points_puts_the_sphere():
  center, radius = np.array([0.4, -0.2, 5.0]), 0.9
  c2w = cameras.look_at(np.array([0.5, -0.5, -0.3]), np.array([0.0, 0.0, 5.0]))
  scene = raytrace.Scene(objects=(raytrace.Sphere(center=center, radius=radius),))
  out = raytrace.render(scene, c2w, INTRINSICS, H, W)
  covered = out.ids == 0
  eye = c2w[:3, 3]
  view = (center - eye) / np.linalg.norm(center - eye)
  rng = np.random.default_rng(0)
  directions = rng.normal(size=(400, 3))
  directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
  # visible surface points: facing the camera (with a margin away from the silhouette)
  surface = center + radius * directions
  facing = (
    np.einsum("ni,ni->n", directions, eye - surface) / np.linalg.norm(eye - surface, axis=-1) > 0.6
  )
  # points just outside the silhouette: a ring of radius 1.15 r perpendicular to the view ray
  perpendicular = directions - (directions @ view)[:, None] * view
  perpendicular /= np.linalg.norm(perpendicular, axis=-1, keepdims=True)
  outside = center + 1.15 * radius * perpendicular
  visible = surface[facing]
  points = np.concatenate([visible, outside]).astype(np.float32)
  uv, depth = camera.project_points(
    jnp.asarray(points), jnp.asarray(np.linalg.inv(c2w))[None], jnp.asarray(INTRINSICS)[None]
  )
  uv, depth = np.asarray(uv[0]), np.asarray(depth[0])
  in_image = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
  cols, rows = np.floor(np.where(in_image[:, None], uv, 0)).astype(int).T
  is_visible = np.arange(len(points)) < len(visible)
  for expect in (True, False):
    chosen = in_image & (is_visible == expect)
    assert chosen.sum() > 20
    # a point may share a pixel with the rim, hence not all
    assert (covered[rows, cols][chosen] == expect).mean() > 0.97
  # the depth at a visible point's pixel is that of a nearby point of the sphere
  hit = in_image & is_visible & covered[rows, cols]
  assert np.all(np.abs(out.depth[rows, cols] - depth)[hit] < 0.3 * radius)


def test_box_front_face_depth():
  box = raytrace.Box(center=np.array([0.0, 0.0, 3.0]), half_size=np.array([2.0, 2.0, 0.5]))
  out = raytrace.render(raytrace.Scene(objects=(box,)), np.eye(4), INTRINSICS, H, W)
  np.testing.assert_allclose(out.depth, 2.5, rtol=1e-5)


def test_segmentation_numbers_each_pixel_by_the_object_instance_it_sees():
  # a floor, a wall and three boxes side by side in front of the camera; the last two are the
  # parts of one rigid instance
  boxes = tuple(
    raytrace.Box(center=np.array([x, 0.0, 3.0]), half_size=np.array([0.3, 0.3, 0.3]))
    for x in (-1.0, 0.0, 1.0)
  )
  planes = (_plane((0, 0, 6), (0, 0, -1)), _plane((0, 1, 0), (0, -1, 0)))
  out = raytrace.render(raytrace.Scene(planes=planes, objects=boxes), np.eye(4), INTRINSICS, H, W)
  assert set(np.unique(out.ids)) == {0, 1, 2, 3, 4}
  expected = np.select([out.ids == 2, out.ids == 3, out.ids == 4], [1, 2, 2], 0)
  grouped = raytrace.Scene(planes=planes, objects=boxes, instances=(0, 1, 1))
  np.testing.assert_array_equal(grouped.segmentation(out.ids), expected)
  # by default every object is its own instance; rays that hit nothing are background too
  alone = raytrace.Scene(planes=planes, objects=boxes)
  np.testing.assert_array_equal(
    alone.segmentation(np.array([-1, 0, 1, 2, 3, 4])), [0, 0, 0, 1, 2, 3]
  )
  with pytest.raises(ValueError, match="2 instance numbers for 3 objects"):
    raytrace.Scene(objects=boxes, instances=(0, 1)).segmentation(out.ids)


def test_object_shadow_leaves_only_ambient_light():
  floor = _plane((0, 0, 0), (0, 1, 0), raytrace.Texture("solid", (1.0, 1.0, 1.0)))
  sphere = raytrace.Sphere(center=np.array([0.0, 1.0, 0.0]), radius=0.3)
  scene = raytrace.Scene(
    planes=(floor,), objects=(sphere,), light_direction=(0.0, 1.0, 0.0), ambient=0.25
  )
  origin = np.array([[3.0, 1.0, 0.0], [3.0, 1.0, 0.0]], np.float32)
  targets = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])  # under the sphere / in the open
  dirs = (targets - origin) / np.linalg.norm(targets - origin, axis=-1, keepdims=True)
  result = raytrace.trace(scene, origin, dirs.astype(np.float32))
  np.testing.assert_array_equal(result.ids, [0, 0])
  np.testing.assert_allclose(result.rgb, [[0.25] * 3, [1.0] * 3], atol=1e-6)


@pytest.mark.parametrize("kind", raytrace.TEXTURE_KINDS)
def test_textures_mix_between_their_two_colours(kind):
  photo = {"image": "grass.png", "tint": True} if kind == "photo" else {}  # a tinted photograph
  texture = raytrace.Texture(kind, (0.1, 0.2, 0.3), (0.9, 0.6, 0.3), frequency=1.7, seed=5, **photo)
  points = np.random.default_rng(1).uniform(-3, 3, (500, 3)).astype(np.float32)
  colors = raytrace.texture_color(texture, points)
  mix = (colors[:, 0] - 0.1) / 0.8
  np.testing.assert_allclose(colors[:, 1], 0.2 + 0.4 * mix, atol=1e-5)  # on the segment a-b
  assert mix.min() >= -1e-6 and mix.max() <= 1 + 1e-6
  if kind != "solid":
    assert mix.std() > 0.1  # an actual pattern


def test_value_noise_is_deterministic_continuous_and_seeded():
  points = np.random.default_rng(2).uniform(-5, 5, (300, 3)).astype(np.float32)
  a = raytrace.value_noise(points, seed=3)
  np.testing.assert_array_equal(a, raytrace.value_noise(points, seed=3))
  assert np.abs(a - raytrace.value_noise(points, seed=4)).mean() > 0.05
  nudged = raytrace.value_noise(points + 1e-3, seed=3)
  assert np.abs(a - nudged).max() < 0.02


def test_unknown_texture_kind_is_refused():
  with pytest.raises(ValueError, match="unknown texture kind"):
    raytrace.Texture("marble")


def test_forward_walk_is_a_smooth_opencv_trajectory():
  frames = 32
  c2w = cameras.forward_walk(np.random.default_rng(7), frames, np.zeros(3), heading=0.3)
  assert c2w.shape == (frames, 4, 4)
  rot = c2w[:, :3, :3]
  np.testing.assert_allclose(
    rot @ np.swapaxes(rot, 1, 2), np.broadcast_to(np.eye(3), rot.shape), atol=1e-9
  )
  np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-9)
  assert (rot[:, :, 1] @ cameras.WORLD_UP < -0.95).all()  # camera +y (down) points down: upright
  steps = np.linalg.norm(np.diff(c2w[:, :3, 3], axis=0), axis=-1)
  config = cameras.WalkConfig()
  assert steps.min() > config.step[0] - 0.05 and steps.max() < config.step[1] + 0.05
  turn = np.arccos(np.clip(np.einsum("fi,fi->f", rot[1:, :, 2], rot[:-1, :, 2]), -1, 1))
  assert turn.max() < 0.1  # no jumps in look direction between frames


def test_room_scene_camera_stays_clear_of_objects_and_inside_the_room():
  scene, c2w = scenes.sample_room_scene(np.random.default_rng(11), 24)
  walls = {tuple(np.round(p.normal)): p for p in scene.planes}
  half_w, half_d = walls[(-1.0, 0.0, 0.0)].point[0], walls[(0.0, 0.0, -1.0)].point[2]
  assert (np.abs(c2w[:, 0, 3]) < half_w).all() and (np.abs(c2w[:, 2, 3]) < half_d).all()
  for obj in scene.objects:
    gap = np.linalg.norm(c2w[:, [0, 2], 3] - np.asarray(obj.center)[[0, 2]], axis=-1)
    assert gap.min() > scenes.RoomConfig().clearance


def test_re10k_like_scene_is_deterministic_by_seed():
  config = Re10kLikeConfig(supersample=1)
  a = render_re10k_like_scene(5, "train", 2, 12, 16, 3, config)
  b = render_re10k_like_scene(5, "train", 2, 12, 16, 3, config)
  c = render_re10k_like_scene(5, "train", 3, 12, 16, 3, config)
  for field in ("c2w", "intrinsics", "images", "depths"):
    np.testing.assert_array_equal(a[field], b[field])
  assert not np.array_equal(a["c2w"], c["c2w"])
  assert (a["depths"] > 0).all()  # a closed room: every ray hits something


def test_generated_chunks_read_back_with_the_same_cameras(tmp_path):
  config = Re10kLikeConfig(supersample=1, scenes_per_chunk=2)
  index = generate_re10k_like(
    tmp_path, num_train=3, num_test=1, height=H, width=W, frames=4, seed=9, config=config
  )
  assert sorted((tmp_path / "train").iterdir()) == [
    tmp_path / "train" / n
    for n in ("000000.depth.npz", "000000.torch", "000001.depth.npz", "000001.torch", "index.json")
  ]
  assert json.loads((tmp_path / "train" / "index.json").read_text()) == index["train"]
  assert len(index["train"]) == 3 and len(index["test"]) == 1
  scenes_read = read_chunk(tmp_path / "train" / "000001.torch")
  assert [s["key"] for s in scenes_read] == ["synthetic9_train_000002"]
  expected = render_re10k_like_scene(9, "train", 2, H, W, 4, config)
  got = scenes_read[0]
  np.testing.assert_allclose(got["c2w"], expected["c2w"], atol=2e-5)
  np.testing.assert_allclose(got["intrinsics"], expected["intrinsics"], rtol=1e-5)
  assert got["images"].shape == (4, H, W, 3)
  assert np.abs(got["images"].astype(float) - expected["images"]).mean() < 4.0  # JPEG q95


def test_generated_dataset_batches_through_the_chunked_source_and_pipeline(tmp_path):
  from tokengs_jax.data.chunked import ChunkedSceneSource
  from tokengs_jax.data.pipeline import ExampleConfig, InputPipeline
  from tokengs_jax.data.sampler import BoundedSamplerConfig

  generate_re10k_like(
    tmp_path,
    num_train=2,
    num_test=0,
    height=H,
    width=W,
    frames=8,
    seed=1,
    config=Re10kLikeConfig(supersample=1),
  )
  source = ChunkedSceneSource(tmp_path / "train")
  assert len(source) == 2
  # Synthetic clips are short (each frame moves further than an RE10K frame): a scaled-down sampler.
  config = ExampleConfig(image_shape=(16, 16), sampler=BoundedSamplerConfig(2, 3, 3, 7, 0, 0, 3, 7))
  pipeline = InputPipeline(
    source, config, batch_size=2, seed=0, num_epochs=1, shard_index=0, shard_count=1
  )
  batch = next(iter(pipeline))
  assert batch["context_images"].shape == (2, 2, 16, 16, 3) and batch["target_c2w"].shape == (
    2,
    3,
    4,
    4,
  )
  assert np.isfinite(batch["context_c2w"]).all() and 0.0 <= batch["context_images"].min() <= 1.0


# ----------------------------------------------------------------------------------------------
# The gallery family (out-of-distribution test set)


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
