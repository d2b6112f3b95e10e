"""Kubric evaluation (issue 24 items 1 and 4): novel views at novel times. The (camera, frame)
index and its validation, the default protocol (no target is an input view, targets at in-between
times), the moving-pixel masks (from the generator's truth, else the image rule), the scene-flow
truth carried into the example's frame, and the batches `experiments.kubric` scores."""

import dataclasses
import io
import json
import tarfile

import numpy as np
import pytest
from PIL import Image

from experiments import cli
from experiments import kubric as kubric_experiment
from experiments import results
from experiments.kubric_task import KubricExperiment, KubricTask
from experiments.config import SyntheticSettings
from experiments.tasks import execute
from tokengs_jax import evaluation, metrics, scene_flow
from tokengs_jax.data import (
  DATASET_PRESETS,
  EvaluationIndexError,
  NotEnoughFramesError,
  kubric,
  make_example,
)
from tokengs_jax.data.synthetic import kubric_ood
from tokengs_jax.data.synthetic.raytrace import Box
from tokengs_jax.data.transforms import resize_and_center_crop_mask

H = W = 16
CAMERAS, FRAMES = 3, 6


def _experiment(root, **changes) -> KubricExperiment:
  """The tiny preset with 2 input views on 2 generated held-out scenes of 3 cameras x 6 frames at
  16x16."""
  tiny = kubric_experiment.PRESETS["synthetic-tiny"]
  return dataclasses.replace(
    tiny,
    synthetic_dir=str(root),
    output_dir=str(root / "results"),
    num_cameras=CAMERAS,
    max_gap=4,
    synthetic=SyntheticSettings(num_train=1, num_test=2, frames=FRAMES, num_ood=0, workers=1),
    model=tiny.model.replace(image_size=(H, W), num_input_views=2),  # the protocol at 2 views
    **changes,
  )


@pytest.fixture(scope="module")
def data_root(tmp_path_factory):
  root = tmp_path_factory.mktemp("kubric_eval")
  KubricTask().prepare(_experiment(root))
  return root


def _write_index(path, entries) -> str:
  path.write_text(json.dumps(entries))
  return str(path)


# ----------------------------------------------------------------------------------------------
# The default protocol


@pytest.mark.parametrize(
  "cameras, frames, context, targets, max_gap",
  [(3, 6, 2, 2, 4), (4, 12, 2, 2, 8), (9, 24, 4, 4, 23), (9, 24, 4, 8, 10), (2, 8, 3, 3, 7)],
)
def test_default_views_are_novel_views_at_in_between_times(
  cameras, frames, context, targets, max_gap
):
  for seed in range(10):
    views = kubric.default_evaluation_views(
      cameras, frames, context, targets, max_gap, np.random.default_rng(seed)
    )
    again = kubric.default_evaluation_views(
      cameras, frames, context, targets, max_gap, np.random.default_rng(seed)
    )
    np.testing.assert_array_equal(views[0], again[0])
    np.testing.assert_array_equal(views[1], again[1])
    inputs, novel = views
    assert inputs.shape == (context, 2) and novel.shape == (targets, 2)
    assert (inputs[:, 0] < cameras).all() and (novel[:, 0] < cameras).all()
    assert (inputs[:, 1] < frames).all() and (novel[:, 1] < frames).all()
    assert not {tuple(p) for p in novel.tolist()} & {tuple(p) for p in inputs.tolist()}
    first, last = inputs[:, 1].min(), inputs[:, 1].max()
    assert last - first == min(max_gap, frames - 1)
    # every target time lies strictly between input times and is none of them
    assert ((novel[:, 1] > first) & (novel[:, 1] < last)).all()
    assert not set(novel[:, 1].tolist()) & set(inputs[:, 1].tolist())
    if cameras >= context:
      assert len(set(inputs[:, 0].tolist())) == context
    # new viewpoints and input viewpoints are both scored at the new times
    used = set(inputs[:, 0].tolist())
    assert any(c in used for c in novel[:, 0].tolist())
    assert any(c not in used for c in novel[:, 0].tolist()) == (cameras > len(used))


