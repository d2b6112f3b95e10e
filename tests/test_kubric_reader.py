"""Kubric reader: the depth convention (ray distance, as real Kubric) on a ray-traced plane, the
motion truth (segmentations, object poses) read back as the generator drew it and optional, and
the scenes it refuses (a missing camera tar, a tar without every frame its metadata lists) with
errors naming the tar and member, through the pipeline's `skip_bad` like any bad data."""

import dataclasses
import io
import json
import shutil
import tarfile

import numpy as np
import pytest
import tifffile
from PIL import Image

from tokengs_jax.data import DATASET_PRESETS, BadExampleError, InputPipeline, kubric, make_example
from tokengs_jax.data.synthetic import generate, scenes
from tokengs_jax.data.synthetic.raytrace import Box, Plane, Scene, render
from tokengs_jax.data.synthetic.scenes import random_rotation

H, W, FRAMES, CAMERAS = 8, 8, 4, 3
CONFIG = dataclasses.replace(DATASET_PRESETS["kubric"], image_shape=(H, W), random_flip=False)


# ---- depth: the distance along each pixel's ray


def test_depth_of_a_traced_plane_is_the_ray_distance_and_unprojects_onto_the_plane(tmp_path):
  height, width, focal, sensor = 12, 16, 20.0, 32.0  # wide lens: off-axis rays differ from z
  intrinsics = kubric.intrinsics_from_metadata(focal, sensor, height, width)
  rng = np.random.default_rng(3)
  c2w = np.eye(4)
  c2w[:3, :3], c2w[:3, 3] = random_rotation(rng), [0.4, 1.5, -2.0]
  forward, right, down = c2w[:3, 2], c2w[:3, 0], c2w[:3, 1]
  point = c2w[:3, 3] + 5.0 * forward
  normal = -forward + 0.4 * right + 0.3 * down
  normal /= np.linalg.norm(normal)
  tangent = np.cross(normal, forward)
  plane = Plane(point, normal, tangent / np.linalg.norm(tangent))
  traced = render(Scene(planes=(plane,)), c2w, intrinsics, height, width)
  assert (traced.ids == 0).all()
  positions, quats = kubric.opencv_to_kubric_pose(np.stack([c2w, c2w]))
  metadata = {
    "metadata": {"resolution": [height, width], "num_frames": 2},
    "camera": {
      "focal_length": focal,
      "sensor_width": sensor,
      "positions": positions.tolist(),
      "quaternions": quats.tolist(),
    },
  }
  stored = kubric.z_to_ray_depth(np.stack([traced.depth] * 2), intrinsics)
  (tmp_path / "v0" / "plane").mkdir(parents=True)
  images = np.round(np.stack([traced.rgb] * 2) * 255).astype(np.uint8)
  generate.write_kubric_view(tmp_path / "v0" / "plane" / "output_000.tar", metadata, images, stored)

  record = kubric.KubricSceneSource(tmp_path, ["v0"], num_cameras=1)[0]
  depth, pose, read_intrinsics = record["depths"][1], record["c2w"][1], record["intrinsics"][1]

  # Analytic distance from the camera centre to the plane along each pixel-centre ray.
  rows, cols = np.mgrid[0:height, 0:width] + 0.5
  fx, fy, cx, cy = intrinsics.astype(np.float64)
  rays = np.stack([(cols - cx) / fx, (rows - cy) / fy, np.ones_like(cols)], -1)
  rays = rays / np.linalg.norm(rays, axis=-1, keepdims=True) @ c2w[:3, :3].T
  expected = ((point - c2w[:3, 3]) @ normal) / (rays @ normal)
  np.testing.assert_allclose(depth, expected, rtol=2e-5)
  np.testing.assert_allclose(kubric.ray_depth_to_z(depth, read_intrinsics), traced.depth, rtol=2e-5)

  on_plane = (kubric.unproject_ray_depth(depth, pose, read_intrinsics) - point) @ normal
  np.testing.assert_allclose(on_plane, 0.0, atol=1e-4)
  # a tar without segmentations or object instances (as the official loader expects) loads
  assert "object_poses" not in record and not record["segmentations"].present(1)
  # Read as planar z (the previous convention), the corner points leave the plane by decimetres.
  as_z = np.stack([(cols - cx) / fx * depth, (rows - cy) / fy * depth, depth], -1)
  off_plane = (as_z @ np.asarray(pose[:3, :3], np.float64).T + pose[:3, 3] - point) @ normal
  assert np.abs(off_plane).max() > 0.1


