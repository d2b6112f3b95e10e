"""The held-out dynamic family (`synthetic.kubric_ood`): frozen and deterministic, unlike the
Kubric-like training scenes, written in the Kubric-4D layout (ray-distance depth, segmentations
and object poses) and scored as a second test set of every synthetic Kubric run."""

import dataclasses

import numpy as np
import pytest

from tokengs_jax.data import kubric
from tokengs_jax.data.synthetic import kubric_ood, photos, scenes
from tokengs_jax.data.synthetic.raytrace import Box, Sphere, render

H, W, FRAMES, CAMERAS = 12, 16, 3, 2
CONFIG = kubric_ood.KubricOodConfig(supersample=1)


def _textures(primitives) -> tuple[set[str], set[str]]:
  """(texture kinds, photograph names) of some primitives."""
  textures = [p.texture for p in primitives]
  return {t.kind for t in textures}, {t.image for t in textures if t.kind == "photo"}


def _all_parts(scene: kubric_ood.OrbitScene):
  return [*scene.backdrop, *(part for parts in scene.parts for part in parts)]


def test_scenes_are_frozen_and_deterministic_per_index():
  scene, c2w, focal = kubric_ood.sample_scene(3, FRAMES, CAMERAS)
  again, c2w_again, focal_again = kubric_ood.sample_scene(3, FRAMES, CAMERAS)
  np.testing.assert_array_equal(c2w, c2w_again)
  np.testing.assert_array_equal(focal, focal_again)
  for time in (0.0, 0.7):
    for first, second in zip(scene.poses(time), again.poses(time)):
      np.testing.assert_array_equal(first, second)
  # the stream is the family's own, with the frozen seed: no experiment seed enters
  rng = np.random.default_rng([kubric_ood.FROZEN_SEED, 13, 3])
  drawn = kubric_ood.sample_orbit_scene(rng)
  np.testing.assert_array_equal(drawn.poses(0.4)[1], scene.poses(0.4)[1])
  other, c2w_other, _ = kubric_ood.sample_scene(4, FRAMES, CAMERAS)
  assert not np.allclose(c2w, c2w_other)
  rendered = [kubric_ood.render_kubric_ood_scene(5, H, W, FRAMES, CAMERAS, CONFIG) for _ in "ab"]
  np.testing.assert_array_equal(rendered[0]["images"], rendered[1]["images"])
  np.testing.assert_array_equal(rendered[0]["depths"], rendered[1]["depths"])


def test_textures_and_shapes_share_nothing_with_the_training_family():
  ood_kinds, ood_photos, shapes = set(), set(), set()
  for index in range(24):
    scene = kubric_ood.sample_scene(index, FRAMES, CAMERAS)[0]
    kinds, names = _textures(_all_parts(scene))
    ood_kinds |= kinds
    ood_photos |= names
    shapes |= {len(parts) for parts in scene.parts}
  train_kinds, train_photos = set(), set()
  for index in range(24):
    dynamic = scenes.sample_dynamic_scene(np.random.default_rng([0, 0, index]))
    kinds, names = _textures([*dynamic.backdrop, *dynamic.objects])
    train_kinds |= kinds
    train_photos |= names
  assert ood_kinds == {"photo", "solid"}
  assert not ood_kinds & train_kinds and not ood_photos & train_photos
  assert ood_photos and ood_photos <= set(photos.HELD_OUT_PHOTOS)
  # every object is a composite of several parts moving together
  assert min(shapes) >= 2


