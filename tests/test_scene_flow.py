"""Scene flow against true object motion (`tokengs_jax.scene_flow`), on hand-made Gaussians: the
data-to-example similarity read off the cameras, the assignment of Gaussians to objects, the
relative end-point error (0 for perfect tracks, 1 for Gaussians that stay put) and the dynamic
coverage of objects' pixels; and the error figure of the Kubric evaluation."""

import numpy as np
import pytest
from PIL import Image

from experiments import figures
from tokengs_jax import scene_flow
from tokengs_jax.data.synthetic.scenes import axis_angle, random_rotation
from tokengs_jax.data.transforms import flip_horizontal, normalize_cameras


def _pose(rotation, translation) -> np.ndarray:
  pose = np.eye(4)
  pose[:3, :3], pose[:3, 3] = rotation, translation
  return pose


def _cameras(rng, count: int) -> np.ndarray:
  """[count, 4, 4] cameras a few metres around the origin, in random orientations."""
  return np.stack([_pose(random_rotation(rng), rng.normal(size=3) * 8.0) for _ in range(count)])


def _example_cameras(world: np.ndarray, num_context: int, scale: float) -> np.ndarray:
  """The example pipeline's camera transform: mean_cam normalisation, then the translations
  scaled (as `make_example` without a flip)."""
  model = normalize_cameras(world, num_context, "mean_cam").astype(np.float64)
  model[:, :3, 3] *= scale
  return model


def _sphere_points(centre, radius, count=400, seed=0) -> np.ndarray:
  directions = np.random.default_rng(seed).normal(size=(count, 3))
  return centre + radius * directions / np.linalg.norm(directions, axis=-1, keepdims=True)


# ----------------------------------------------------------------------------------------------
# The example's frame


def test_the_similarity_is_the_pipelines_camera_transform():
  rng = np.random.default_rng(0)
  world = _cameras(rng, 5)
  model = _example_cameras(world, 3, 0.37)
  similarity = scene_flow.example_similarity(world, model.astype(np.float32))
  # a point seen by a camera keeps its camera coordinates, scaled: the map the cameras went by
  points = rng.normal(size=(10, 3)) * 5.0
  for view in range(5):
    local = (points - world[view, :3, 3]) @ world[view, :3, :3]
    mapped = scene_flow.transform_points(similarity, points)
    np.testing.assert_allclose(
      (mapped - model[view, :3, 3]) @ model[view, :3, :3], 0.37 * local, atol=1e-5
    )
  np.testing.assert_allclose(np.linalg.det(similarity[:3, :3]), 0.37**3, rtol=1e-5)


def test_the_similarity_refuses_cameras_it_cannot_explain():
  rng = np.random.default_rng(1)
  world = _cameras(rng, 4)
  model = _example_cameras(world, 2, 0.5)
  _, mirrored, _ = flip_horizontal(np.zeros((4, 2, 2, 3)), model, np.ones((4, 4)))
  with pytest.raises(scene_flow.SimilarityError, match="not the data's under one similarity"):
    scene_flow.example_similarity(world, mirrored)
  moved = model.copy()
  moved[1, :3, 3] += 0.1  # one camera off the map
  with pytest.raises(scene_flow.SimilarityError, match="not the data's under one similarity"):
    scene_flow.example_similarity(world, moved)
  with pytest.raises(scene_flow.SimilarityError, match="coincide"):
    scene_flow.example_similarity(np.stack([world[0]] * 3), np.stack([model[0]] * 3))


def test_motions_in_the_example_frame_move_mapped_points_as_the_world_motion_moves_them():
  rng = np.random.default_rng(2)
  similarity = _pose(random_rotation(rng), rng.normal(size=3))
  similarity[:3, :3] *= 0.2
  motion = _pose(axis_angle(np.array([0.0, 1.0, 0.0]), 0.7), [1.0, 0.0, -2.0])
  points = rng.normal(size=(20, 3))
  in_frame = scene_flow.motions_in_frame(similarity, motion[None])[0]
  np.testing.assert_allclose(
    scene_flow.transform_points(in_frame, scene_flow.transform_points(similarity, points)),
    scene_flow.transform_points(similarity, scene_flow.transform_points(motion, points)),
    atol=1e-12,
  )
  np.testing.assert_allclose(in_frame[:3, :3] @ in_frame[:3, :3].T, np.eye(3), atol=1e-12)


# ----------------------------------------------------------------------------------------------
# Gaussians on objects, and their flow


