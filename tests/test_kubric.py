"""Kubric-4D reader: conventions (OpenGL -> OpenCV, quaternions, intrinsics), tar round trips of
generated scenes, index sampling, time normalisation, pointmap scale and examples assembled by the
input pipeline (the one Kubric path), including a resumed pipeline."""

import dataclasses

import io
import json
import tarfile
import threading

import jax.numpy as jnp
import numpy as np
import pytest

from tokengs_jax import camera
from tokengs_jax.data import (
  DATASET_PRESETS,
  InputPipeline,
  NotEnoughFramesError,
  kubric,
  make_example,
)
from tokengs_jax.data.transforms import normalize_times
from tokengs_jax.data.synthetic import generate
from tokengs_jax.data.synthetic.scenes import random_rotation

H, W, FRAMES, CAMERAS = 16, 16, 6, 3


@pytest.fixture(scope="module")
def kubric_root(tmp_path_factory):
  root = tmp_path_factory.mktemp("kubric")
  config = generate.KubricLikeConfig(supersample=1)
  generate.generate_kubric_like(root, 2, H, W, FRAMES, CAMERAS, seed=4, config=config)
  return root, config


CONFIG = dataclasses.replace(DATASET_PRESETS["kubric"], image_shape=(H, W), random_flip=False)


def _example(root, index, seed, num_context=2, num_targets=2, config=CONFIG):
  """The pipeline's example of scene `index`, views drawn from `default_rng(seed)`."""
  record = kubric.KubricSceneSource(root, num_cameras=CAMERAS)[index]
  rng = np.random.default_rng(seed)
  views = kubric.kubric_view_selector(num_context, num_targets, 2, 5)(record, rng, 0)
  return make_example(record, config, rng, views=views)


def test_the_selector_can_take_the_inputs_from_fewer_cameras_in_turn(kubric_root):
  """`context_cameras=2`: four inputs from two of the drawn cameras in turn (each at two times),
  targets at one frame from the first two; frames and the official draws otherwise unchanged."""
  root, _ = kubric_root
  record = kubric.KubricSceneSource(root, num_cameras=CAMERAS)[0]
  frames = record["num_frames"]
  for seed in range(5):
    official = kubric.kubric_view_selector(4, 2, 2, 5)(record, np.random.default_rng(seed), 0)
    paired = kubric.kubric_view_selector(4, 2, 2, 5, context_cameras=2)(
      record, np.random.default_rng(seed), 0
    )
    np.testing.assert_array_equal(paired[0] % frames, official[0] % frames)
    cameras = official[0] // frames
    assert (paired[0] // frames).tolist() == [*cameras[:2], *cameras[:2]]
    np.testing.assert_array_equal(paired[1], official[1])
  with pytest.raises(ValueError, match="context_cameras"):
    kubric.kubric_view_selector(4, 2, context_cameras=-1)


def test_stored_quaternions_are_normalised_and_degenerate_ones_refused():
  quarter_turn_z = np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
  rotation = kubric.quat_wxyz_to_rotation(quarter_turn_z)
  # a stored length off 1 gives the same rotation (the official loader's would scale it by 1.21)
  np.testing.assert_allclose(
    kubric.quat_wxyz_to_rotation(1.1 * quarter_turn_z), rotation, atol=1e-12
  )
  for bad in (np.zeros(4), np.array([np.nan, 0, 0, 1.0])):
    with pytest.raises(ValueError, match="quaternion"):
      kubric.quat_wxyz_to_rotation(np.stack([quarter_turn_z, bad]))


def test_quaternion_conversions_invert_each_other_and_follow_hamilton():
  rng = np.random.default_rng(0)
  rotations = np.stack([random_rotation(rng) for _ in range(50)])
  quats = kubric.rotation_to_quat_wxyz(rotations)
  np.testing.assert_allclose(np.linalg.norm(quats, axis=-1), 1.0, atol=1e-12)
  np.testing.assert_allclose(kubric.quat_wxyz_to_rotation(quats), rotations, atol=1e-12)
  # Hamilton: (cos 45, 0, 0, sin 45) turns +x into +y
  quarter_turn_z = np.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])
  np.testing.assert_allclose(
    kubric.quat_wxyz_to_rotation(quarter_turn_z) @ [1, 0, 0], [0, 1, 0], atol=1e-12
  )
  # 180-degree turns (trace -1) are where trace-based conversions break
  half_turn = np.diag([1.0, -1.0, -1.0])
  np.testing.assert_allclose(
    kubric.quat_wxyz_to_rotation(kubric.rotation_to_quat_wxyz(half_turn)), half_turn, atol=1e-12
  )


