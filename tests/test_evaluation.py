"""tokengs_jax.evaluation: baselines, the scorer, per-scene means, checks (the target renders:
test_renders.py)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tokengs_jax import copies, evaluation, metrics, splatting
from tokengs_jax.camera import invert_rigid
from tokengs_jax.gaussians import Gaussians
from tokengs_jax.tuning import TuningConfig

from scenes import EVAL_HEIGHT as HEIGHT
from scenes import EVAL_WIDTH as WIDTH
from scenes import evaluation_batch, evaluation_gaussians


def test_nearest_view_is_the_input_with_the_nearest_frame_index():
  batch = evaluation_batch(np.random.default_rng(0), [0, 5, 12], [1, 3, 8, 9, 12])
  np.testing.assert_array_equal(copies.nearest_views(batch), [[0, 1, 1, 2, 2]])
  images = copies.nearest_view_images(batch)
  assert images.shape == batch["target_images"].shape
  for view, source in enumerate([0, 1, 1, 2, 2]):
    np.testing.assert_array_equal(images[0, view], batch["context_images"][0, source])
  # a tie (frame 6 is 6 from 0 and from 12) goes to the earlier input
  tie = evaluation_batch(np.random.default_rng(0), [0, 12], [6])
  np.testing.assert_array_equal(copies.nearest_views(tie), [[0]])


def test_nearest_view_falls_back_to_camera_centres_without_frames():
  batch = evaluation_batch(np.random.default_rng(0), [0, 10], [2, 7])
  del batch["context_frames"], batch["target_frames"]
  np.testing.assert_array_equal(copies.nearest_views(batch), [[0, 1]])


def test_mean_colour_and_input_average_baselines():
  batch = evaluation_batch(np.random.default_rng(1), [0, 4], [1, 2, 3])
  mean = copies.mean_colour_images(batch)
  assert mean.shape == (1, 3, HEIGHT, WIDTH, 3)
  np.testing.assert_allclose(
    mean[0, 2, 1, 1], batch["context_images"][0].mean(axis=(0, 1, 2)), rtol=1e-6
  )
  average = copies.input_average_images(batch)
  np.testing.assert_allclose(average[0, 1], batch["context_images"][0].mean(axis=0), rtol=1e-6)


def test_baselines_are_scored_on_exactly_the_evaluated_targets():
  """Every baseline is scored once per evaluated target view, against that target, per scene."""
  rng = np.random.default_rng(2)
  scenes = [
    ("a", evaluation_batch(rng, [0, 8], [1, 4, 7])),
    ("b", evaluation_batch(rng, [2, 20], [3, 19])),
  ]
  scored = evaluation.evaluate(scenes, evaluation.baselines(), evaluation.Scorer(lpips=False))
  assert list(scored.scores) == ["mean_colour", "input_average", "nearest_view"]
  for name, method in evaluation.baselines().items():
    scores = scored.scores[name]
    assert [s["key"] for s in scores.per_scene] == ["a", "b"]
    for (_, batch), views, scene in zip(scenes, scores.per_view, scores.per_scene, strict=True):
      expected = np.asarray(metrics.psnr(method.images(batch)[0], batch["target_images"][0]))
      assert views["psnr"].shape == (batch["target_images"].shape[1],)
      np.testing.assert_allclose(views["psnr"], expected, rtol=1e-5)
      assert scene["psnr"] == pytest.approx(float(np.mean(expected)), rel=1e-5)
    assert scores.summary()["psnr"] == pytest.approx(np.mean([s["psnr"] for s in scores.per_scene]))


def test_scorer_clips_every_metric_to_the_displayed_range():
  rng = np.random.default_rng(3)
  target = rng.uniform(size=(2, HEIGHT, WIDTH, 3)).astype(np.float32)
  pred = target + rng.normal(0, 0.3, size=target.shape).astype(np.float32)  # leaves [0, 1]
  scorer = evaluation.Scorer(lpips=False)
  raw, clipped = scorer(pred, target), scorer(np.clip(pred, 0, 1), target)
  for name in ("psnr", "ssim"):
    np.testing.assert_allclose(raw[name], clipped[name], rtol=1e-6)
  assert not np.allclose(
    raw["ssim"], np.asarray(metrics.ssim(pred, target))
  )  # SSIM alone would not clip


def test_a_method_that_scored_nothing_has_an_empty_summary_and_no_check():
  assert evaluation.MethodScores().summary() == {}
  summary = {"trained": {}, "nearest_view": {"psnr": 20.0}, "trained+token_tuning": {"psnr": 22.0}}
  assert evaluation.checks(summary) == {}
  lines = evaluation.checks(
    {
      "trained": {"psnr": 21.0},
      "nearest_view": {"psnr": 20.0},
      "mean_colour": {"psnr": 15.0},
      "trained+token_tuning": {"psnr": 20.5},
    }
  )
  assert lines["trained beats nearest_view"] == "True (PSNR margin +1.000 dB)"
  assert lines["trained beats mean_colour"].startswith("True")
  assert lines["token tuning improves trained"] == "False (PSNR gain -0.500 dB)"


def test_a_method_has_exactly_one_predictor():
  with pytest.raises(ValueError, match="exactly one"):
    evaluation.Method()
  with pytest.raises(ValueError, match="exactly one"):
    evaluation.Method(gaussians=lambda b: None, images=lambda b: None)


def test_only_process_zero_writes(monkeypatch):
  assert evaluation.writes_results()
  monkeypatch.setattr(jax, "process_index", lambda: 2)
  assert not evaluation.writes_results()


def test_evaluate_renders_gaussian_methods_and_keeps_pictures():
  batch = evaluation_batch(np.random.default_rng(5), [0, 4], [1, 3])
  gaussians = evaluation_gaussians((1,))
  methods = {"splats": evaluation.Method(gaussians=lambda b: gaussians), **evaluation.baselines()}
  scored = evaluation.evaluate([("s", batch)], methods, evaluation.Scorer(lpips=False), keep=1)
  expected = evaluation.render_targets(
    gaussians, batch["target_c2w"], batch["target_intrinsics"], height=HEIGHT, width=WIDTH
  ).rgb
  np.testing.assert_allclose(
    scored.scores["splats"].per_view[0]["psnr"],
    metrics.psnr(expected[0], batch["target_images"][0]),
    rtol=1e-5,
  )
  kept = scored.kept[0]
  assert kept["key"] == "s" and kept["splats"]["rgb"].shape == (2, HEIGHT, WIDTH, 3)
  assert kept["splats"]["depth"].shape == (2, HEIGHT, WIDTH, 1)
  assert kept["nearest_view"]["depth"] is None and kept["nearest_view"]["gaussians"] is None
  assert len(scored.scores["splats"].predict_seconds) == 1


def test_evaluation_renders_each_method_with_its_objective(monkeypatch):
  """A method's Gaussians are rendered with the objective its model trained with ("input_mean":
  the render on black plus (1 - alpha) x the batch's mean input colour), and the model methods
  of a run carry (and tune with) the run's objective."""
  from experiments import pixel_baseline
  from experiments.kubric_task import KubricExperiment, KubricTask
  from tokengs_jax import model, tuning
  from tokengs_jax.objective import ObjectiveConfig

  batch = evaluation_batch(np.random.default_rng(9), [0, 4], [1, 3])
  batch["context_images"] *= 0.4  # a mean colour near 0.2, far from the official grey
  gaussians = evaluation_gaussians((1,))
  input_mean = ObjectiveConfig(background="input_mean")
  methods = {
    "grey": evaluation.Method(gaussians=lambda b: gaussians),
    "input_mean": evaluation.Method(gaussians=lambda b: gaussians, objective=input_mean),
  }
  scored = evaluation.evaluate([("s", batch)], methods, evaluation.Scorer(lpips=False), keep=1)
  black = evaluation.render_targets(
    gaussians,
    batch["target_c2w"],
    batch["target_intrinsics"],
    height=HEIGHT,
    width=WIDTH,
    objective=ObjectiveConfig(background=(0.0, 0.0, 0.0)),
  )
  uncovered = 1.0 - black.alpha[0]
  assert 0.1 < uncovered.mean() < 0.9  # the background shows, but not everywhere
  mean = batch["context_images"][0].mean(axis=(0, 1, 2))
  for name, colour in (("grey", 0.5), ("input_mean", mean)):
    expected = black.rgb[0] + uncovered * colour
    np.testing.assert_allclose(scored.kept[0][name]["rgb"], expected, atol=1e-6)

  config = model.preset("tiny")
  seen = {}

  def fake_tune(*args, objective, **kwargs):
    seen["objective"] = objective
    return tuning.TuningResult(gaussians, jnp.zeros(1))

  monkeypatch.setattr(evaluation.tuning, "tune", fake_tune)
  tuned = evaluation.tuned(None, config, TuningConfig(), objective=input_mean)
  tuned.gaussians(batch)
  assert seen["objective"] == tuned.objective == input_mean
  assert evaluation.feed_forward(None, config, input_mean).objective == input_mean
  assert pixel_baseline.method(None, config, input_mean).objective == input_mean
  experiment = KubricExperiment(background="input_mean")
  run = KubricTask().methods(experiment, None, include_untrained=False)
  rendered = {name: m.objective for name, m in run.items() if m.gaussians is not None}
  assert set(rendered) == {"trained", "trained+token_tuning"}
  assert all(o == KubricTask().objective(experiment) for o in rendered.values())
  assert KubricTask().objective(experiment).background == "input_mean"