def test_objects_tumble_along_curved_paths_above_the_floor():
  scene = kubric_ood.sample_scene(0, FRAMES, CAMERAS)[0]
  times = np.linspace(0.0, 2.0, 9)
  rotations, origins = zip(*(scene.poses(t) for t in times))
  rotations, origins = np.stack(rotations, 1), np.stack(origins, 1)  # [K, T, 3, 3], [K, T, 3]
  identity = np.broadcast_to(np.eye(3), rotations.shape)
  np.testing.assert_allclose(rotations @ np.swapaxes(rotations, -1, -2), identity, atol=1e-9)
  for k in range(len(scene.parts)):
    # the relative rotation between two times turns by a visible angle
    relative = rotations[k, 2] @ rotations[k, 0].T
    angle = np.arccos(np.clip((np.trace(relative) - 1.0) / 2.0, -1.0, 1.0))
    assert angle > 0.3, (k, angle)
    assert np.linalg.norm(origins[k, 2] - origins[k, 0]) > 0.05
    # curved: the direction of travel on the floor turns between successive steps
    steps = np.diff(origins[k][:, [0, 2]], axis=0)
    headings = np.unwrap(np.arctan2(steps[:, 1], steps[:, 0]))
    assert np.ptp(headings) > 0.2, k
  moved = scene.at(0.7)
  for part in moved.objects:
    extent = part.radius if isinstance(part, Sphere) else np.linalg.norm(part.half_size)
    assert part.center[1] - extent > 0.0  # above the floor at any orientation


def test_cameras_keep_clear_of_the_objects_and_vary_their_rig():
  scene, c2w, focal = kubric_ood.sample_scene(1, 24, 9)
  assert c2w.shape == (9, 24, 4, 4) and np.ptp(focal) > 0
  reach = np.array([kubric_ood.bounding_radius(p) for p in scene.parts])
  for frame in range(24):
    origins = scene.poses(frame / CONFIG.frame_rate)[1]
    gaps = np.linalg.norm(origins[:, None] - c2w[None, :, frame, :3, 3], axis=-1)
    assert (gaps > reach[:, None]).all()
  assert (c2w[..., 1, 3] > 0.2).all()
  distance = np.linalg.norm(c2w[:, 0, [0, 2], 3], axis=-1)
  assert distance.min() < 7.0 or distance.max() > 10.0  # outside the training ring's 7-10 m


@pytest.fixture(scope="module")
def written(tmp_path_factory):
  root = tmp_path_factory.mktemp("kubric_ood")
  directories = kubric_ood.generate_kubric_ood(root, 2, H, W, FRAMES, CAMERAS, config=CONFIG)
  return root, directories


def test_written_scenes_read_back_through_the_kubric_reader(written):
  root, directories = written
  assert [d.name for d in directories] == ["scene_000000", "scene_000001"]
  source = kubric.KubricSceneSource(root, ["ood_kubric"], num_cameras=CAMERAS)
  assert source.keys == ["scene_000000", "scene_000001"]
  record = source[1]
  assert (record["num_cameras"], record["num_frames"]) == (CAMERAS, FRAMES)
  expected = kubric_ood.render_kubric_ood_scene(1, H, W, FRAMES, CAMERAS, CONFIG)
  np.testing.assert_allclose(
    record["c2w"], expected["c2w"].reshape(-1, 4, 4), atol=1e-5
  )  # via Kubric's OpenGL quaternions
  np.testing.assert_allclose(record["intrinsics"][::FRAMES], expected["intrinsics"], rtol=1e-6)
  for camera, frame in ((0, 0), (1, FRAMES - 1)):
    at = camera * FRAMES + frame
    np.testing.assert_array_equal(record["images"][at], expected["images"][camera, frame])


def test_written_scenes_carry_each_composites_segmentation_and_poses(written):
  """The motion truth, as Kubric writes it: one instance per composite (all its parts), its pose
  (`OrbitScene.poses`) at every frame."""
  root, _ = written
  record = kubric.KubricSceneSource(root, ["ood_kubric"], num_cameras=CAMERAS)[1]
  scene, c2w, focal = kubric_ood.sample_scene(1, FRAMES, CAMERAS)
  owner = np.concatenate(
    [[0] * len(scene.backdrop)] + [[k + 1] * len(p) for k, p in enumerate(scene.parts)]
  )
  for frame in range(FRAMES):
    rotations, origins = scene.poses(frame / CONFIG.frame_rate)
    np.testing.assert_allclose(record["object_poses"][:, frame, :3, :3], rotations, atol=1e-6)
    np.testing.assert_allclose(record["object_poses"][:, frame, :3, 3], origins, atol=1e-6)
  for camera, frame in ((0, 1), (1, FRAMES - 1)):
    intrinsics = kubric.intrinsics_from_metadata(focal[camera], CONFIG.sensor_width, H, W)
    ids = render(scene.at(frame / CONFIG.frame_rate), c2w[camera, frame], intrinsics, H, W).ids
    expected = np.where(ids >= 0, owner[ids], 0)
    np.testing.assert_array_equal(record["segmentations"][camera * FRAMES + frame], expected)
  assert record["segmentations"][FRAMES].max() > 0  # an object in view