def _write_handmade_view(path, position, quaternion, height=H, width=W):
  """A tar with metadata written by hand (not through our pose conversion)."""
  metadata = {
    "metadata": {"resolution": [height, width]},
    "camera": {
      "focal_length": 35.0,
      "sensor_width": 32.0,
      "positions": [list(position)] * 2,
      "quaternions": [list(quaternion)] * 2,
    },
  }
  images = np.zeros((2, height, width, 3), np.uint8)
  generate.write_kubric_view(path, metadata, images, np.ones((2, height, width), np.float32))


def test_opengl_camera_projects_known_points_through_the_opencv_pose(tmp_path):
  # Kubric/Blender camera with identity rotation: looks down world -z, image up is world +y.
  position = np.array([1.0, 2.0, 3.0])
  _write_handmade_view(tmp_path / "output_000.tar", position, [1.0, 0.0, 0.0, 0.0])
  view = kubric.read_kubric_view(tmp_path / "output_000.tar", [1])
  fx, fy, cx, cy = view["intrinsics"][0]
  np.testing.assert_allclose([fx, fy, cx, cy], [35.0 * W / 32.0, 35.0 * H / 32.0, W / 2, H / 2])
  points = position + np.array(
    [
      [0.0, 0.0, -4.0],  # straight ahead
      [1.0, 0.0, -4.0],  # to the right
      [0.0, 1.0, -2.0],
    ]
  )  # above
  w2c = np.linalg.inv(view["c2w"][0])[None]
  uv, depth = camera.project_points(
    jnp.asarray(points, jnp.float32), jnp.asarray(w2c), jnp.asarray(view["intrinsics"])
  )
  np.testing.assert_allclose(np.asarray(depth[0]), [4.0, 4.0, 2.0], rtol=1e-6)
  np.testing.assert_allclose(
    np.asarray(uv[0]), [[cx, cy], [cx + fx / 4.0, cy], [cx, cy - fy / 2.0]], rtol=1e-5
  )


def test_rotated_opengl_camera_matches_a_look_at_pose(tmp_path):
  # A Blender camera turned 90 degrees about +y looks down world -x.
  quat = [np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4), 0.0]
  _write_handmade_view(tmp_path / "output_000.tar", [0.0, 0.0, 0.0], quat)
  c2w = kubric.read_kubric_view(tmp_path / "output_000.tar", [0], load_images=False)["c2w"][0]
  np.testing.assert_allclose(c2w[:3, 2], [-1.0, 0.0, 0.0], atol=1e-6)  # OpenCV forward
  np.testing.assert_allclose(c2w[:3, 1], [0.0, -1.0, 0.0], atol=1e-6)  # OpenCV down


def test_generated_tars_round_trip_frames_cameras_and_depth(kubric_root):
  root, config = kubric_root
  expected = generate.render_kubric_like_scene(4, 1, H, W, FRAMES, CAMERAS, config)
  scene_dir = root / "v0" / "scene_000001"
  with tarfile.open(scene_dir / "output_002.tar") as tar:
    names = tar.getnames()
  assert (
    names[0] == "./metadata.json" and "./rgba_00005.png" in names and "./depth_00000.tiff" in names
  )
  view = kubric.read_kubric_view(scene_dir / "output_002.tar", [4, 1], load_depth=True)
  assert view["num_frames"] == FRAMES and (view["height"], view["width"]) == (H, W)
  np.testing.assert_array_equal(view["images"], expected["images"][2, [4, 1]])  # PNG is lossless
  np.testing.assert_array_equal(view["depths"], expected["depths"][2, [4, 1]])
  np.testing.assert_allclose(view["c2w"], expected["c2w"][2, [4, 1]], atol=1e-6)
  np.testing.assert_allclose(view["intrinsics"][0], expected["intrinsics"], rtol=1e-6)
  # the scene is dynamic: the same camera sees different images over time
  assert not np.array_equal(expected["images"][0, 0], expected["images"][0, -1])