def test_evaluate_sets_scores_each_named_set():
  rng = np.random.default_rng(6)
  sets = {
    "test": [("a", evaluation_batch(rng, [0, 4], [2]))],
    "ood": [
      ("b", evaluation_batch(rng, [0, 6], [1, 5])),
      ("c", evaluation_batch(rng, [0, 6], [3])),
    ],
  }
  scored = evaluation.evaluate_sets(sets, evaluation.baselines(), evaluation.Scorer(lpips=False))
  assert list(scored) == ["test", "ood"]
  assert [s["key"] for s in scored["ood"].scores["nearest_view"].per_scene] == ["b", "c"]


@pytest.mark.slow
def test_feed_forward_and_tuned_methods_on_the_tiny_model(tiny):
  config, params = tiny
  rng = np.random.default_rng(7)
  batch = evaluation_batch(rng, [0, 4], [1, 3], height=32, width=32)
  methods = {
    "trained": evaluation.feed_forward(params, config),
    # a learning rate at which 5 steps move the untrained model's loss visibly (by about 1e-6)
    "tuned": evaluation.tuned(params, config, TuningConfig(steps=5, learning_rate=1e-2)),
  }
  scored = evaluation.evaluate([("s", batch)], methods, evaluation.Scorer(lpips=True), keep=1)
  for name in methods:
    views = scored.scores[name].per_view[0]
    assert views["psnr"].shape == views["ssim"].shape == views["lpips"].shape == (2,)
    assert np.all(np.isfinite(views["psnr"])) and np.all(views["lpips"] >= 0)
    assert scored.kept[0][name]["gaussians"].means.shape == (1, config.num_gaussians, 3)
  # the tuned method returns what tuning moved, not the feed-forward Gaussians
  trained, tuned = (scored.kept[0][name]["gaussians"] for name in ("trained", "tuned"))
  assert float(np.abs(np.asarray(tuned.means) - np.asarray(trained.means)).max()) > 1e-6
  # and tuning lowered what it minimises: the loss of renders of the input views
  trained_loss, tuned_loss = (_input_view_loss(g, batch) for g in (trained, tuned))
  assert tuned_loss < trained_loss, (tuned_loss, trained_loss)