def test_default_views_from_fewer_cameras_see_each_at_several_times():
  """`context_cameras=2`: the inputs alternate between two cameras over increasing frames; the
  targets still take new times, half of them from the two cameras no input uses."""
  for seed in range(5):
    inputs, novel = kubric.default_evaluation_views(
      4, 12, 4, 2, 8, np.random.default_rng(seed), context_cameras=2
    )
    a, b = inputs[:2, 0]
    assert a != b and inputs[:, 0].tolist() == [a, b, a, b]
    assert (np.diff(inputs[:, 1]) > 0).all()
    assert not set(novel[:, 1].tolist()) & set(inputs[:, 1].tolist())
    assert novel[0, 0] not in (a, b) and novel[1, 0] in (a, b)
    # 0 is the official draw: the same views as before the option existed
    official = kubric.default_evaluation_views(4, 12, 4, 2, 8, np.random.default_rng(seed))
    assert len(set(official[0][:, 0].tolist())) == 4


def test_default_views_need_an_in_between_frame():
  with pytest.raises(NotEnoughFramesError, match="no in-between frame"):
    kubric.default_evaluation_views(9, 24, 4, 2, 3, np.random.default_rng(0))
  with pytest.raises(NotEnoughFramesError, match="no in-between frame"):
    kubric.default_evaluation_views(9, 24, 1, 2, 10, np.random.default_rng(0))


def _pairs(batch, side: str) -> set[tuple[int, float]]:
  cameras, times = batch[f"{side}_cameras"][0], batch[f"{side}_times"][0]
  return {(int(c), float(t)) for c, t in zip(cameras, times)}


def test_experiment_batches_never_score_an_input_view(data_root):
  experiment = _experiment(data_root)
  task = KubricTask()
  assert task.check_evaluation(experiment) is None
  examples = task.evaluation_scenes(experiment)
  assert [key for key, _ in examples] == ["scene_000000", "scene_000001"]
  for _, batch in examples:
    vt = batch["target_images"].shape[1]
    assert batch["target_cameras"].shape == (1, vt) and batch["context_cameras"].shape == (1, 2)
    assert batch["target_motion_masks"].shape == (1, vt, H, W)
    assert batch["target_motion_masks"].dtype == bool
    # (camera, time) identifies a view: no target is an input
    assert not _pairs(batch, "target") & _pairs(batch, "context")
    context_times = batch["context_times"][0]
    inside = (batch["target_times"][0] > context_times.min()) & (
      batch["target_times"][0] < context_times.max()
    )
    assert inside.any() and not set(batch["target_times"][0]) & set(context_times)
    assert set(batch["target_cameras"][0]) - set(batch["context_cameras"][0])  # a new viewpoint
    assert batch["target_motion_masks"].any()  # the synthetic objects move


# ----------------------------------------------------------------------------------------------
# Foreground masks (the PNG alpha): the official masked metrics


def _copy_scene(data_root, root, rewrite) -> kubric.KubricSceneSource:
  """Scene 0 of `data_root`'s test split copied to `root/v0`, each tar member's bytes passed
  through `rewrite(name, data)` (None leaves the member out).  -> the copy's source."""
  scene = root / "v0" / "scene_000000"
  scene.mkdir(parents=True)
  for camera in range(CAMERAS):
    name = f"output_{camera:03d}.tar"
    with (
      tarfile.open(data_root / "test" / "scene_000000" / name) as source,
      tarfile.open(scene / name, "w") as copy,
    ):
      for member in source.getmembers():
        data = rewrite(member.name, source.extractfile(member).read())
        if data is not None:
          member.size = len(data)
          copy.addfile(member, io.BytesIO(data))
  return kubric.KubricSceneSource(root, ["v0"], num_cameras=CAMERAS)


def _copy_with_alpha(data_root, root, alpha: np.ndarray) -> kubric.KubricSceneSource:
  """`_copy_scene` with `alpha` (uint8 [H, W]) as the alpha channel of every `rgba_*.png`."""

  def with_alpha(name: str, data: bytes) -> bytes:
    if "rgba_" not in name:
      return data
    rgba = np.array(Image.open(io.BytesIO(data)).convert("RGBA"))
    rgba[..., 3] = alpha
    png = io.BytesIO()
    Image.fromarray(rgba, "RGBA").save(png, format="PNG")
    return png.getvalue()

  return _copy_scene(data_root, root, with_alpha)


