"""The one evaluator: methods, target renders, scores per scene, for every caller.

Entry points (`experiments.*`), the studies and the tests all score through `evaluate`:

    scenes = [(key, batch), ...]                      # batches of one (the data contract)
    methods = {**baselines(), "trained": feed_forward(params, config)}
    evaluation = evaluate(scenes, methods, Scorer(lpips=True))
    evaluation.scores["trained"].summary()            # {"psnr": ..., "ssim": ..., "lpips": ...}

A `Method` either gives Gaussians for a batch (`gaussians`, rendered at the target cameras by
`render_targets` (`tokengs_jax.renders`), the single place where evaluation renders, with the
objective the method's model was trained with: its background, near / far) or predicts the
target images directly (the image baselines). Scores follow the pixelSplat / MVSplat protocol:
per target view, averaged per scene over its targets, then over scenes
(`metrics.mean_over_scenes`).

Clipping policy: the scorer clips predictions and targets to [0, 1] once, before every metric.
The protocol's PSNR clips (pixelSplat `compute_psnr`), and a render composited over the
background only leaves [0, 1] by round-off; clipping for SSIM and LPIPS too means that all three
metrics judge the same images, the ones a person sees in the saved PNGs.

Baselines (`baselines()`): the mean colour of the input views; the **nearest input view** (the
context view whose frame index is nearest the target's; by camera centre where a batch carries no
frame indices); the **input-view average** (pixel-wise mean of the context views). A model that
does not beat the nearest view has not learnt to render a new viewpoint. Dynamic scenes
(`baselines(dynamic=True)`) add the **same camera** (the target camera's input nearest in time;
without one, the nearest camera centre) and the **nearest time** (the input nearest in time; ties:
the nearest camera centre): a model that does not beat them has not learnt motion.

Moving pixels (`motion_scores`), where a batch carries `target_motion_masks` (Kubric): `psnr_moving`
is the PSNR over the pixels where the scene moved, for every method. A target view without a
moving pixel is left out of its scene's mean, and a scene without any out of the mean over scenes
(which then averages the scenes where something moved).

Foreground masks, where a test set's batches carry `target_masks` [1, Vt, H, W] in [0, 1] (Kubric:
the targets' PNG alpha / 255): `psnr_masked`, `ssim_masked` (and `lpips_masked` with LPIPS), the
official evaluation's masked metrics (`metrics.masked_psnr` / `masked_ssim` / `masked_lpips`), for
every method. A view with an empty mask is left out of its scene's mean, a scene without
foreground out of the mean over scenes. A set whose masks are 1 everywhere (opaque alpha, as the
synthetic generator writes) has no foreground to restrict to: its masked scores would repeat the
unmasked ones, so they are omitted and `Evaluation.notes` says so.

Geometry (`geometry_scores`), for methods that render: `holes`, the share of target pixels left
uncovered (alpha < 0.5), and where a test set knows its true depth (`target_depths`, written by
the synthetic generators) the rendered expected depth's AbsRel and delta < 1.25
(`metrics.depth_errors`).

Several test sets (e.g. in-distribution and out-of-distribution rooms) are scored by
`evaluate_sets`, one `Evaluation` per named set, with the same methods and scorer.

Results are computed by every process (each evaluates the same scenes, deterministically) and
written only where `writes_results()` is true: process 0.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from tokengs_jax import metrics, model, splatting, tuning
from tokengs_jax.copies import (
  input_average_images,
  mean_colour_images,
  nearest_time_images,
  nearest_view_images,
  same_camera_images,
)
from tokengs_jax.gaussians import Gaussians
from tokengs_jax.objective import ObjectiveConfig
from tokengs_jax.renders import Rendered as Rendered, render_targets

Scene = tuple[str, dict]  # (scene key, batch of one in the data contract)


# The method name of each test-time tuning target (`tuning.TuningConfig.target`) in results.
TUNED_METHODS = {
  "tokens": "trained+token_tuning",
  "gaussians": "trained+gaussian_tuning",
  "tokens+gaussians": "trained+joint_tuning",
  "latents": "trained+latent_tuning",
}


def writes_results() -> bool:
  """True on the process that writes results (metrics, pictures, weights): process 0."""
  return jax.process_index() == 0


# ----------------------------------------------------------------------------------------------
# Methods


@dataclasses.dataclass(frozen=True)
class Method:
  """One evaluated method: exactly one of the two predictors.

  Attributes:
    gaussians: batch -> Gaussians [B] (one set for every target) or [B, Vt] (one set per
      target view, e.g. a dynamic model decoded at each target's time); rendered at the targets.
    images: batch -> target-view images [B, Vt, H, W, 3] (image baselines; nothing rendered).
    objective: how the `gaussians` are rendered (background, near / far): the one
      their model was trained with, so that evaluation sees what training supervised.
    compact: render the `gaussians` with `render_targets(compact=True)` (the same images).
  """

  gaussians: Callable[[dict], Gaussians] | None = None
  images: Callable[[dict], np.ndarray] | None = None
  objective: ObjectiveConfig = ObjectiveConfig()
  compact: bool = False

  def __post_init__(self):
    if (self.gaussians is None) == (self.images is None):
      raise ValueError("a Method has exactly one of `gaussians` and `images`")


@functools.partial(jax.jit, static_argnames=("config",))
def _reconstruct(params, images, c2w, intrinsics, times, target_times, viewer_c2w, *, config):
  if times is None:
    return model.reconstruct(params, images, c2w, intrinsics, config=config, viewer_c2w=viewer_c2w)
  encoded = model.encode_views(params, images, c2w, intrinsics, config, times)
  if target_times.ndim == 1:
    return Gaussians.from_flat(
      model.decode(params, encoded, config, times=target_times, viewer_c2w=viewer_c2w)
    )
  return model.decode_at_times(params, encoded, config, target_times, viewer_c2w=viewer_c2w)


def gaussians_for_batch(
  params, batch: dict, config: model.ModelConfig, target_times=None, viewer_c2w=None
) -> Gaussians:
  """The network's Gaussians for a batch's context views.

  Time-conditioned models decode at `target_times`: [B] (one set, batch shape [B]) or [B, T]
  (batch shape [B, T]); default `batch["target_times"]`, one set per target view.
  Models whose colours depend on the viewer (`config.viewer_dependent`) are decoded for the
  cameras `viewer_c2w` [B, T, 4, 4] (default: `batch["target_c2w"]` when `target_times` is
  not given), one set per camera, batch shape [B, T]; without cameras their colours are the
  views' mean.
  """
  if target_times is None and viewer_c2w is None:
    viewer_c2w = batch["target_c2w"]
  times = None
  if config.time_embedding:
    times = batch["context_times"]
    target_times = batch["target_times"] if target_times is None else target_times
  return _reconstruct(
    params,
    batch["context_images"],
    batch["context_c2w"],
    batch["context_intrinsics"],
    times,
    target_times,
    viewer_c2w if config.viewer_dependent else None,
    config=config,
  )


def feed_forward(
  params, config: model.ModelConfig, objective: ObjectiveConfig = ObjectiveConfig()
) -> Method:
  """The network's Gaussians (dynamic models: at every target view's time), rendered with the
  training `objective`."""
  return Method(
    gaussians=lambda batch: gaussians_for_batch(params, batch, config), objective=objective
  )


def tuned(
  params,
  config: model.ModelConfig,
  settings: tuning.TuningConfig,
  loss_config=None,
  objective: ObjectiveConfig = ObjectiveConfig(),
  lpips_params=None,
) -> Method:
  """The network's Gaussians after test-time tuning on the input views (`tuning.tune`).

  Dynamic models tune with every input view at its own time and return the Gaussians at every
  target view's time. loss_config: the tuning loss (`losses.LossConfig`; None: the default).
  objective: the training objective, which renders both the tuned input views and the targets.
  lpips_params: VGG weights when `loss_config.lambda_lpips > 0`.
  """
  # on the device once: `load_vgg_params` gives host arrays, which every call would copy again
  lpips_params = None if lpips_params is None else jax.device_put(lpips_params)

  def predict(batch):
    keywords = {}
    if config.time_embedding:
      keywords = {"times": batch["context_times"], "output_times": batch["target_times"]}
    if config.viewer_dependent:
      keywords["output_c2w"] = batch["target_c2w"]
    return tuning.tune(
      params,
      batch["context_images"],
      batch["context_c2w"],
      batch["context_intrinsics"],
      model_config=config,
      tuning=settings,
      loss_config=loss_config,
      objective=objective,
      lpips_params=lpips_params,
      **keywords,
    ).gaussians

  return Method(gaussians=predict, objective=objective)


def baselines(dynamic: bool = False) -> dict[str, Method]:
  """The trivial baselines every evaluation scores, weakest first; `dynamic` adds the copies of
  dynamic scenes, `same_camera` and `nearest_time` (batches with `context_times` /
  `target_times` and `context_cameras` / `target_cameras`, e.g. Kubric's)."""
  methods = {
    "mean_colour": Method(images=mean_colour_images),
    "input_average": Method(images=input_average_images),
    "nearest_view": Method(images=nearest_view_images),
  }
  if dynamic:
    methods["same_camera"] = Method(images=same_camera_images)
    methods["nearest_time"] = Method(images=nearest_time_images)
  return methods


# ----------------------------------------------------------------------------------------------
# Scoring


class Scorer:
  """PSNR, SSIM (and LPIPS) of views [V, H, W, 3] against targets, per view (numpy).

  Both images are clipped to [0, 1] before every metric (see the module docstring).
  """

  def __init__(self, lpips: bool):
    self.lpips_params = None
    if lpips:
      from tokengs_jax.lpips import load_vgg_params

      self.lpips_params = load_vgg_params()

  def __call__(self, pred, target) -> dict[str, np.ndarray]:
    pred, target = (jnp.clip(jnp.asarray(x, jnp.float32), 0.0, 1.0) for x in (pred, target))
    scores = {"psnr": _psnr(pred, target), "ssim": _ssim(pred, target)}
    if self.lpips_params is not None:
      scores["lpips"] = metrics.lpips(pred, target, params=self.lpips_params)
    return {name: np.asarray(value) for name, value in scores.items()}

  def masked(self, pred, target, masks) -> dict[str, np.ndarray]:
    """`psnr_masked`, `ssim_masked` (and `lpips_masked`) of views [V, H, W, 3] over their
    foreground masks [V, H, W] in [0, 1], per view (NaN where a view's mask is empty), after the
    same clipping."""
    pred, target = (jnp.clip(jnp.asarray(x, jnp.float32), 0.0, 1.0) for x in (pred, target))
    masks = jnp.asarray(masks, jnp.float32)
    scores = {
      "psnr_masked": _masked_psnr(pred, target, masks),
      "ssim_masked": _masked_ssim(pred, target, masks),
    }
    if self.lpips_params is not None:
      scores["lpips_masked"] = metrics.masked_lpips(pred, target, masks, self.lpips_params)
    return {name: np.asarray(value) for name, value in scores.items()}


_psnr = jax.jit(metrics.psnr)
_ssim = jax.jit(metrics.ssim)
_masked_psnr = jax.jit(metrics.masked_psnr)
_masked_ssim = jax.jit(metrics.masked_ssim)

# The foreground-mask scores (`Scorer.masked`), and why a set has none although it has masks.
MASKED_METRICS = ("psnr_masked", "ssim_masked", "lpips_masked")
OPAQUE_MASKS_NOTE = (
  "omitted: every target's foreground mask is 1 everywhere (opaque alpha), so the masked scores "
  "would repeat psnr / ssim / lpips"
)


@dataclasses.dataclass
class MethodScores:
  """One method's scores on one test set.

  Attributes:
    per_scene: {"key", metric: mean over the scene's targets} per scored scene.
    per_view: metric -> [Vt] per-target scores, per scored scene (same order).
    predict_seconds: per scored scene, seconds of the prediction alone (reconstruction and
      tuning, arrays ready; the first call of a shape includes compilation).
    render_seconds: per scored scene, seconds of the target render (0 for image methods).
    seconds: wall time of predicting, rendering and scoring every scene.
  """

  per_scene: list[dict] = dataclasses.field(default_factory=list)
  per_view: list[dict[str, np.ndarray]] = dataclasses.field(default_factory=list)
  predict_seconds: list[float] = dataclasses.field(default_factory=list)
  render_seconds: list[float] = dataclasses.field(default_factory=list)
  seconds: float = 0.0

  def summary(self) -> dict[str, float]:
    """Metric -> mean over scenes; empty when the method scored no scene."""
    if not self.per_scene:
      return {}
    names = dict.fromkeys(k for s in self.per_scene for k in s if k != "key")
    # a metric some scenes have no value for (`psnr_moving` where nothing moved): over the others
    return {k: metrics.mean_over_scenes([[s[k]] for s in self.per_scene if k in s]) for k in names}


@dataclasses.dataclass
class Evaluation:
  """Every method's scores on one test set, and the pictures of its first scenes.

  Attributes:
    scores: method name -> MethodScores.
    kept: for the first `keep` scenes, {"key", "batch", method: {"rgb", "depth", "alpha",
      "gaussians"}} (host arrays; depth / alpha / gaussians None for image methods).
    notes: what -> why, for scores the set's data could not give (metrics.json, metrics.md).
  """

  scores: dict[str, MethodScores]
  kept: list[dict]
  notes: dict[str, str] = dataclasses.field(default_factory=dict)

  def summary(self) -> dict[str, dict[str, float]]:
    return {name: scores.summary() for name, scores in self.scores.items()}


def _predict(method: Method, batch: dict, render_config) -> tuple[dict, float, float]:
  """({"rgb" [B, Vt, H, W, 3], "depth", "alpha", "gaussians"}, prediction seconds, render
  seconds) of one method on one batch."""
  start = time.perf_counter()
  if method.images is not None:
    rgb = np.asarray(method.images(batch))
    seconds = time.perf_counter() - start
    return {"rgb": rgb, "depth": None, "alpha": None, "gaussians": None}, seconds, 0.0
  gaussians = jax.block_until_ready(method.gaussians(batch))
  seconds = time.perf_counter() - start
  height, width = batch["target_images"].shape[-3:-1]
  rendered = render_targets(
    gaussians,
    batch["target_c2w"],
    batch["target_intrinsics"],
    height=height,
    width=width,
    render_config=render_config,
    objective=method.objective,
    context_images=batch["context_images"],
    compact=method.compact,
  )
  views = {"rgb": rendered.rgb, "depth": rendered.depth, "alpha": rendered.alpha}
  return {**views, "gaussians": gaussians}, seconds, time.perf_counter() - start - seconds


def geometry_scores(prediction: dict, batch: dict) -> dict[str, np.ndarray]:
  """Per target view of a batch of one: `holes` for a method that renders, plus depth AbsRel and
  delta < 1.25 where the batch carries `target_depths` (synthetic test sets); {} for an image
  method (nothing rendered, no geometry)."""
  if prediction["alpha"] is None:
    return {}
  scores = {"holes": metrics.holes(prediction["alpha"][0])}
  if "target_depths" in batch:
    scores.update(metrics.depth_errors(prediction["depth"][0], batch["target_depths"][0]))
  return scores


def motion_scores(prediction: dict, batch: dict) -> dict[str, np.ndarray]:
  """Per target view of a batch of one carrying `target_motion_masks` [1, Vt, H, W] (dynamic
  test sets): `psnr_moving`, the PSNR over the pixels where the scene moved
  (`metrics.masked_psnr`; NaN for a view without one), for every method, image baselines
  included; {} without masks."""
  if "target_motion_masks" not in batch:
    return {}
  masks = batch["target_motion_masks"][0]
  return {
    "psnr_moving": np.asarray(_masked_psnr(prediction["rgb"][0], batch["target_images"][0], masks))
  }


def has_foreground(batch: dict) -> bool:
  """Whether a batch carries foreground masks (`target_masks`) that leave something out: a
  weight below 1 somewhere (masks of 1 everywhere, an opaque alpha, restrict nothing)."""
  masks = batch.get("target_masks")
  return masks is not None and bool(np.any(np.asarray(masks) < 1.0))


def _target_masks(batch: dict) -> np.ndarray:
  """A batch of one's foreground masks [Vt, H, W]; 1 everywhere for a batch without them (as
  the official evaluation scores a scene without masks among scenes with masks)."""
  if "target_masks" in batch:
    return np.asarray(batch["target_masks"][0], np.float32)
  return np.ones(batch["target_images"].shape[1:-1], np.float32)


def _scene_means(views: dict[str, np.ndarray], batch: dict) -> dict[str, float]:
  """A scene's scores: each metric's mean over its target views, but `psnr_moving` only over the
  views with a moving pixel and the masked metrics only over the views with foreground; such a
  metric is absent when no view has any (the mean over scenes then covers the other scenes)."""
  counted = {}
  if "psnr_moving" in views:
    counted["psnr_moving"] = np.asarray(batch["target_motion_masks"][0]).any(axis=(-2, -1))
  if any(name in views for name in MASKED_METRICS):
    foreground = _target_masks(batch).sum(axis=(-2, -1)) > 0
    counted.update(dict.fromkeys(MASKED_METRICS, foreground))
  means = {}
  for name, values in views.items():
    chosen = counted.get(name)
    if chosen is None:
      means[name] = float(np.mean(values))
    elif chosen.any():
      means[name] = float(np.mean(np.asarray(values)[chosen]))
  return means


def _on_host(prediction: dict) -> dict:
  """A batch-of-one prediction kept for pictures: rgb / depth / alpha without the batch axis,
  Gaussians fetched with it ([1] or [1, Vt])."""
  views = {
    field: None if prediction[field] is None else prediction[field][0]
    for field in ("rgb", "depth", "alpha")
  }
  return {**views, "gaussians": jax.device_get(prediction["gaussians"])}


def evaluate(
  scenes: Sequence[Scene],
  methods: Mapping[str, Method],
  scorer: Scorer,
  *,
  render_config: splatting.RenderConfig | None = None,
  keep: int = 0,
) -> Evaluation:
  """Scores every method on every scene.

  Args:
    scenes: (key, batch of one) pairs; batches may carry `context_frames` / `target_frames`.
    methods: name -> Method.
    scorer: the metrics.
    render_config: renderer settings.
    keep: for the first `keep` scenes, keep the predictions (grids, video, PLY).

  Where a scene carries foreground masks that mask something (`has_foreground`), every scene is
  also scored over its masks (`Scorer.masked`; a scene without masks over all its pixels).
  """
  scores = {name: MethodScores() for name in methods}
  kept = []
  masked = any(has_foreground(batch) for _, batch in scenes)
  notes = {}
  if not masked and any("target_masks" in batch for _, batch in scenes):
    notes["masked metrics"] = OPAQUE_MASKS_NOTE
  for position, (key, batch) in enumerate(scenes):
    entry = {"key": key, "batch": batch}
    for name, method in methods.items():
      start = time.perf_counter()
      prediction, predict_seconds, render_seconds = _predict(method, batch, render_config)
      views = scorer(prediction["rgb"][0], batch["target_images"][0])
      views.update(geometry_scores(prediction, batch))
      views.update(motion_scores(prediction, batch))
      if masked:
        views.update(
          scorer.masked(prediction["rgb"][0], batch["target_images"][0], _target_masks(batch))
        )
      scores[name].seconds += time.perf_counter() - start
      scores[name].predict_seconds.append(predict_seconds)
      scores[name].render_seconds.append(render_seconds)
      scores[name].per_view.append(views)
      scores[name].per_scene.append({"key": key, **_scene_means(views, batch)})
      if position < keep:
        entry[name] = _on_host(prediction)
    if position < keep:
      kept.append(entry)
  return Evaluation(scores, kept, notes)


def evaluate_sets(
  test_sets: Mapping[str, Sequence[Scene]], methods: Mapping[str, Method], scorer: Scorer, **kwargs
) -> dict[str, Evaluation]:
  """`evaluate` on each named test set (same methods, same scorer)."""
  return {name: evaluate(scenes, methods, scorer, **kwargs) for name, scenes in test_sets.items()}


def checks(summary: Mapping[str, Mapping[str, float]]) -> dict[str, str]:
  """The claims an evaluation must show, as readable lines with the measured PSNR margins.

  A baseline or method that scored no scene gives no line (nothing was measured).
  """
  psnr = {name: values["psnr"] for name, values in summary.items() if "psnr" in values}
  lines = {}
  if "trained" in psnr:
    copies = ("nearest_view", "same_camera", "nearest_time")
    for other in (*copies, "input_average", "mean_colour", "untrained"):
      if other in psnr:
        margin = psnr["trained"] - psnr[other]
        lines[f"trained beats {other}"] = f"{margin > 0} (PSNR margin {margin:+.3f} dB)"
    for method in TUNED_METHODS.values():
      if method in psnr:
        gain = psnr[method] - psnr["trained"]
        label = method.removeprefix("trained+").replace("_", " ")
        lines[f"{label} improves trained"] = f"{gain > 0} (PSNR gain {gain:+.3f} dB)"
  return lines