def _input_view_loss(gaussians: Gaussians, batch: dict) -> float:
  """Test-time tuning's loss (the default objective and loss) of Gaussians on the input views."""
  from tokengs_jax import losses
  from tokengs_jax.objective import supervision_loss

  images = jnp.asarray(batch["context_images"])
  loss, terms = supervision_loss(
    gaussians,
    images,
    invert_rigid(jnp.asarray(batch["context_c2w"])),
    jnp.asarray(batch["context_intrinsics"]),
    losses.LossConfig(),
    splatting.RenderConfig(),
    context_images=images,
  )
  assert int(terms["render_overflow"]) == 0  # a whole render, as tuning scores it
  return float(loss)


@pytest.mark.slow
def test_dynamic_methods_decode_at_each_target_views_time():
  from scenes import DYNAMIC_CONFIG, DYNAMIC_SIZE, dynamic_batch, dynamic_params

  from tokengs_jax import model

  params = dynamic_params()
  batch = dynamic_batch([[0.0, 1.0]], [[0.3, 0.8]])
  scored = evaluation.evaluate(
    [("s", batch)],
    {"ff": evaluation.feed_forward(params, DYNAMIC_CONFIG)},
    evaluation.Scorer(lpips=False),
  )
  context = (batch["context_images"], batch["context_c2w"], batch["context_intrinsics"])
  expected = []
  for t in range(2):
    gaussians = model.reconstruct(
      params,
      *context,
      config=DYNAMIC_CONFIG,
      times=batch["context_times"],
      target_times=batch["target_times"][:, t],
    )
    view = slice(t, t + 1)
    rgb = evaluation.render_targets(
      gaussians,
      batch["target_c2w"][:, view],
      batch["target_intrinsics"][:, view],
      height=DYNAMIC_SIZE,
      width=DYNAMIC_SIZE,
    ).rgb
    expected.append(
      np.asarray(metrics.psnr(np.clip(rgb, 0, 1), batch["target_images"][:, view]))[0]
    )
  np.testing.assert_allclose(
    scored.scores["ff"].per_view[0]["psnr"], np.concatenate(expected), rtol=1e-5
  )
  tuned = evaluation.tuned(params, DYNAMIC_CONFIG, TuningConfig(steps=2, learning_rate=1e-2))
  assert tuned.gaussians(batch).batch_shape == (1, 2)  # one tuned set per target time