def test_rendered_depth_unprojects_to_the_same_point_in_another_camera(kubric_root):
  """Cross-view geometry through the reader's cameras: a pixel's depth point from camera 0
  (stored ray distance along the pixel-centre ray, as Kubric), projected into camera 1 at the same
  frame, lands where camera 1's depth agrees (if visible)."""
  root, _ = kubric_root
  scene_dir = root / "v0" / "scene_000000"
  views = [
    kubric.read_kubric_view(scene_dir / f"output_{c:03d}.tar", [3], load_depth=True) for c in (0, 1)
  ]
  world = kubric.unproject_ray_depth(
    views[0]["depths"][0], views[0]["c2w"][0], views[0]["intrinsics"][0]
  ).reshape(-1, 3)
  uv, depth = camera.project_points(
    jnp.asarray(world, jnp.float32),
    jnp.asarray(np.linalg.inv(views[1]["c2w"][0]))[None],
    jnp.asarray(views[1]["intrinsics"][:1]),
  )
  uv, depth = np.asarray(uv[0]), np.asarray(depth[0])
  inside = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H) & (depth > 0)
  # Inverse depth of a plane is affine in pixel coordinates: interpolating it between the four
  # nearest pixel centres is exact inside one surface, so agreement is tight where not occluded.
  x, y = (uv[inside] - 0.5).T
  x0, y0 = np.clip(np.floor(x), 0, W - 2).astype(int), np.clip(np.floor(y), 0, H - 2).astype(int)
  fx_, fy_ = x - x0, y - y0
  # inverse planar z (not inverse ray distance) is the affine one
  inverse = 1.0 / kubric.ray_depth_to_z(views[1]["depths"][0], views[1]["intrinsics"][0])
  seen = 1.0 / (
    (1 - fy_) * ((1 - fx_) * inverse[y0, x0] + fx_ * inverse[y0, x0 + 1])
    + fy_ * ((1 - fx_) * inverse[y0 + 1, x0] + fx_ * inverse[y0 + 1, x0 + 1])
  )
  relative = np.abs(seen - depth[inside]) / depth[inside]
  assert inside.sum() > 50
  assert np.mean(relative < 1e-3) > 0.5  # interior of shared surfaces; the rest: edges, occlusion


def test_sample_dynamic_indices_properties():
  for seed in range(30):
    frames, views = kubric.sample_dynamic_indices(np.random.default_rng(seed), 24, 9, 4, 3, 23)
    context, target = frames[:-1], frames[-1]
    assert len(frames) == 5 and np.all(np.diff(context) > 0)
    assert 3 <= context[-1] - context[0] <= 23 and context[0] <= target <= context[-1]
    assert len(set(views.tolist())) == 4 and views.max() < 9
    again = kubric.sample_dynamic_indices(np.random.default_rng(seed), 24, 9, 4, 3, 23)
    np.testing.assert_array_equal(frames, again[0])
    fixed, _ = kubric.sample_dynamic_indices(
      np.random.default_rng(seed), 24, 9, 4, 3, 23, interp_target=False
    )
    assert fixed[-1] in fixed[:-1]
  _, cycled = kubric.sample_dynamic_indices(np.random.default_rng(0), 24, 2, 4)
  assert sorted(cycled.tolist()) == [0, 0, 1, 1]
  with pytest.raises(NotEnoughFramesError, match="fewer than"):  # skip_bad drops such scenes
    kubric.sample_dynamic_indices(np.random.default_rng(0), 3, 9, 4)