def test_pointmap_scale_reads_the_stored_depth_as_the_official_provider():
  # The official `_compute_pointmap_scale`: depth x ((u - cx) / fx, (v - cy) / fy, 1) at integer
  # pixels, whatever the file's convention; on ray distances it is that formula, not the geometry.
  rng = np.random.default_rng(0)
  depths = rng.uniform(1.0, 4.0, (2, 3, 5)).astype(np.float32)
  intrinsics = np.array([[4.0, 3.0, 2.5, 1.5], [5.0, 5.0, 2.0, 1.0]])
  c2w = np.tile(np.eye(4), (2, 1, 1))
  c2w[:, :3, 3] = [[0.0, 0.0, 1.0], [0.5, -0.2, 0.0]]
  rows, cols = np.mgrid[0:3, 0:5]
  distances = []
  for depth, pose, (fx, fy, cx, cy) in zip(depths, c2w, intrinsics):
    points = np.stack([(cols - cx) / fx * depth, (rows - cy) / fy * depth, depth], -1)
    distances.append(np.linalg.norm(points.reshape(-1, 3) + pose[:3, 3], axis=-1))
  expected = np.concatenate(distances).mean()
  assert kubric.pointmap_scale(depths, c2w, intrinsics) == pytest.approx(expected, rel=1e-6)
  # a NaN or inf depth value would make the scale, and so every camera position, NaN (or, NaN
  # being no "depth > 1e-8" pixel, a NaN-only map would silently give the scale 1.0): refused
  for bad in (np.inf, np.nan):
    poisoned = depths.copy()
    poisoned[1, 2, 3] = bad
    with pytest.raises(kubric.KubricError, match="1 of 30 depth values are NaN or inf"):
      kubric.pointmap_scale(poisoned, c2w, intrinsics)


# ---- scenes the reader refuses


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
  root = tmp_path_factory.mktemp("kubric_reader")
  config = generate.KubricLikeConfig(supersample=1)
  generate.generate_kubric_like(root, 1, H, W, FRAMES, CAMERAS, seed=2, config=config)
  return root / "v0" / "scene_000000"


def _copy(generated, root, name="scene_000000"):
  shutil.copytree(generated, root / "v0" / name)
  return root / "v0" / name


def _member_offsets(path) -> dict:
  """member name -> (header offset, data offset, size)."""
  with tarfile.open(path) as tar:
    return {m.name: (m.offset, m.offset_data, m.size) for m in tar.getmembers()}


def _cut(path, at: int):
  path.write_bytes(path.read_bytes()[:at])


def _rewrite(path, change: dict):
  """Rebuilds the tar with members replaced (name -> bytes) or dropped (name -> None)."""
  with tarfile.open(path) as tar:
    members = [(m.name, tar.extractfile(m).read()) for m in tar.getmembers()]
  with tarfile.open(path, "w") as tar:
    for name, data in members:
      data = change.get(name, data)
      if data is not None:
        info = tarfile.TarInfo(name)
        info.size = len(data)
        tar.addfile(info, io.BytesIO(data))


def test_a_scene_without_its_last_camera_tar_is_rejected(generated, tmp_path):
  scene = _copy(generated, tmp_path)
  assert kubric.KubricSceneSource(tmp_path, num_cameras=CAMERAS)[0]["num_cameras"] == CAMERAS
  assert kubric.KubricSceneSource(tmp_path, num_cameras=None)[0]["num_cameras"] == CAMERAS
  # the default expects the official 9-camera rig
  with pytest.raises(kubric.KubricError, match=r"scene_000000/output_003\.tar is missing.*=9"):
    kubric.KubricSceneSource(tmp_path)[0]
  (scene / "output_002.tar").unlink()
  with pytest.raises(
    kubric.KubricError, match=r"scene_000000: camera tar \S*scene_000000/output_002\.tar is missing"
  ):
    kubric.KubricSceneSource(tmp_path, num_cameras=CAMERAS)[0]
  # configured as a 2-camera rig, the scene is whole (further tars would be ignored, as official)
  assert kubric.KubricSceneSource(tmp_path, num_cameras=2)[0]["num_cameras"] == 2
  # num_cameras=None takes the tars there are, but not around a gap
  (scene / "output_001.tar").rename(scene / "output_002.tar")
  with pytest.raises(kubric.KubricError, match=r"output_001\.tar is missing"):
    kubric.KubricSceneSource(tmp_path, num_cameras=None)[0]