def test_geometry_scores_for_rendering_methods_only():
  batch = evaluation_batch(np.random.default_rng(8), [0, 4], [1, 3])
  gaussians = evaluation_gaussians((1,))
  rendered = evaluation.render_targets(
    gaussians, batch["target_c2w"], batch["target_intrinsics"], height=HEIGHT, width=WIDTH
  )
  batch["target_depths"] = np.where(rendered.alpha[..., 0] > 0.5, 2.0 * rendered.depth[..., 0], 0)
  batch["target_depths"][0, :, 0, 0] = 1.0  # at least one known pixel per view
  methods = {"splats": evaluation.Method(gaussians=lambda b: gaussians), **evaluation.baselines()}
  scored = evaluation.evaluate([("s", batch)], methods, evaluation.Scorer(lpips=False))
  splats = scored.scores["splats"].per_view[0]
  np.testing.assert_allclose(splats["holes"], metrics.holes(rendered.alpha[0]))
  expected = metrics.depth_errors(rendered.depth[0], batch["target_depths"][0])
  np.testing.assert_allclose(splats["depth_absrel"], expected["depth_absrel"])
  assert (splats["depth_absrel"] > 0.3).all()  # the truth is twice the render almost everywhere
  assert set(scored.summary()["nearest_view"]) == {"psnr", "ssim"}  # no geometry for a copy


def _dynamic_batch(rng, context, target) -> dict:
  """A batch of one whose views are (camera, time) pairs; camera c sits at x = c."""
  batch = evaluation_batch(rng, [c for c, _ in context], [c for c, _ in target])
  del batch["context_frames"], batch["target_frames"]  # nearest_view: by camera centre
  for side, views in (("context", context), ("target", target)):
    batch[f"{side}_cameras"] = np.asarray([[c for c, _ in views]])
    batch[f"{side}_times"] = np.asarray([[t for _, t in views]], np.float32)
    batch[f"{side}_c2w"][0, :, 0, 3] = [c for c, _ in views]
  return batch