def test_normalize_times_is_min_max_over_the_example():
  np.testing.assert_allclose(normalize_times(np.array([5, 9, 7, 13, 9])), [0, 0.5, 0.25, 1, 0.5])
  # one instant (official: 0 / 0 = NaN): every time is 0
  np.testing.assert_array_equal(normalize_times(np.array([3, 3])), [0.0, 0.0])


def test_pointmap_scale_is_the_mean_distance_of_depth_points():
  # 1x2 depth map, fx = fy = 1, principal point at the origin pixel: points (0,0,2) and (3,0,3)
  depths = np.array([[[2.0, 3.0]]], np.float32)
  intrinsics = np.array([[1.0, 1.0, 0.0, 0.0]])
  pose = np.eye(4)
  pose[:3, 3] = [0.0, 0.0, 1.0]
  expected = (3.0 + np.linalg.norm([3.0, 0.0, 4.0])) / 2
  assert kubric.pointmap_scale(depths, pose[None], intrinsics) == pytest.approx(expected)
  assert kubric.pointmap_scale(np.zeros_like(depths), pose[None], intrinsics) == 1.0


def test_example_pairs_cameras_frames_and_times_as_official(kubric_root):
  root, _ = kubric_root
  example = _example(root, 1, seed=3)
  vc, vt = 2, 2
  shapes = {
    "context_images": (vc, H, W, 3),
    "context_c2w": (vc, 4, 4),
    "context_intrinsics": (vc, 4),
    "context_times": (vc,),
    "target_images": (vt, H, W, 3),
    "target_c2w": (vt, 4, 4),
    "target_intrinsics": (vt, 4),
    "target_times": (vt,),
  }
  assert {k: v.shape for k, v in example.items()} == shapes
  for key, value in _example(root, 1, seed=3).items():  # deterministic per rng
    np.testing.assert_array_equal(value, example[key])

  # Replay the draws: context v = camera v at frame v, target v = camera v at the target frame.
  frames, views = kubric.sample_dynamic_indices(np.random.default_rng(3), FRAMES, CAMERAS, 2, 2, 5)
  scene_dir = root / "v0" / "scene_000001"
  raw = [
    kubric.read_kubric_view(scene_dir / f"output_{views[v]:03d}.tar", [f])
    for v, f in [(0, frames[0]), (1, frames[1]), (0, frames[2]), (1, frames[2])]
  ]
  images = np.concatenate([example["context_images"], example["target_images"]])
  np.testing.assert_allclose(images, np.concatenate([r["images"] for r in raw]) / 255.0, atol=1e-6)
  times = np.concatenate([example["context_times"], example["target_times"]])
  np.testing.assert_allclose(times, normalize_times(frames[[0, 1, 2, 2]]))
  assert times.min() == 0.0 and times.max() == 1.0

  # Normalised cameras are a similarity of the raw ones: same relative rotations, translations
  # scaled by one factor; mean_cam puts the context cameras' mean position at the origin.
  c2w = np.concatenate([example["context_c2w"], example["target_c2w"]]).astype(np.float64)
  raw_c2w = np.concatenate([r["c2w"] for r in raw]).astype(np.float64)
  np.testing.assert_allclose(c2w[:vc, :3, 3].mean(0), 0.0, atol=1e-5)
  relative = np.linalg.inv(c2w[0]) @ c2w
  raw_relative = np.linalg.inv(raw_c2w[0]) @ raw_c2w
  np.testing.assert_allclose(relative[:, :3, :3], raw_relative[:, :3, :3], atol=1e-5)
  ratio = np.linalg.norm(relative[1:, :3, 3], axis=-1) / np.linalg.norm(
    raw_relative[1:, :3, 3], axis=-1
  )
  np.testing.assert_allclose(ratio, ratio[0], rtol=1e-4)