def test_evaluation_batches_carry_the_alpha_and_score_the_foreground(data_root, tmp_path):
  alpha = np.zeros((H, W), np.uint8)
  alpha[3:12, 2:9] = 255
  alpha[3:12, 9] = 100  # an antialiased edge: a soft weight
  source = _copy_with_alpha(data_root, tmp_path, alpha)
  experiment = _experiment(data_root)
  chosen = KubricTask._default_views(experiment, source, 0, experiment.seed)
  scenes = KubricTask._evaluation_scenes(experiment, source, chosen, experiment.seed)
  ((_, batch),) = scenes
  vt = batch["target_images"].shape[1]
  assert batch["target_masks"].shape == (1, vt, H, W)
  for view in range(vt):  # the data's own size: no resize, no flip in evaluation
    np.testing.assert_allclose(batch["target_masks"][0, view], alpha / 255.0, atol=1e-6)
  methods = evaluation.baselines(dynamic=True)
  scored = evaluation.evaluate(scenes, methods, evaluation.Scorer(lpips=False))
  assert scored.notes == {}
  for name, scores in scored.scores.items():
    prediction = np.clip(methods[name].images(batch)[0], 0.0, 1.0)
    expected = metrics.masked_psnr(prediction, batch["target_images"][0], alpha / 255.0)
    np.testing.assert_allclose(scores.per_view[0]["psnr_masked"], expected, rtol=1e-5)
    assert {"psnr_masked", "ssim_masked"} <= set(scores.summary())


def test_opaque_kubric_data_omits_the_masked_metrics_and_says_so(data_root, tmp_path):
  """The synthetic generator writes opaque RGBA: every mask is 1, so no masked column, and
  metrics.json / metrics.md say why."""
  experiment = _experiment(data_root)
  scenes = KubricTask().evaluation_scenes(experiment)
  assert all(np.all(batch["target_masks"] == 1.0) for _, batch in scenes)
  scored = evaluation.evaluate(
    scenes, {"nearest_view": evaluation.baselines()["nearest_view"]}, evaluation.Scorer(False)
  )
  assert "psnr_masked" not in scored.scores["nearest_view"].summary()
  payload = results.write_metrics(tmp_path, {"test": scored}, {"title": "t"})
  assert payload["notes"] == {"masked metrics": evaluation.OPAQUE_MASKS_NOTE}
  assert json.loads((tmp_path / "metrics.json").read_text())["notes"] == payload["notes"]
  assert f"- masked metrics: {evaluation.OPAQUE_MASKS_NOTE}" in results.summary_text(
    {"test": scored}
  )


# ----------------------------------------------------------------------------------------------
# The index


def test_index_views_are_read_as_camera_and_frame(data_root, tmp_path):
  """Bullet time: the inputs are at different times; each view is the tar's own frame."""
  entries = {
    "scene_000001": {"context": [[0, 1], [2, 4]], "target": [[1, 2], [0, 4], [2, 1]]},
    "scene_404": {"context": [[0, 0], [1, 1]], "target": [[2, 2]]},
    "scene_000000": None,  # left out by the benchmark
  }
  experiment = _experiment(data_root, eval_index=_write_index(tmp_path / "index.json", entries))
  task = KubricTask()
  assert task.check_evaluation(experiment) == {
    "requested": 2,
    "evaluated": 1,
    "missing": ["scene_404"],
  }
  [(key, batch)] = task.evaluation_scenes(experiment)
  assert key == "scene_000001"
  scene = data_root / "test" / key
  for side, pairs in (("context", [[0, 1], [2, 4]]), ("target", [[1, 2], [0, 4], [2, 1]])):
    np.testing.assert_array_equal(batch[f"{side}_cameras"][0], [c for c, _ in pairs])
    for view, (camera, frame) in enumerate(pairs):
      raw = kubric.read_kubric_view(scene / f"output_{camera:03d}.tar", [frame])["images"][0]
      np.testing.assert_allclose(batch[f"{side}_images"][0, view], raw / 255.0, atol=1e-6)
  np.testing.assert_allclose(batch["context_times"][0], [0.0, 1.0])
  np.testing.assert_allclose(batch["target_times"][0], [1 / 3, 1.0, 0.0])
  # a target at an input time: nothing moved since then, no pixel to score
  assert not batch["target_motion_masks"][0, 1:].any()