@pytest.mark.parametrize(
  "cut, message",
  [
    # at a member boundary the tar reads as a valid, shorter one
    ("header ./rgba_00002.png", r"output_001\.tar member \./rgba_00002\.png is missing.*4 frames"),
    ("header ./depth_00003.tiff", r"output_001\.tar member \./depth_00003\.tiff is missing"),
    # inside a member: tarfile finds the end of data missing
    ("inside ./rgba_00002.png", r"output_001\.tar: not a readable tar"),
  ],
)
def test_a_tar_without_every_listed_frame_rejects_the_scene(generated, tmp_path, cut, message):
  scene = _copy(generated, tmp_path)
  tar = scene / "output_001.tar"
  where, name = cut.split(" ")
  header, data, size = _member_offsets(tar)[name]
  _cut(tar, header if where == "header" else data + size // 2)
  source = kubric.KubricSceneSource(tmp_path, num_cameras=CAMERAS)
  with pytest.raises(kubric.KubricError, match=message):
    source[0]  # the whole scene, not only the examples that draw the lost frames
  with pytest.raises(kubric.KubricError, match=message):
    kubric.read_kubric_view(tar, [0])


def test_metadata_frame_count_must_match_the_poses(generated, tmp_path):
  scene = _copy(generated, tmp_path)
  tar = scene / "output_000.tar"
  with tarfile.open(tar) as handle:
    metadata = json.load(handle.extractfile("./metadata.json"))
  metadata["metadata"]["num_frames"] = FRAMES + 1
  _rewrite(tar, {"./metadata.json": json.dumps(metadata).encode()})
  with pytest.raises(kubric.KubricError, match=r"output_000\.tar: metadata.json num_frames 5"):
    kubric.KubricSceneSource(tmp_path, num_cameras=CAMERAS)[0]


def _views(camera: int, frame: int):
  """Context views (camera, frame) and (camera 1 - ..., frame 0), one target: flat indices."""
  other = (camera + 1) % CAMERAS
  return np.array([camera * FRAMES + frame, other * FRAMES]), np.array([other * FRAMES + 1])


def _tiff(depth):
  buffer = io.BytesIO()
  tifffile.imwrite(buffer, np.asarray(depth, np.float32))
  return buffer.getvalue()


def _depth_with(values: dict):
  """A depth map of the scene's size at 5.0, but `values` at the given (row, col) pixels."""
  depth = np.full((H, W), 5.0, np.float32)
  for pixel, value in values.items():
    depth[pixel] = value
  return _tiff(depth)


def _small_png(shape):
  buffer = io.BytesIO()
  Image.new("RGBA", shape[::-1]).save(buffer, format="PNG")
  return buffer.getvalue()


@pytest.mark.parametrize(
  "change, message",
  [
    ({"./rgba_00001.png": b"\0" * 64}, r"member \./rgba_00001\.png: corrupt image"),
    ({"./rgba_00001.png": _small_png((4, 6))}, r"member \./rgba_00001\.png is \[4, 6\]"),
    ({"./depth_00001.tiff": b"\0" * 64}, r"member \./depth_00001\.tiff: corrupt image"),
    ({"./depth_00001.tiff": _tiff(np.ones((4, 4)))}, r"member \./depth_00001\.tiff is \[4, 4\]"),
    # one inf pixel would make the pointmap scale and every camera position NaN; a NaN-only map
    # has no pixel with depth > 1e-8 and would silently give the scale 1.0
    (
      {"./depth_00001.tiff": _depth_with({(3, 5): np.inf})},
      r"member \./depth_00001\.tiff: 1 of 64 depth values are NaN or inf",
    ),
    (
      {"./depth_00001.tiff": _tiff(np.full((H, W), np.nan))},
      r"member \./depth_00001\.tiff: 64 of 64 depth values are NaN or inf",
    ),
    # depth is optional in a tar; the pointmap scale then names the member it lacks
    (
      {f"./depth_{f:05d}.tiff": None for f in range(FRAMES)},
      r"member \./depth_00001\.tiff is miss",
    ),
  ],
)
def test_frame_errors_name_the_tar_and_member(generated, tmp_path, change, message):
  scene = _copy(generated, tmp_path)
  _rewrite(scene / "output_002.tar", change)
  record = kubric.KubricSceneSource(tmp_path, num_cameras=CAMERAS)[0]
  with pytest.raises(BadExampleError, match=rf"output_002\.tar {message}") as error:
    make_example(record, CONFIG, np.random.default_rng(0), views=_views(2, 1))
  assert isinstance(error.value.__cause__, kubric.KubricError)
  # frames of the scene's sound members still make examples
  make_example(record, CONFIG, np.random.default_rng(0), views=_views(0, 1))


def test_target_masks_are_the_png_alpha_read_only_when_asked(generated, tmp_path):
  """`alphas` is each `rgba_*.png`'s alpha channel (the generator writes opaque frames: all
  255); `target_masks` carries the targets' alpha / 255 (the official mask loss's truth), and an
  example that is not asked for them never decodes them."""
  scene = _copy(generated, tmp_path)
  record = kubric.KubricSceneSource(tmp_path, num_cameras=CAMERAS)[0]
  assert record["alphas"][5].dtype == np.uint8 and (record["alphas"][5] == 255).all()
  alpha = np.zeros((H, W), np.uint8)
  alpha[:, : W // 2], alpha[0, -1] = 255, 51  # left half foreground, one 20 % pixel
  rgb = np.asarray(Image.open(io.BytesIO(_read_member(scene / "output_001.tar", 1))))[..., :3]
  buffer = io.BytesIO()
  Image.fromarray(np.concatenate([rgb, alpha[..., None]], -1), "RGBA").save(buffer, format="PNG")
  _rewrite(scene / "output_001.tar", {"./rgba_00001.png": buffer.getvalue()})
  record = kubric.KubricSceneSource(tmp_path, num_cameras=CAMERAS)[0]
  views = _views(0, 1)  # the target: camera 1, frame 1
  example = make_example(
    record, dataclasses.replace(CONFIG, target_masks=True), np.random.default_rng(0), views=views
  )
  np.testing.assert_allclose(example["target_masks"][0], alpha / np.float32(255.0), atol=1e-7)
  np.testing.assert_array_equal(example["target_images"][0] * 255, rgb.astype(np.float32))

  class Unread:  # any read of an alpha would fail the example
    def __getitem__(self, index):
      raise AssertionError("an alpha was decoded without target_masks")

  assert "target_masks" not in make_example(
    {**record, "alphas": Unread()}, CONFIG, np.random.default_rng(0), views=views
  )


def _read_member(path, frame: int) -> bytes:
  with tarfile.open(path) as tar:
    return tar.extractfile(f"./rgba_{frame:05d}.png").read()


# ---- motion truth: segmentations and object poses


def _surface_gap(primitive, points: np.ndarray) -> np.ndarray:
  """How far points [N, 3] are from a sphere's or box's surface.  -> [N]."""
  local = (points - primitive.center) @ np.asarray(primitive.rotation)
  if isinstance(primitive, Box):
    return np.abs(np.max(np.abs(local) - primitive.half_size, axis=-1))
  return np.abs(np.linalg.norm(local, axis=-1) - primitive.radius)


def test_segmentations_and_object_poses_read_back_as_the_generator_drew_them(generated):
  record = kubric.KubricSceneSource(generated.parent.parent, num_cameras=CAMERAS)[0]
  config = generate.KubricLikeConfig(supersample=1)
  drawn = generate.render_kubric_like_scene(2, 0, H, W, FRAMES, CAMERAS, config)
  dynamic = scenes.sample_dynamic_scene(generate.scene_rng(2, "train", 0), config.dynamic)
  poses = record["object_poses"]
  assert poses.shape == (len(dynamic.objects), FRAMES, 4, 4)
  with tarfile.open(generated / "output_001.tar") as tar:  # Kubric's palette PNG
    assert Image.open(tar.extractfile("./segmentation_00002.png")).mode == "P"
  seen = set()
  for camera, frame in ((0, 0), (1, 2), (2, FRAMES - 1)):
    at = camera * FRAMES + frame
    segmentation = record["segmentations"][at]
    np.testing.assert_array_equal(segmentation, drawn["segmentations"][camera, frame])
    moved = dynamic.at(frame / config.dynamic.frame_rate).objects
    points = kubric.unproject_ray_depth(
      record["depths"][at], record["c2w"][at], record["intrinsics"][at]
    )
    for k, start in enumerate(dynamic.objects):
      np.testing.assert_allclose(poses[k, frame, :3, 3], moved[k].center, atol=1e-6)
      np.testing.assert_allclose(poses[k, frame, :3, :3], moved[k].rotation, atol=1e-6)
      # every pixel numbered k + 1 sees object k: carried back to time 0 by the poses read
      # from the files, its surface point lies on the object as it started
      mine = points[segmentation == k + 1]
      back = poses[k, 0] @ np.linalg.inv(poses[k, frame])
      at_start = mine @ back[:3, :3].T + back[:3, 3]
      assert (_surface_gap(start, at_start) < 1e-3).all(), (camera, frame, k)
      seen |= {k} if len(mine) else set()
  assert len(seen) >= 2


def _metadata(tar) -> dict:
  with tarfile.open(tar) as handle:
    return json.load(handle.extractfile("./metadata.json"))


def test_cameras_listing_other_instances_leave_the_motion_truth_out(generated, tmp_path, caplog):
  scene = _copy(generated, tmp_path)
  metadata = _metadata(scene / "output_001.tar")
  metadata["instances"] = metadata["instances"][1:]  # e.g. only the objects this camera sees
  _rewrite(scene / "output_001.tar", {"./metadata.json": json.dumps(metadata).encode()})
  record = kubric.KubricSceneSource(tmp_path, num_cameras=CAMERAS)[0]
  assert "object_poses" not in record
  assert "output_001.tar lists other object instances than output_000.tar" in caplog.text
  assert record["segmentations"].present(0)  # the frames still read


@pytest.mark.parametrize(
  "change, message",
  [
    (lambda m: m["instances"][0].pop("quaternions"), r"bad metadata.json instances \(KeyError"),
    (
      lambda m: m["instances"][1].update(positions=[[0.0, 0.0, 0.0]]),
      r"instance 1 positions \[1, 3\] / quaternions \[4, 4\] must be \[4, 3\] / \[4, 4\]",
    ),
    (
      lambda m: m["instances"][0]["positions"][2].__setitem__(0, float("nan")),
      "instance 0: NaN/inf",
    ),
  ],
)
def test_malformed_instances_are_kubric_errors_naming_the_tar(generated, tmp_path, change, message):
  scene = _copy(generated, tmp_path)
  metadata = _metadata(scene / "output_002.tar")
  change(metadata)
  _rewrite(scene / "output_002.tar", {"./metadata.json": json.dumps(metadata).encode()})
  with pytest.raises(kubric.KubricError, match=rf"output_002\.tar: (metadata.json )?{message}"):
    kubric.KubricSceneSource(tmp_path, num_cameras=CAMERAS)[0]


def test_segmentations_are_all_or_none_and_one_number_per_pixel(generated, tmp_path):
  scene = _copy(generated, tmp_path)
  _rewrite(scene / "output_000.tar", {"./segmentation_00002.png": None})
  with pytest.raises(kubric.KubricError, match=r"member \./segmentation_00002\.png is missing"):
    kubric.KubricSceneSource(tmp_path, num_cameras=CAMERAS)[0]
  _rewrite(scene / "output_000.tar", {f"./segmentation_{f:05d}.png": None for f in range(FRAMES)})
  _rewrite(scene / "output_001.tar", {"./segmentation_00001.png": _small_png((H, W))})
  record = kubric.KubricSceneSource(tmp_path, num_cameras=CAMERAS)[0]
  assert not record["segmentations"].present(1) and record["segmentations"].present(FRAMES)
  with pytest.raises(kubric.KubricError, match=r"segmentation_00001\.png: a segmentation holds"):
    record["segmentations"][FRAMES + 1]


def test_refused_scenes_are_counted_rejections_under_skip_bad(generated, tmp_path):
  _copy(generated, tmp_path, "a_good")
  (_copy(generated, tmp_path, "b_missing_tar") / "output_002.tar").unlink()
  cut = _copy(generated, tmp_path, "c_cut") / "output_000.tar"
  _cut(cut, _member_offsets(cut)["./rgba_00003.png"][0])
  source = kubric.KubricSceneSource(tmp_path, ["v0"], num_cameras=CAMERAS)
  pipeline = InputPipeline(
    source,
    CONFIG,
    batch_size=1,
    shard_index=0,
    shard_count=1,
    num_epochs=1,
    shuffle=False,
    skip_bad=True,
    select_views=kubric.kubric_view_selector(2, 1, 1, 3),
  )
  assert [int(b["scene_index"][0]) for b in pipeline] == [0]
  assert dict(pipeline.rejections.counts) == {"KubricError": 2}
  messages = "\n".join(pipeline.rejections.messages)
  assert "b_missing_tar/output_002.tar is missing" in messages
  assert "c_cut/output_000.tar member ./rgba_00003.png is missing" in messages
  with pytest.raises(kubric.KubricError, match=r"b_missing_tar.*output_002\.tar is missing"):
    list(
      InputPipeline(
        source,
        CONFIG,
        batch_size=1,
        shard_index=0,
        shard_count=1,
        num_epochs=1,
        shuffle=False,
        select_views=kubric.kubric_view_selector(2, 1, 1, 3),
      )
    )