def test_pointmap_scale_makes_the_mean_context_point_distance_one(kubric_root):
  root, _ = kubric_root
  example = _example(root, 0, seed=1, num_context=3)
  # Depth scales with the translations, so re-measuring on the normalised cameras gives the base 1.
  frames, views = kubric.sample_dynamic_indices(np.random.default_rng(1), FRAMES, CAMERAS, 3, 2, 5)
  scene_dir = root / "v0" / "scene_000000"
  read = [
    kubric.read_kubric_view(
      scene_dir / f"output_{views[v]:03d}.tar", [frames[v]], load_images=False, load_depth=True
    )
    for v in range(3)
  ]
  depths = np.concatenate([r["depths"] for r in read])
  raw_c2w = np.concatenate([r["c2w"] for r in read])
  scale = np.linalg.norm(
    example["context_c2w"][1, :3, 3] - example["context_c2w"][0, :3, 3]
  ) / np.linalg.norm(raw_c2w[1, :3, 3] - raw_c2w[0, :3, 3])
  measured = kubric.pointmap_scale(
    depths * scale, example["context_c2w"], example["context_intrinsics"]
  )
  assert measured == pytest.approx(1.0, rel=1e-4)


def test_training_examples_flip_some_scenes(kubric_root):
  root, _ = kubric_root
  flipping = dataclasses.replace(CONFIG, random_flip=True)
  flipped_any = False
  for seed in range(6):
    example = _example(root, 0, seed, config=flipping)
    reference = _example(root, 0, seed)  # the same draws: the flip is drawn after the views
    if not np.array_equal(example["context_images"], reference["context_images"]):
      np.testing.assert_array_equal(
        example["context_images"], reference["context_images"][:, :, ::-1]
      )
      flipped_any = True
  assert flipped_any


def test_bad_kubric_files_name_the_file(tmp_path):
  broken = tmp_path / "output_000.tar"
  broken.write_bytes(b"not a tar at all")
  with pytest.raises(kubric.KubricError, match="output_000.tar"):
    kubric.read_kubric_view(broken)
  _write_handmade_view(tmp_path / "output_001.tar", [0, 0, 0], [1, 0, 0, 0])
  with pytest.raises(kubric.KubricError, match=r"output_001.tar.*outside"):
    kubric.read_kubric_view(tmp_path / "output_001.tar", [7])
  no_meta = tmp_path / "output_002.tar"
  with tarfile.open(no_meta, "w"):
    pass
  with pytest.raises(kubric.KubricError, match="metadata.json"):
    kubric.read_kubric_view(no_meta)
  with tarfile.open(tmp_path / "output_003.tar", "w") as tar:
    data = json.dumps(
      {
        "camera": {
          "positions": [[0, 0, float("nan")]],
          "quaternions": [[1, 0, 0, 0]],
          "focal_length": 35,
          "sensor_width": 32,
        },
        "metadata": {"resolution": [4, 4]},
      }
    ).encode()
    info = tarfile.TarInfo("./metadata.json")
    info.size = len(data)

    tar.addfile(info, io.BytesIO(data))
  with pytest.raises(kubric.KubricError, match="NaN"):
    kubric.read_kubric_view(tmp_path / "output_003.tar")
  with pytest.raises(kubric.KubricError, match="no Kubric scenes"):
    kubric.list_kubric_scenes(tmp_path / "empty")


def test_scene_records_batch_through_the_generic_pipeline(kubric_root):
  from tokengs_jax.data.pipeline import ExampleConfig, InputPipeline

  root, config = kubric_root
  source = kubric.KubricSceneSource(root, num_cameras=CAMERAS)
  record = source[0]
  assert len(record["images"]) == record["c2w"].shape[0] == CAMERAS * FRAMES
  selector = kubric.kubric_view_selector(num_context=2, num_targets=1, min_gap=2, max_gap=5)
  example_config = ExampleConfig(
    image_shape=(H, W), translation_scale=0.1, normalization="mean_cam", random_flip=False
  )
  pipeline = InputPipeline(
    source,
    example_config,
    batch_size=2,
    seed=0,
    shuffle=False,
    num_epochs=1,
    shard_index=0,
    shard_count=1,
    select_views=selector,
  )
  batch = next(iter(pipeline))
  assert batch["context_images"].shape == (2, 2, H, W, 3) and batch["target_images"].shape == (
    2,
    1,
    H,
    W,
    3,
  )
  assert batch["context_times"].shape == (2, 2) and batch["target_times"].shape == (2, 1)
  times = np.concatenate([batch["context_times"], batch["target_times"]], axis=1)
  np.testing.assert_array_equal(times.min(1), 0.0)
  np.testing.assert_array_equal(times.max(1), 1.0)
  # Every view of the first example is some (camera, frame) of the scene, and the example's times
  # are those frames min-max normalised.
  rendered = generate.render_kubric_like_scene(4, 0, H, W, FRAMES, CAMERAS, config)["images"]
  views = np.concatenate([batch["context_images"][0], batch["target_images"][0]])
  frames = []
  for image in views:
    matches = np.argwhere(np.all(np.abs(rendered / 255.0 - image) < 1e-6, axis=(2, 3, 4)))
    assert len(matches) >= 1
    frames.append(matches[0][1])
  np.testing.assert_allclose(times[0], normalize_times(np.array(frames)), atol=1e-6)