def test_the_cli_takes_an_index_and_a_bad_one_fails_before_any_work(data_root, tmp_path):
  path = _write_index(tmp_path / "bad.json", {"scene_000000": {"context": [[0, 0]], "target": []}})
  _, parsed = cli.parse(
    ["eval", "--eval-index", path], kubric_experiment.PRESETS, "synthetic-tiny", "prog"
  )
  assert parsed.eval_index == path
  experiment = _experiment(data_root, eval_index=path)
  with pytest.raises(EvaluationIndexError, match="scene_000000' 'target'"):
    execute("run", experiment, KubricTask())
  assert not (data_root / "results" / "params.msgpack").exists()  # nothing was trained


@pytest.mark.parametrize(
  "entries, message",
  [
    ({"scene_999": {"context": [[0, 0], [1, 1]], "target": [[2, 2]]}}, "none of its 1 scenes"),
    (
      {"scene_000000": {"context": [[0, 0], [3, 1]], "target": [[2, 2]]}},
      r"scene 'scene_000000' context entry 1 \[camera 3, frame 1\]: the scene has cameras 0-2",
    ),
    (
      {"scene_000001": {"context": [[0, 0], [1, 1]], "target": [[2, 2], [1, 6]]}},
      r"scene 'scene_000001' target entry 1 \[camera 1, frame 6\].*frames 0-5",
    ),
    (
      {"scene_000000": {"context": [[0, 0], [1, 1], [2, 2]], "target": [[2, 3]]}},
      "3 context views, the model takes 2",
    ),
  ],
)
def test_index_entries_outside_the_data_are_errors(data_root, tmp_path, entries, message):
  experiment = _experiment(data_root, eval_index=_write_index(tmp_path / "index.json", entries))
  with pytest.raises(EvaluationIndexError, match=message):
    KubricTask().check_evaluation(experiment)


@pytest.mark.parametrize(
  "raw, message",
  [
    ([], "maps scene keys"),
    ({"s": [[0, 0]]}, "scene 's': needs exactly 'context' and 'target'"),
    ({"s": {"context": [[0, 0]]}}, r"needs exactly 'context' and 'target'.*\['context'\]"),
    ({"s": {"context": [[0, 0]], "targets": [[0, 1]]}}, "'targets'"),
    ({"s": {"context": [], "target": [[0, 1]]}}, "scene 's' 'context': needs a non-empty list"),
    ({"s": {"context": [[0, 0]], "target": [[0]]}}, "'target' entry 0: expected"),
    ({"s": {"context": [[0, 0], [1, "a"]], "target": [[0, 1]]}}, "'context' entry 1"),
    ({"s": {"context": [[0, 0]], "target": [[0, 1], [True, 2]]}}, "'target' entry 1"),
    ({"s": {"context": [[0, -1]], "target": [[0, 1]]}}, "non-negative integers, got \\[0, -1\\]"),
    ({"s": {"context": [[0, 1.0]], "target": [[0, 1]]}}, "'context' entry 0"),
  ],
)
def test_malformed_index_entries_are_rejected_with_a_clear_message(tmp_path, raw, message):
  path = _write_index(tmp_path / "index.json", raw)
  with pytest.raises(EvaluationIndexError, match=message):
    kubric.load_kubric_evaluation_index(path)


def test_null_entries_are_left_out_and_broken_json_is_named(tmp_path):
  path = _write_index(
    tmp_path / "index.json", {"a": None, "b": {"context": [[1, 2]], "target": [[0, 3]]}}
  )
  index = kubric.load_kubric_evaluation_index(path)
  assert list(index) == ["b"]
  np.testing.assert_array_equal(index["b"][0], [[1, 2]])
  (tmp_path / "broken.json").write_text("{")
  with pytest.raises(EvaluationIndexError, match="broken.json: not JSON"):
    kubric.load_kubric_evaluation_index(tmp_path / "broken.json")