def test_same_camera_copies_the_targets_own_camera_nearest_in_time():
  context = [(0, 0.0), (1, 0.5), (0, 1.0)]
  # camera 0 twice (nearest time wins, then a tie goes to the first), camera 1, and camera 3,
  # which has no input: the nearest camera centre (camera 1 at x = 1 beats camera 0 at x = 0)
  target = [(0, 0.8), (0, 0.5), (1, 0.0), (3, 0.1)]
  batch = _dynamic_batch(np.random.default_rng(9), context, target)
  np.testing.assert_array_equal(copies.same_camera_views(batch), [[2, 0, 1, 1]])
  images = copies.same_camera_images(batch)
  for view, source in enumerate([2, 0, 1, 1]):
    np.testing.assert_array_equal(images[0, view], batch["context_images"][0, source])


def test_nearest_time_copies_the_input_nearest_in_time_ties_by_camera_centre():
  context = [(0, 0.0), (4, 0.5), (1, 1.0)]
  target = [(0, 0.3), (4, 0.9), (0, 0.25), (2, 0.75), (9, 0.5)]
  batch = _dynamic_batch(np.random.default_rng(10), context, target)
  # 0.25 is as near 0.0 as 0.5: camera 0's centre is nearer; 0.75: camera 1 (x = 1) beats 4
  np.testing.assert_array_equal(copies.nearest_time_views(batch), [[1, 2, 0, 2, 1]])
  np.testing.assert_array_equal(
    copies.nearest_time_images(batch)[0, 3], batch["context_images"][0, 2]
  )
  # float32 rounding of equal gaps is still a tie
  batch["target_times"][0, 2] = np.nextafter(np.float32(0.25), np.float32(1.0))
  assert copies.nearest_time_views(batch)[0, 2] == 0


def test_dynamic_baselines_are_added_on_request_and_checked_against():
  assert list(evaluation.baselines()) == ["mean_colour", "input_average", "nearest_view"]
  dynamic = evaluation.baselines(dynamic=True)
  assert list(dynamic) == [
    "mean_colour",
    "input_average",
    "nearest_view",
    "same_camera",
    "nearest_time",
  ]
  lines = evaluation.checks(
    {"trained": {"psnr": 21.0}, "same_camera": {"psnr": 22.0}, "nearest_time": {"psnr": 20.5}}
  )
  assert lines == {
    "trained beats same_camera": "False (PSNR margin -1.000 dB)",
    "trained beats nearest_time": "True (PSNR margin +0.500 dB)",
  }


def test_psnr_moving_scores_every_method_over_the_moving_pixels_only():
  rng = np.random.default_rng(11)
  moving = _dynamic_batch(rng, [(0, 0.0), (1, 1.0)], [(2, 0.5), (0, 0.5)])
  masks = np.zeros((1, 2, HEIGHT, WIDTH), bool)
  masks[0, 0, 2:6, 3:9] = True  # the second target view has no moving pixel
  moving["target_motion_masks"] = masks
  still = _dynamic_batch(rng, [(0, 0.0), (1, 1.0)], [(2, 0.5)])
  still["target_motion_masks"] = np.zeros((1, 1, HEIGHT, WIDTH), bool)
  static = evaluation_batch(rng, [0, 4], [2])  # no masks at all: no psnr_moving
  scenes = [("moving", moving), ("still", still), ("static", static)]
  methods = {"splats": evaluation.Method(gaussians=lambda b: evaluation_gaussians((1,)))}
  methods.update(evaluation.baselines())
  scored = evaluation.evaluate(scenes, methods, evaluation.Scorer(lpips=False))
  for name, scores in scored.scores.items():
    views = scores.per_view[0]["psnr_moving"]
    prediction = _scored_rgb(methods[name], moving)
    expected = metrics.masked_psnr(prediction[0, 0], moving["target_images"][0, 0], masks[0, 0])
    np.testing.assert_allclose(views[0], expected, rtol=1e-5)
    assert np.isnan(views[1])  # nothing moved in this view: left out of the scene's mean
    assert scores.per_scene[0]["psnr_moving"] == pytest.approx(float(views[0]))
    assert "psnr_moving" not in scores.per_scene[1] and "psnr_moving" not in scores.per_scene[2]
    summary = scores.summary()
    assert summary["psnr_moving"] == pytest.approx(float(views[0]))  # the scene that moved
    assert summary["psnr"] == pytest.approx(np.mean([s["psnr"] for s in scores.per_scene]))
    assert all(np.isfinite(v) for v in summary.values())