def _pipeline(root, **kwargs):
  return InputPipeline(
    kubric.KubricSceneSource(root, num_cameras=CAMERAS),
    CONFIG,
    batch_size=1,
    seed=5,
    shard_index=0,
    shard_count=1,
    select_views=kubric.kubric_view_selector(2, 1, 2, 5),
    **kwargs,
  )


def test_resumed_pipeline_sees_the_same_batches_as_an_uninterrupted_one(kubric_root):
  root, _ = kubric_root
  uninterrupted = _pipeline(root).iterator()
  expected = [next(uninterrupted) for _ in range(5)]  # 2 scenes: crosses an epoch boundary
  first = _pipeline(root).iterator()
  for _ in range(3):
    next(first)
  state = first.get_state()
  resumed = _pipeline(root).iterator()  # a new run: new source, new pipeline
  resumed.set_state(state)
  for batch in expected[3:]:
    got = next(resumed)
    assert set(got) == set(batch)
    for key in batch:
      np.testing.assert_array_equal(got[key], batch[key], err_msg=key)


def test_scene_metadata_is_parsed_once_per_process(kubric_root, monkeypatch):
  root, _ = kubric_root
  source = kubric.KubricSceneSource(root, num_cameras=CAMERAS)
  parsed = []
  parse = kubric.parse_kubric_view
  test_thread = threading.get_ident()

  def counting_parse(path):
    # Counts this thread's parses only: a prefetch thread an earlier test's pipeline left running
    # may still parse its own source's metadata through the patched function (seen once in CI).
    if threading.get_ident() == test_thread:
      parsed.append(path)
    return parse(path)

  monkeypatch.setattr(kubric.source, "parse_kubric_view", counting_parse)
  record = source[0]
  assert len(parsed) == CAMERAS
  monkeypatch.setattr(kubric.camera_tar.tarfile, "open", None)  # reading frames never reopens a tar
  for _ in range(3):
    record = source[0]
  assert len(parsed) == CAMERAS
  frame, depth = record["images"][CAMERAS * FRAMES - 1], record["depths"][0]
  assert frame.shape == (H, W, 3) and frame.dtype == np.uint8
  assert depth.shape == (H, W) and depth.dtype == np.float32


@pytest.mark.slow
def test_worker_processes_give_the_same_kubric_batches(kubric_root):
  root, _ = kubric_root
  inline = [b for _, b in zip(range(3), _pipeline(root))]
  workers = [b for _, b in zip(range(3), _pipeline(root, num_workers=2))]
  for a, b in zip(inline, workers):
    for key in a:
      np.testing.assert_array_equal(a[key], b[key], err_msg=key)


# ---- a static model on Kubric (official `finetune_dl3dv_kubric_static`, issue 26)