# ----------------------------------------------------------------------------------------------
# Moving pixels


def _plane_view(camera_x: float, patch: bool):
  """A 16x16 view (fx = fy = 16, centred) of a plane at z = 4 whose red channel ramps with world x
  (12.5 levels a pixel), from a camera at (camera_x, 0, 0) looking down +z; the top row sees
  nothing (a constant sky). `patch`: a green square object at depth 3 over rows/cols 5-9.
  -> (uint8 image [H, W, 3], ray depth [H, W], c2w [4, 4])."""
  intrinsics = np.array([16.0, 16.0, 8.0, 8.0])
  cols = np.arange(W) + 0.5
  world_x = camera_x + (cols - 8.0) / 16.0 * 4.0
  image = np.zeros((H, W, 3))
  image[:, :, 0] = 128 + 50 * world_x
  image[:, :, 1] = 100
  image[0] = [20, 30, 200]
  z = np.full((H, W), 4.0)
  z[0] = 0.0
  if patch:
    image[5:10, 5:10] = [40, 250, 40]
    z[5:10, 5:10] = 3.0
  c2w = np.eye(4)
  c2w[0, 3] = camera_x
  return np.round(image).astype(np.uint8), kubric.z_to_ray_depth(z, intrinsics), c2w, intrinsics


def test_motion_mask_marks_what_moved_not_what_the_camera_did():
  target, depth, target_c2w, intrinsics = _plane_view(0.0, patch=True)
  reference, _, reference_c2w, _ = _plane_view(0.5, patch=False)  # the camera moved 2 pixels
  moved = np.zeros((H, W), bool)
  moved[5:10, 5:10] = True
  mask = kubric.motion_mask(target, reference, depth, target_c2w, reference_c2w, intrinsics)
  np.testing.assert_array_equal(mask, moved)
  # the plain per-pixel rule would call the whole shifted ramp moving
  plain = kubric.motion_mask(target, reference, None, target_c2w, reference_c2w, intrinsics)
  assert plain.mean() > 0.8
  # a camera that did not move: with or without depth, exactly the object
  still, _, _, _ = _plane_view(0.0, patch=False)
  for known in (depth, None):
    np.testing.assert_array_equal(
      kubric.motion_mask(target, still, known, target_c2w, target_c2w, intrinsics), moved
    )
  # a change below the threshold is no motion
  dimmer = (target.astype(int) - 3).clip(0).astype(np.uint8)
  assert not kubric.motion_mask(target, dimmer, depth, target_c2w, target_c2w, intrinsics).any()


def test_motion_masks_follow_the_images_resize_and_crop():
  masks = np.zeros((1, 4, 4), bool)
  masks[0, :, :2] = True
  np.testing.assert_array_equal(resize_and_center_crop_mask(masks, (2, 2)), [[[1, 0], [1, 0]]])
  np.testing.assert_array_equal(resize_and_center_crop_mask(masks, (4, 4)), masks)
  wide = np.zeros((1, 2, 4), bool)
  wide[0, :, 2:] = True
  np.testing.assert_array_equal(resize_and_center_crop_mask(wide, (2, 2)), [[[0, 1], [0, 1]]])


def _copy_without(data_root, root, dropped: tuple[str, ...]) -> dict:
  """`_copy_scene` without the tar members whose names hold any of `dropped`.  -> its record."""

  def keep(name: str, data: bytes) -> bytes | None:
    return None if any(word in name for word in dropped) else data

  return _copy_scene(data_root, root, keep)[0]