def test_stored_depth_is_the_ray_distance(written):
  root, _ = written
  record = kubric.KubricSceneSource(root, ["ood_kubric"], num_cameras=CAMERAS)[0]
  scene, c2w, focal = kubric_ood.sample_scene(0, FRAMES, CAMERAS)
  camera, frame = 1, 2
  intrinsics = kubric.intrinsics_from_metadata(focal[camera], CONFIG.sensor_width, H, W)
  z = render(scene.at(frame / CONFIG.frame_rate), c2w[camera, frame], intrinsics, H, W).depth
  stored = record["depths"][camera * FRAMES + frame]
  np.testing.assert_allclose(stored, kubric.z_to_ray_depth(z, intrinsics), rtol=1e-6)
  assert (stored > z + 1e-3)[:, [0, -1]].all()  # off-axis rays: distance exceeds z


def _tiny_experiment(tmp_path, **changes):
  from experiments import kubric as kubric_experiment
  from experiments.config import EvalSettings, SyntheticSettings

  preset = kubric_experiment.PRESETS["synthetic-tiny"]
  tiny = dataclasses.replace(
    preset,
    synthetic_dir=str(tmp_path / "data"),
    output_dir=str(tmp_path / "out"),
    model=preset.model.replace(image_size=(H, W), num_input_views=2),
    num_cameras=CAMERAS,
    min_gap=1,
    max_gap=2,
    synthetic=SyntheticSettings(num_train=1, num_test=1, frames=FRAMES, num_ood=2, workers=1),
    eval=dataclasses.replace(EvalSettings(), num_target_views=1),
  )
  return dataclasses.replace(tiny, **changes)


def test_the_kubric_experiment_scores_the_held_out_family(tmp_path):
  from experiments.kubric_data import OOD_SUBSET
  from experiments.kubric_task import KubricTask

  task, experiment = KubricTask(), _tiny_experiment(tmp_path)
  task.prepare(experiment)
  assert len(list((tmp_path / "data" / OOD_SUBSET).glob("scene_*/output_*.tar"))) == 2 * CAMERAS
  assert task.check_evaluation(experiment) is None
  sets = task.test_sets(experiment)
  assert list(sets) == ["test", "ood_kubric"]
  assert [key for key, _ in sets["ood_kubric"]] == ["scene_000000", "scene_000001"]
  for _, batch in sets["ood_kubric"]:
    for field in ("context_cameras", "target_cameras", "target_motion_masks", "target_times"):
      assert field in batch, field
    assert batch["target_images"].shape == (1, 1, H, W, 3)
  # frozen: the family's views do not follow the experiment's seed
  reseeded = task.test_sets(_tiny_experiment(tmp_path, seed=5))["ood_kubric"]
  for (_, batch), (_, again) in zip(sets["ood_kubric"], reseeded):
    np.testing.assert_array_equal(batch["target_cameras"], again["target_cameras"])
    np.testing.assert_array_equal(batch["target_images"], again["target_images"])
  no_ood = _tiny_experiment(
    tmp_path, synthetic=dataclasses.replace(experiment.synthetic, num_ood=0)
  )
  assert list(task.test_sets(no_ood)) == ["test"]


def test_composite_parts_move_rigidly_together():
  scene = kubric_ood.sample_scene(2, FRAMES, CAMERAS)[0]
  parts = scene.parts[0]
  for time in (0.0, 0.9):
    moved = scene.at(time).objects[: len(parts)]
    centres = np.stack([p.center for p in moved])
    local = np.stack([p.center for p in parts])
    # pairwise distances between a composite's parts are those of its own frame
    np.testing.assert_allclose(
      np.linalg.norm(centres[:, None] - centres[None], axis=-1),
      np.linalg.norm(local[:, None] - local[None], axis=-1),
      atol=1e-9,
    )
    assert all(isinstance(p, (Box, Sphere)) for p in moved)
    for part in moved[1:]:
      np.testing.assert_array_equal(part.rotation, moved[0].rotation)