def _scored_rgb(method: evaluation.Method, batch: dict) -> np.ndarray:
  """What `evaluate` scores for a method: its images, or its render at the target cameras."""
  if method.images is not None:
    return method.images(batch)
  return evaluation.render_targets(
    method.gaussians(batch),
    batch["target_c2w"],
    batch["target_intrinsics"],
    height=HEIGHT,
    width=WIDTH,
  ).rgb


def test_masked_metrics_score_the_foreground_of_every_method():
  """Batches carrying foreground masks (Kubric's alpha): the official masked PSNR / SSIM per
  view; an empty mask leaves its view out, a scene without masks is scored over all pixels."""
  rng = np.random.default_rng(12)
  masked = evaluation_batch(rng, [0, 4], [1, 2])
  masks = np.zeros((1, 2, HEIGHT, WIDTH), np.float32)
  masks[0, 0, 3:11, 2:9] = 1.0
  masks[0, 0, 3:11, 9] = 0.4  # a soft edge; the second view shows no foreground
  masked["target_masks"] = masks
  unmasked = evaluation_batch(rng, [0, 4], [2])  # no masks: the official all-ones mask
  scenes = [("masked", masked), ("unmasked", unmasked)]
  methods = {"splats": evaluation.Method(gaussians=lambda b: evaluation_gaussians((1,)))}
  methods.update(evaluation.baselines())
  scored = evaluation.evaluate(scenes, methods, evaluation.Scorer(lpips=False))
  assert scored.notes == {}
  for name, scores in scored.scores.items():
    views = scores.per_view[0]
    prediction = np.clip(_scored_rgb(methods[name], masked)[0, 0], 0.0, 1.0)
    target = masked["target_images"][0, 0]
    psnr = metrics.masked_psnr(prediction, target, masks[0, 0])
    ssim = metrics.masked_ssim(prediction, target, masks[0, 0])
    np.testing.assert_allclose(views["psnr_masked"][0], psnr, rtol=1e-5)
    np.testing.assert_allclose(views["ssim_masked"][0], ssim, rtol=1e-5, atol=1e-6)
    assert np.isnan(views["psnr_masked"][1]) and np.isnan(views["ssim_masked"][1])
    assert scores.per_scene[0]["psnr_masked"] == pytest.approx(float(views["psnr_masked"][0]))
    assert "lpips_masked" not in views  # no LPIPS scorer
    whole = scores.per_scene[1]  # scored over all its pixels
    assert whole["psnr_masked"] == pytest.approx(whole["psnr"], rel=1e-5)
    assert whole["ssim_masked"] == pytest.approx(whole["ssim"], rel=1e-5)
    summary = scores.summary()
    expected = np.mean([float(views["psnr_masked"][0]), whole["psnr"]])
    assert summary["psnr_masked"] == pytest.approx(expected, rel=1e-5)


def test_opaque_masks_give_no_masked_metrics_and_say_so():
  rng = np.random.default_rng(13)
  opaque = evaluation_batch(rng, [0, 4], [1, 2])
  opaque["target_masks"] = np.ones((1, 2, HEIGHT, WIDTH), np.float32)
  scorer = evaluation.Scorer(lpips=False)
  scored = evaluation.evaluate([("opaque", opaque)], evaluation.baselines(), scorer)
  assert scored.notes == {"masked metrics": evaluation.OPAQUE_MASKS_NOTE}
  for scores in scored.scores.values():
    assert not set(evaluation.MASKED_METRICS) & set(scores.summary())
  plain = evaluation.evaluate(
    [("plain", evaluation_batch(rng, [0, 4], [2]))], evaluation.baselines(), scorer
  )
  assert plain.notes == {}  # a set without masks has nothing to explain