def test_points_go_to_the_object_whose_surface_they_sit_on():
  surfaces = np.stack(
    [_sphere_points(np.zeros(3), 1.0), _sphere_points(np.array([5.0, 0, 0]), 0.5, seed=1)]
  )
  unseen = np.full((1, 400, 3), np.nan)
  points = np.array(
    [
      [0.0, 0.0, 1.05],  # on the first sphere
      [5.0, 0.55, 0.0],  # on the second, within a quarter of its radius
      [5.0, 0.8, 0.0],  # 0.3 off the second (radius 0.5): on none
      [2.5, 0.0, 0.0],  # between them: on none
    ]
  )
  assignment = scene_flow.assign_to_objects(points, np.concatenate([surfaces, unseen]))
  np.testing.assert_array_equal(assignment, [0, 1, -1, -1])
  np.testing.assert_array_equal(
    scene_flow.assign_to_objects(points, surfaces, relative_distance=1.0), [0, 1, 1, -1]
  )
  np.testing.assert_array_equal(scene_flow.assign_to_objects(points, unseen), [-1] * 4)


def test_perfect_tracks_score_zero_and_gaussians_that_stay_put_score_one():
  rng = np.random.default_rng(3)
  motions = np.stack(
    [
      _pose(axis_angle(np.array([0.3, 1.0, 0.0]) / np.linalg.norm([0.3, 1, 0]), 0.9), [1, 0, 0]),
      _pose(np.eye(3), [0.0, 0.0, 0.5]),
      np.eye(4),  # an object that does not move
      _pose(np.eye(3), [1.0, 0.0, 0.0]),  # no Gaussian on it
    ]
  )
  start = rng.normal(size=(30, 3))
  assignment = np.repeat([0, 1, 2], 10)
  tracked = np.stack(
    [scene_flow.transform_points(motions[k], x) for k, x in zip(assignment, start)]
  )

  perfect = scene_flow.object_flow(start, tracked, motions, assignment)
  np.testing.assert_array_equal(perfect.gaussians, [10, 10, 10, 0])
  np.testing.assert_allclose(perfect.relative_epe[:2], 0.0, atol=1e-12)
  np.testing.assert_allclose(perfect.median_displacement[1], 0.5)
  assert np.isnan(perfect.relative_epe[2:]).all()  # did not move; nothing on it

  static = scene_flow.object_flow(start, start, motions, assignment)
  np.testing.assert_allclose(static.relative_epe[:2], 1.0)
  np.testing.assert_allclose(static.median_predicted[:2], 0.0)

  halfway = scene_flow.object_flow(start, (start + tracked) / 2, motions, assignment)
  np.testing.assert_allclose(halfway.relative_epe[:2], 0.5)
  backwards = scene_flow.object_flow(start, 2 * start - tracked, motions, assignment)
  np.testing.assert_allclose(backwards.relative_epe[:2], 2.0)  # worse than staying put
  # unassigned Gaussians count for no object
  none = scene_flow.object_flow(start, start, motions, np.full(30, -1))
  assert (none.gaussians == 0).all() and np.isnan(none.median_epe).all()


def test_dynamic_coverage_counts_the_pixels_the_dynamic_gaussians_carry():
  full = np.ones((2, 2, 3))
  dynamic = np.array([[[1.0, 0.5, 0.4], [0.0, 0.9, 0.0]], [[0.0, 0.0, 0.0], [0.6, 0.6, 0.6]]])
  full[1, 0] = 0.0  # nothing rendered there: not covered, whatever the ratio
  masks = np.zeros((2, 2, 2, 3), bool)
  masks[0, 0, 0] = True  # object 0, view 0, top row: 1.0, 0.5, 0.4 -> 2 of 3
  masks[1, 0, 0, :2] = True  # object 0, view 1, empty pixels: 0 of 2
  masks[:, 1, 1] = True  # object 1, bottom rows: 0.0, 0.9, 0.0 and 0.6 x 3 -> 4 of 6
  covered, pixels = scene_flow.dynamic_coverage(full, dynamic, masks)
  np.testing.assert_array_equal(covered, [2, 4])
  np.testing.assert_array_equal(pixels, [5, 6])


def _truth_batch(rng, world_motions, world_surfaces):
  """A batch of one carrying the scene-flow truth in a world unlike the example's frame; in both
  4x4 target views, object 0 fills the top half, object 1 the bottom left, the background the
  bottom right."""
  world = _cameras(rng, 4)
  model = _example_cameras(world, 2, 0.25)
  masks = np.zeros((1, 2, 2, 4, 4), bool)
  masks[:, :, 0, :2] = masks[:, :, 1, 2:, :2] = True
  return {
    "context_c2w": model[None, :2].astype(np.float32),
    "target_c2w": model[None, 2:].astype(np.float32),
    "world_c2w": world[None],
    "object_motions": world_motions[None],
    "object_points": world_surfaces[None],
    "target_object_masks": masks,
  }, scene_flow.example_similarity(world, model)