def test_a_tar_without_depth_or_segmentation_compares_the_same_pixel(data_root, tmp_path):
  """The fallback for data without motion truth: the image rule."""
  record = _copy_without(data_root, tmp_path, ("depth", "segmentation"))
  views = (np.array([[0, 0], [1, 4]]), np.array([[2, 3], [0, 1]]))
  fields = kubric.evaluation_fields(record, views, (H, W))
  np.testing.assert_array_equal(fields["context_cameras"], [0, 1])
  np.testing.assert_array_equal(fields["target_cameras"], [2, 0])
  assert "object_motions" not in fields  # no scene-flow truth either
  for view, (camera, frame, reference) in enumerate([(2, 3, 4), (0, 1, 0)]):
    at, before = camera * FRAMES + frame, camera * FRAMES + reference
    expected = kubric.motion_mask(
      record["images"][at],
      record["images"][before],
      None,
      record["c2w"][at],
      record["c2w"][before],
      record["intrinsics"][at],
    )
    np.testing.assert_array_equal(fields["target_motion_masks"][view], expected)


# ----------------------------------------------------------------------------------------------
# Motion truth


def test_truth_masks_mark_where_moved_objects_are_now_or_were():
  poses = np.tile(np.eye(4), (3, 1, 1))
  later = poses.copy()
  later[1, 0, 3] = 0.5  # object 1 slides
  later[2, :3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]  # object 2 turns
  later[0, 1, 3] = 1e-8  # object 0: float noise is no motion
  moved = kubric.moved_objects(later, poses)
  np.testing.assert_array_equal(moved, [False, True, True])
  now, then = np.zeros((4, 4), int), np.zeros((4, 4), int)
  now[0, :2], then[3, 2:] = 2, 2  # object 1 left the bottom right for the top left
  now[1, 0] = then[1, 0] = 3  # object 2 turns in place
  now[2] = then[2] = 1  # object 0 stays
  expected = np.zeros((4, 4), bool)
  expected[0, :2] = expected[3, 2:] = expected[1, 0] = True
  np.testing.assert_array_equal(kubric.truth_motion_mask(now, then, moved), expected)
  assert not kubric.truth_motion_mask(now, then, np.zeros(3, bool)).any()


TRUTH_SIZE = 24


@pytest.fixture(scope="module")
def ood_record(tmp_path_factory):
  """Scene 0 of the held-out family (composites that tumble) at 24x24, 3 cameras x 6 frames."""
  root = tmp_path_factory.mktemp("kubric_truth")
  config = kubric_ood.KubricOodConfig(supersample=1)
  kubric_ood.generate_kubric_ood(root, 1, TRUTH_SIZE, TRUTH_SIZE, FRAMES, CAMERAS, config=config)
  return kubric.KubricSceneSource(root, ["ood_kubric"], num_cameras=CAMERAS)[0]


TRUTH_VIEWS = (np.array([[0, 1], [1, 5]]), np.array([[2, 3], [0, 4]]))  # frames 1-5, refs 1 and 5


def test_motion_masks_come_from_the_truth_where_the_scene_has_it(ood_record):
  fields = kubric.evaluation_fields(ood_record, TRUTH_VIEWS, (TRUTH_SIZE, TRUTH_SIZE))
  poses, segmentations = ood_record["object_poses"], ood_record["segmentations"]
  for view, (camera, frame, reference) in enumerate([(2, 3, 1), (0, 4, 5)]):
    moved = kubric.moved_objects(poses[:, frame], poses[:, reference])
    assert moved.all()  # every composite of the family moves
    now, then = segmentations[camera * FRAMES + frame], segmentations[camera * FRAMES + reference]
    np.testing.assert_array_equal(fields["target_motion_masks"][view], (now > 0) | (then > 0))
    for k in range(len(poses)):
      np.testing.assert_array_equal(fields["target_object_masks"][view, k], now == k + 1)


def _gap(parts, points: np.ndarray) -> np.ndarray:
  """Distance [N] of points [N, 3] to the nearest surface of a composite's posed parts."""
  gaps = []
  for part in parts:
    local = (points - part.center) @ part.rotation
    if isinstance(part, Box):
      gaps.append(np.abs(np.max(np.abs(local) - part.half_size, axis=-1)))
    else:
      gaps.append(np.abs(np.linalg.norm(local, axis=-1) - part.radius))
  return np.min(gaps, axis=0)