def _tiny_static_kubric(tmp_path, **changes):
  """`paper-static` at toy size: a 1-block static model (no time embedding, no dynamic tokens)
  at 16x16 on one generated training and one test scene of 2 cameras x 4 frames."""
  from experiments import kubric as kubric_cli
  from experiments.config import EvalSettings, SyntheticSettings

  static = kubric_cli.PRESETS["paper-static"]
  tiny = kubric_cli.PRESETS["synthetic-tiny"].model.replace(
    num_dynamic_gs_tokens=0,
    time_embedding=False,
    enc_depth=1,
    dec_depth=1,
    enc_embed_dim=32,
    enc_num_heads=2,
    num_gs_tokens=4,
    image_size=(H, W),
    dec_patch_size=4,
    num_input_views=2,
  )
  return dataclasses.replace(
    static,
    data_dir=None,
    synthetic_dir=str(tmp_path / "data"),
    output_dir=str(tmp_path / "out"),
    model=tiny,
    num_cameras=2,
    min_gap=1,
    max_gap=3,
    synthetic=SyntheticSettings(num_train=1, num_test=1, frames=4, num_ood=0, workers=1),
    train=dataclasses.replace(
      static.train,
      steps=3,
      batch_size=4,  # the tests' 4 CPU devices
      num_target_views=2,
      learning_rate=1e-2,
      warmup_steps=1,
      log_every=1,
      checkpoint_every=0,
      num_workers=0,
    ),
    eval=EvalSettings(
      num_scenes=1, num_target_views=2, tuning_steps=2, lpips=False, grid_scenes=1, video_frames=2
    ),
    **changes,
  )


def test_a_static_model_trains_on_kubric_targets_with_their_times_ignored(kubric_root, tmp_path):
  """The Kubric entry point's loss for a model without time embedding is the static objective
  on the target views: the same whatever the views' times, or without them."""
  import jax

  from experiments.kubric_task import KubricTask
  from tokengs_jax import model

  root, _ = kubric_root
  experiment = _tiny_static_kubric(tmp_path)
  example = _example(root, 0, seed=2)
  batch = {k: jnp.asarray(v[None]) for k, v in example.items()}
  params = model.init_params(jax.random.key(0), experiment.model)
  loss_fn = jax.jit(KubricTask().loss_fn(experiment, experiment.model))
  key, step = jax.random.key(1), jnp.asarray(0)
  loss, terms = loss_fn(params, batch, key, step)
  assert np.isfinite(float(loss)) and {"rgb", "ssim", "visibility"} <= set(terms)
  assert "dyn_aux" not in terms
  reversed_times = {**batch, "target_times": 1.0 - batch["target_times"]}
  timeless = {k: v for k, v in batch.items() if not k.endswith("_times")}
  for other in (reversed_times, timeless):
    np.testing.assert_allclose(float(loss_fn(params, other, key, step)[0]), float(loss))
  # no dynamic pictures: its Gaussians do not move
  assert KubricTask().extra_visuals(experiment, experiment.model, params, [], None, 0) == {}


@pytest.mark.slow
def test_a_static_model_runs_through_the_kubric_entry_point(tmp_path):
  """`paper-static` at toy size: a few training steps, then the Kubric protocol scores it (its
  baselines, the trained model and its token tuning; `psnr_moving` too)."""
  import json
  import math

  from experiments import tasks
  from experiments.kubric_task import KubricTask

  experiment = _tiny_static_kubric(tmp_path)
  payload = tasks.execute("run", experiment, KubricTask())
  metrics = payload["metrics"]
  assert set(metrics) == {
    "mean_colour",
    "input_average",
    "nearest_view",
    "same_camera",
    "nearest_time",
    "untrained",
    "trained",
    "trained+token_tuning",
  }
  for method in ("trained", "trained+token_tuning"):
    assert math.isfinite(metrics[method]["mean"]["psnr"])
    assert math.isfinite(metrics[method]["mean"]["psnr_moving"])
  assert metrics["trained"]["mean"]["psnr"] != metrics["untrained"]["mean"]["psnr"]  # it trained
  out = tmp_path / "out"
  history = json.loads((out / "train_history.json").read_text())
  assert len(history) == 3 and all(math.isfinite(h["loss"]) for h in history)
  assert not any("dyn_aux_weight" in h for h in history)
  assert (out / "params.msgpack").stat().st_size > 0 and not (out / "dynamic").exists()
  assert "dynamic" not in payload and "scene_flow" not in payload