def test_a_scene_scores_gaussians_in_the_example_frame_against_the_world_truth():
  rng = np.random.default_rng(4)
  world_motions = np.stack(
    [_pose(axis_angle(np.array([0.0, 0.0, 1.0]), 0.5), [0.8, 0.0, 0.0]), np.eye(4)]
  )
  world_surfaces = np.stack(
    [_sphere_points(np.zeros(3), 0.6), _sphere_points(np.array([4.0, 0.0, 0.0]), 0.6, seed=1)]
  )
  batch, similarity = _truth_batch(rng, world_motions, world_surfaces)
  # Gaussians on both objects, made in the world, seen in the example's frame
  on_objects = world_surfaces[:, ::10].reshape(-1, 3)  # 40 + 40
  moved = np.concatenate(
    [scene_flow.transform_points(m, s[::10]) for m, s in zip(world_motions, world_surfaces)]
  )
  far = scene_flow.transform_points(similarity, np.array([[0.0, 9.0, 0.0]]))  # on no object
  start = np.concatenate([scene_flow.transform_points(similarity, on_objects), far])
  end = np.concatenate([scene_flow.transform_points(similarity, moved), far])
  opacities = np.ones(len(start))
  opacities[:40:2] = 0.01  # faint Gaussians are not scored
  full = np.ones((2, 4, 4))
  dynamic = np.zeros((2, 4, 4))
  dynamic[:, :2] = 1.0  # the dynamic Gaussians draw exactly the moving object: a clean split
  scene = scene_flow.score_scene(batch, start, end, opacities, full, dynamic)
  scores = scene["objects"]
  assert [s["moving"] for s in scores] == [True, False]
  assert [s["gaussians"] for s in scores] == [20, 40]
  assert (scene["dynamic_gaussians"], scene["on_objects"]) == (61, 60)
  assert scores[0]["relative_epe"] == pytest.approx(0.0, abs=1e-9)
  assert scores[1]["relative_epe"] is None  # it did not move
  assert [s["dynamic_coverage"] for s in scores] == [1.0, 0.0]
  assert [s["pixels"] for s in scores] == [16, 8]
  assert scene["background"] == {"pixels": 8, "covered": 0}
  # the same Gaussians left where they were, and drawing everything: relative error 1 on the
  # moving object, the background and the static object covered too
  static = scene_flow.score_scene(batch, start, start, opacities, full, full)
  assert static["objects"][0]["relative_epe"] == pytest.approx(1.0)
  summary = scene_flow.summarise([scene, static])
  assert summary == {
    "objects": 4,
    "moving_objects": 2,
    "moving_objects_with_gaussians": 2,
    "median_relative_epe": pytest.approx(0.5),
    "median_dynamic_coverage": 1.0,
    "median_dynamic_coverage_static": 0.5,
    "dynamic_coverage_background": 0.5,
    "dynamic_gaussians_on_objects": pytest.approx(120 / 122),
  }
  # the displacement is in the example's units: the world's 0.25 times (mean_cam keeps lengths)
  scored = on_objects[:40][1::2]
  world_displacement = np.median(
    np.linalg.norm(scene_flow.transform_points(world_motions[0], scored) - scored, axis=-1)
  )
  assert scores[0]["median_displacement"] == pytest.approx(0.25 * world_displacement)


def test_the_error_figure_draws_each_object_and_the_stay_put_line(tmp_path):
  path = figures.scatter_plot(
    tmp_path / "error.png",
    {"moving objects": ([0.1, 0.2, float("nan")], [0.05, 0.3, 1.0])},
    title="t",
    xlabel="true displacement",
    ylabel="end-point error",
    diagonal="Gaussians that stay put",
  )
  image = np.asarray(Image.open(path).convert("RGB"))
  for color in (figures.PALETTE[0], (127, 127, 127)):
    assert np.all(image == np.array(color, np.uint8), axis=-1).sum() > 20, color
  # a marker per finite point and no line between them: two blobs of the series' colour
  blue = np.all(image == np.array(figures.PALETTE[0], np.uint8), axis=-1)
  blue[:, -170:] = False  # the legend
  rows = np.flatnonzero(blue.any(axis=1))
  assert np.ptp(rows) > 20 and blue.sum() < 2 * 60