def test_flow_truth_points_ride_the_objects_from_the_first_frame_to_the_last(ood_record):
  fields = kubric.evaluation_fields(ood_record, TRUTH_VIEWS, (TRUTH_SIZE, TRUTH_SIZE))
  np.testing.assert_array_equal(
    fields["world_c2w"], ood_record["c2w"][[0 * FRAMES + 1, 1 * FRAMES + 5, 2 * FRAMES + 3, 4]]
  )
  scene = kubric_ood.sample_scene(0, FRAMES, CAMERAS)[0]
  frame_rate = kubric_ood.KubricOodConfig().frame_rate
  first, last = scene.at(1 / frame_rate).objects, scene.at(5 / frame_rate).objects
  start = 0
  for k, parts in enumerate(scene.parts):
    points = fields["object_points"][k]
    assert points.shape == (kubric.OBJECT_POINTS, 3) and np.isfinite(points).all()
    mine = slice(start, start + len(parts))
    start += len(parts)
    assert _gap(first[mine], points).max() < 1e-3
    motion = fields["object_motions"][k]
    assert _gap(last[mine], points @ motion[:3, :3].T + motion[:3, 3]).max() < 1e-3


def test_the_truth_goes_into_the_example_frame_as_the_cameras_do(ood_record):
  config = dataclasses.replace(
    DATASET_PRESETS["kubric"], image_shape=(TRUTH_SIZE, TRUTH_SIZE), random_flip=False
  )
  example = make_example(
    ood_record, config, np.random.default_rng(0), views=kubric.flat_views(ood_record, TRUTH_VIEWS)
  )
  fields = kubric.evaluation_fields(ood_record, TRUTH_VIEWS, (TRUTH_SIZE, TRUTH_SIZE))
  model_c2w = np.concatenate([example["context_c2w"], example["target_c2w"]])
  similarity = scene_flow.example_similarity(fields["world_c2w"], model_c2w)
  # the scale is the pipeline's own: the pointmap of the inputs' depth maps, carried into the
  # example's frame, has mean distance `translation_scale` (1) from its origin
  context = kubric.flat_views(ood_record, TRUTH_VIEWS)[0]
  depths = np.stack([ood_record["depths"][i] for i in context])
  carried = similarity @ fields["world_c2w"][:2]
  intrinsics = ood_record["intrinsics"][context]
  assert kubric.pointmap_scale(depths, carried, intrinsics) == pytest.approx(1.0, rel=1e-5)
  # a point moved by an object's motion is seen at the same pixel in the example's target
  # camera (its motion carried into the example's frame) as in the data's
  motions = scene_flow.motions_in_frame(similarity, fields["object_motions"])
  for view in range(2):
    world_camera, (fx, fy, cx, cy) = (
      fields["world_c2w"][2 + view],
      example["target_intrinsics"][view],
    )
    for k, points in enumerate(fields["object_points"]):
      moved = scene_flow.transform_points(fields["object_motions"][k], points)
      in_frame = scene_flow.transform_points(
        motions[k], scene_flow.transform_points(similarity, points)
      )
      pixels = []
      for c2w, xyz in ((world_camera, moved), (example["target_c2w"][view], in_frame)):
        local = (xyz - c2w[:3, 3]) @ np.asarray(c2w[:3, :3], np.float64)
        pixels.append(np.stack([fx * local[:, 0], fy * local[:, 1]], -1) / local[:, 2:] + [cx, cy])
      np.testing.assert_allclose(pixels[1], pixels[0], atol=1e-3)


def test_a_scene_with_segmentations_but_no_depth_has_truth_masks_and_no_flow_truth(
  data_root, tmp_path
):
  record = _copy_without(data_root, tmp_path, ("depth",))
  views = (np.array([[0, 0], [1, 4]]), np.array([[2, 3]]))
  fields = kubric.evaluation_fields(record, views, (H, W))
  assert "object_motions" not in fields and "target_object_masks" not in fields
  poses, segmentations = record["object_poses"], record["segmentations"]
  moved = kubric.moved_objects(poses[:, 3], poses[:, 4])
  expected = kubric.truth_motion_mask(
    segmentations[2 * FRAMES + 3], segmentations[2 * FRAMES + 4], moved
  )
  np.testing.assert_array_equal(fields["target_motion_masks"][0], expected)
