"""What `python -m experiments.kubric` runs besides its presets: `KubricExperiment` (the
settings: `Experiment` plus the Kubric view sampling, loss weights and synthetic rig) and
`KubricTask` (the training batches and the evaluated views, by index or the default protocol, on
`kubric_data`'s sources; the dynamic loss, the static-only baseline and the dynamic pictures). The presets and
their description (`--help`) are the entry point's, `experiments/kubric.py`."""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Literal

import numpy as np

from experiments import data, dynamic_pictures, dynamic_videos, weights
from experiments.config import SSIM_LOSS, Experiment, TrainSettings
from experiments.kubric_data import (
  OOD_SUBSET,
  data_root,
  kubric_example_config,
  kubric_views,
  ood_source,
  scene_sources,
)
from experiments.tasks import Task, TrainedBaseline
from tokengs_jax import evaluation, losses
from tokengs_jax.data import EvaluationIndexReport, InputPipeline, make_example
from tokengs_jax.data.kubric import (
  KubricSceneSource,
  default_evaluation_views,
  evaluation_fields,
  flat_views,
  load_kubric_evaluation_index,
  validate_kubric_evaluation_index,
)
from tokengs_jax.data.synthetic.kubric_ood import FROZEN_SEED as OOD_SEED
from tokengs_jax.objective import ObjectiveConfig

# Training settings whose loss terms are the official Kubric release's (L1 x 0.8 + SSIM x 0.2).
KUBRIC_TRAIN = TrainSettings(**SSIM_LOSS)


@dataclasses.dataclass(frozen=True)
class KubricExperiment(Experiment):
  """`Experiment` plus the Kubric view sampling and the synthetic rig.

  Attributes:
    num_cameras: cameras per scene: the synthetic rig's size, and the camera tars every scene
      must have and is read from (`KubricSceneSource`; a scene with fewer is rejected). The
      released Kubric-4D rig, and the official loader, have 9 (the `paper` preset).
    min_gap / max_gap: frame span of an example's input views (official 3 / 23); the default
      evaluation spreads its inputs over `max_gap` frames (at most the clip).
    context_cameras: the input views come from this many cameras in turn, each seen at several
      times, in training and in the default evaluation (`kubric_view_selector`,
      `default_evaluation_views`; not official); 0: distinct cameras while there are enough
      (official).
    flow_times: times sampled for the scene-flow and in-between pictures.
    flow_tracks: dynamic Gaussians drawn in the scene-flow plot (the most opaque ones).
    train: as `Experiment`'s, its loss terms (`--train.rgb-loss`, `--train.lambda-ssim`, ...)
      the official Kubric release's by default (`SSIM_LOSS`: L1 x 0.8 + SSIM x 0.2); the
      dynamic terms are the fields below. `train.lambda_depth` must stay 0: Kubric examples
      carry no true depth.
    lambda_dyn_aux: base weight of the dynamic-only auxiliary loss (official release 0.3).
    dyn_aux_hold_fraction / dyn_aux_decay_fraction: the auxiliary weight is held for this
      fraction of `train.steps`, then decays linearly to 0 over the next (official 5k / 10k of 50k).
    lambda_motion: the target pixels that moved weigh 1 + this (`losses.LossConfig`; 0: off).
    dyn_aux_on_motion: the auxiliary loss scores the moving pixels only (False: all, official).
    dyn_aux_on_objects: the auxiliary loss scores the object pixels of the data's segmentations
      and the dynamic render's alpha against them (`losses.LossConfig.dyn_aux_on_objects`; the
      training examples then carry `target_objects`).
    lambda_flow: weight of the scene-flow term (`losses.LossConfig.lambda_flow`; 0: off; the
      training examples then carry `target_flows`).
    decode_times: the time the training loss decodes each supervised view's Gaussians at:
      "first" (official: one decode at the targets' time, shared by every view, the input views
      too under `train.use_input_supervision`) or "per_view" (each view at its own time, so input
      supervision scores every input at its own time; a deviation, `ObjectiveConfig.decode_times`).
    background: what every render of training, token tuning and evaluation composites behind the
      Gaussians: "grey" (official `bg_color`, 0.5) or "input_mean" (each example's mean input
      colour: targets from other cameras show regions no input saw; `ObjectiveConfig.background`).
    normalization: the frame the cameras are expressed in: "mean_cam" (official Kubric: the
      mean input camera) or "first_cam" (the first input camera, as RE10K: the frame of a static
      base trained on RE10K-like data).
    pointmap_trim_lo / pointmap_trim_hi: the scene scale (the "pointmap" scale, the context
      views' mean depth-point distance) averages only the distances between these quantiles
      (official `pointmap_trim_lo` / `pointmap_trim_hi`; `ExampleConfig`); 0 / 1, official: all.
  """

  num_cameras: int = 4
  min_gap: int = 3
  max_gap: int = 23
  context_cameras: int = 0
  flow_times: int = 8
  flow_tracks: int = 48
  train: TrainSettings = KUBRIC_TRAIN
  lambda_dyn_aux: float = 0.3
  dyn_aux_hold_fraction: float = 0.1
  dyn_aux_decay_fraction: float = 0.2
  lambda_motion: float = 0.0
  dyn_aux_on_motion: bool = False
  dyn_aux_on_objects: bool = False
  lambda_flow: float = 0.0
  decode_times: Literal["first", "per_view"] = "first"
  background: Literal["grey", "input_mean"] = "grey"
  normalization: Literal["mean_cam", "first_cam"] = "mean_cam"
  pointmap_trim_lo: float = 0.0
  pointmap_trim_hi: float = 1.0

  def __post_init__(self):
    if not 0 <= self.context_cameras <= self.num_cameras:
      raise ValueError(f"context_cameras must be in 0..{self.num_cameras}: {self.context_cameras}")
    if self.data_mode:  # `Experiment.data_mode` mixes static datasets only
      raise ValueError(
        "--data-mode mixes static datasets (python -m experiments.re10k / experiments.dl3dv); "
        "a Kubric run trains on its one dataset"
      )
    if self.train.lambda_depth > 0:
      raise ValueError("train.lambda_depth must be 0 on Kubric: its examples carry no true depth")
    if self.train.cross_view_renders:
      raise ValueError("train.cross_view_renders is for static models (experiments.re10k)")
    if (self.train.lambda_mask > 0 or self.lambda_flow > 0) and self.train.use_input_supervision:
      raise ValueError(
        "train.lambda_mask and lambda_flow need every supervised view's per-pixel truth, and the "
        "examples carry the targets' only: they exclude train.use_input_supervision"
      )
    KubricTask().loss_config(self)  # the dynamic terms' checks, at parse time
    kubric_example_config(self, training=True)  # the examples' (the trim's), at parse time
    self._check_static_model()

  def _check_static_model(self) -> None:
    """A model without time embedding (official `finetune_dl3dv_kubric_static`) trains with the
    static loss on the target views, times ignored: refuses the settings that would then be
    dropped unsaid (dynamic tokens, the motion-weighted and object terms, the static-only twin).
    The auxiliary weight needs dynamic tokens and is unused without them, as officially."""
    config = self.model
    if config.time_embedding:
      return
    dropped = [
      f"--{flag}"
      for flag, used in (
        ("model.num-dynamic-gs-tokens", config.num_dynamic_gs_tokens > 0),
        ("lambda-motion", self.lambda_motion > 0),
        ("dyn-aux-on-motion", self.dyn_aux_on_motion),
        ("dyn-aux-on-objects", self.dyn_aux_on_objects),
        ("lambda-flow", self.lambda_flow > 0),
        ("eval.static-baseline", self.eval.static_baseline),
      )
      if used
    ]
    if dropped:
      raise ValueError(
        f"a static Kubric model (no --model.time-embedding) trains with the static loss, times "
        f"ignored; {', '.join(dropped)} need a time-conditioned model with dynamic tokens"
      )

  @staticmethod
  def upgrade_record(fields: dict) -> dict:
    """A run recorded before the loss terms moved to `train` (a top-level `rgb_loss`; `train`'s
    other weights then unused): the loss it trained with, in `train`."""
    if "rgb_loss" not in fields:
      return fields
    fields = dict(fields)
    used = {**SSIM_LOSS, "rgb_loss": fields.pop("rgb_loss"), "lambda_depth": 0.0}
    fields["train"] = {**fields.get("train", {}), **used, "lambda_opacity": 0.0}
    return fields


class KubricTask(Task):
  """Kubric data (generated when synthetic), the dynamic loss and the dynamic pictures; a model
  without time embedding trains with the library's static loss on the same examples (the common
  `Task.loss_fn`, as the static-only baseline's), its pictures the common ones only."""

  name = "kubric"

  def prepare(self, experiment: KubricExperiment) -> None:
    data_root(experiment)

  def training_batches(self, experiment: KubricExperiment):
    """This process's batches from the shared input pipeline: grain workers, and an iterator
    state the checkpoints save, so a resumed run continues the data stream where it stopped."""
    local = data.local_batch_size(experiment.train.batch_size)  # before any data is written
    train, _ = scene_sources(experiment)
    pipeline = InputPipeline(
      train,
      kubric_example_config(experiment, training=True),
      batch_size=local,
      seed=experiment.seed,
      num_workers=experiment.train.num_workers,
      select_views=kubric_views(experiment, experiment.train.num_target_views),
      skip_bad=bool(experiment.data_dir),
    )
    return pipeline

  def test_sets(self, experiment: KubricExperiment) -> dict[str, list[evaluation.Scene]]:
    """Its test split and, when synthetic, every scene of the held-out dynamic family
    (`ood_kubric`; the default protocol's views, drawn with the family's frozen seed so they do
    not follow `--seed`). The static galleries and courtyards are not scored: they do not move."""
    sets = {"test": self.evaluation_scenes(experiment)}
    ood = ood_source(experiment)
    if ood is not None:
      sets[OOD_SUBSET] = self._evaluation_scenes(
        experiment, ood, self._default_views(experiment, ood, 0, OOD_SEED), OOD_SEED
      )
    return sets

  def check_evaluation(self, experiment: KubricExperiment) -> dict | None:
    """Chooses every evaluated scene's views (the held-out family's too) before any work, so a
    bad `--eval-index` (or a clip too short for the default protocol) fails now; returns the
    index report for metrics.json (None without an index)."""
    _, report = self.evaluation_views(experiment)
    ood = ood_source(experiment)
    if ood is not None:
      self._default_views(experiment, ood, 0, OOD_SEED)
    return None if report is None else report.as_dict()

  def evaluation_views(
    self, experiment: KubricExperiment
  ) -> tuple[list[tuple[int, tuple[np.ndarray, np.ndarray]]], EvaluationIndexReport | None]:
    """(position in the held-out source, (context [Vc, 2], target [Vt, 2]) (camera, frame)
    pairs) of each evaluated scene, at most `eval.num_scenes` (0: all), and the index's report
    (None without `--eval-index`: the default protocol, drawn per scene from (seed, position))."""
    _, test = scene_sources(experiment)
    limit = experiment.eval.num_scenes
    if experiment.eval_index:
      index = load_kubric_evaluation_index(experiment.eval_index)
      report = validate_kubric_evaluation_index(
        index, test, num_context=experiment.num_context_views, where=experiment.eval_index
      )
      position = {key: i for i, key in enumerate(test.keys)}
      keys = report.matched[:limit] if limit > 0 else report.matched
      return [(position[key], index[key]) for key in keys], report
    return self._default_views(experiment, test, limit, experiment.seed), None

  @staticmethod
  def _default_views(
    experiment: KubricExperiment, source: KubricSceneSource, limit: int, seed: int
  ) -> list[tuple[int, tuple[np.ndarray, np.ndarray]]]:
    """The default protocol's views of the first `limit` scenes of `source` (0: all), scene at
    `position` drawn from `default_rng([seed, position])`."""
    chosen = []
    for position in range(min(len(source), limit) if limit > 0 else len(source)):
      record = source[position]
      views = default_evaluation_views(
        record["num_cameras"],
        record["num_frames"],
        experiment.num_context_views,
        experiment.eval.num_target_views,
        experiment.max_gap,
        np.random.default_rng([seed, position]),
        experiment.context_cameras,
      )
      chosen.append((position, views))
    return chosen

  def evaluation_scenes(self, experiment: KubricExperiment) -> list[tuple[str, dict]]:
    """(key, batch of one) per evaluated scene of the test split (`_evaluation_scenes`)."""
    _, test = scene_sources(experiment)
    return self._evaluation_scenes(
      experiment, test, self.evaluation_views(experiment)[0], experiment.seed
    )

  @staticmethod
  def _evaluation_scenes(
    experiment: KubricExperiment,
    source: KubricSceneSource,
    chosen: list[tuple[int, tuple[np.ndarray, np.ndarray]]],
    seed: int,
  ) -> list[tuple[str, dict]]:
    """(key, batch of one) per (position, views) of `chosen`; besides `make_example`'s fields the
    batches carry `context_cameras` / `target_cameras` and `target_motion_masks`
    (`evaluation_fields`), and `target_masks`, the targets' foreground masks (their PNG alpha):
    the evaluation's masked metrics, omitted with a note where every alpha is opaque."""
    config = dataclasses.replace(
      kubric_example_config(experiment, training=False), target_masks=True
    )
    examples = []
    for position, views in chosen:
      record = source[position]
      rng = np.random.default_rng([seed, position])
      example = make_example(record, config, rng, views=flat_views(record, views))
      example.update(evaluation_fields(record, views, config.image_shape))
      examples.append((record["key"], {k: v[None] for k, v in example.items()}))
    return examples

  def methods(
    self, experiment: KubricExperiment, params, include_untrained: bool
  ) -> dict[str, evaluation.Method]:
    """The common methods, the baselines of dynamic scenes (same camera, nearest time) among
    the baselines."""
    return {
      **evaluation.baselines(dynamic=True),
      **super().methods(experiment, params, include_untrained),
    }

  def trained_baselines(self, experiment: KubricExperiment) -> list[TrainedBaseline]:
    """The common ones, and with `eval.static_baseline` the static-only model: every dynamic
    token becomes a static one (the same Gaussian budget and input-time embedding), so its
    Gaussians cannot depend on the target time."""
    baselines = super().trained_baselines(experiment)
    if not experiment.eval.static_baseline:
      return baselines
    config = experiment.model
    static = config.replace(
      num_gs_tokens=config.num_gs_tokens + config.num_dynamic_gs_tokens, num_dynamic_gs_tokens=0
    )

    def init_params(key):
      # its own weights beside --checkpoint where a run saved them (`run pretrain` ships both),
      # else from --checkpoint as the dynamic model, its dynamic tokens then fresh static ones
      start = experiment.checkpoint and weights.beside(experiment.checkpoint, "static_only")
      if start:
        print(f"[static_only] starting from {start}", flush=True)
        return weights.load_params(start)
      return weights.initial_params(dataclasses.replace(experiment, model=static), finetune=False)

    return baselines + [
      TrainedBaseline(
        "static_only",
        init_params,
        self.loss_fn(experiment, static),
        lambda params: evaluation.feed_forward(params, static, self.objective(experiment)),
      )
    ]

  def loss_config(self, experiment: KubricExperiment) -> losses.LossConfig:
    """The common terms of `experiment.train` (`TrainSettings.loss_config`: photometric, SSIM,
    LPIPS, coverage, opacity; the official release's L1 x 0.8 + SSIM x 0.2 in every preset) plus
    the dynamic ones: visibility x 1 and the auxiliary loss, its schedule scaled to
    `train.steps`."""
    steps = experiment.train.steps
    return dataclasses.replace(
      experiment.train.loss_config(),
      lambda_vis=1.0,
      lambda_dyn_aux=experiment.lambda_dyn_aux,
      lambda_motion=experiment.lambda_motion,
      dyn_aux_on_motion=experiment.dyn_aux_on_motion,
      dyn_aux_on_objects=experiment.dyn_aux_on_objects,
      lambda_flow=experiment.lambda_flow,
      dyn_aux_hold_steps=round(experiment.dyn_aux_hold_fraction * steps),
      dyn_aux_decay_steps=max(round(experiment.dyn_aux_decay_fraction * steps), 1),
    )

  def objective(self, experiment: KubricExperiment) -> ObjectiveConfig:
    objective = ObjectiveConfig(
      view_chunk_size=experiment.train.view_chunk_size,
      decode_times=experiment.decode_times,
      use_input_supervision=experiment.train.use_input_supervision,
      eps2d=experiment.train.eps2d,
    )
    if experiment.background == "input_mean":
      return dataclasses.replace(objective, background="input_mean")
    return objective

  def extra_visuals(
    self, experiment: KubricExperiment, config, params, examples, writer, step
  ) -> dict:
    """`dynamic/`'s pictures, the scene-flow scores and (`eval.video_frames` > 0) the official
    videos of the first `eval.media_scenes` scenes (`experiments.dynamic_videos`); none for a
    static model (no time embedding: its Gaussians do not move)."""
    if not config.time_embedding:
      return {}
    out = pathlib.Path(experiment.output_dir) / "dynamic"
    visuals = {
      "dynamic": dynamic_pictures.write_pictures(
        out,
        params,
        config,
        examples[0],
        experiment.flow_times,
        experiment.flow_tracks,
        writer,
        step,
      ),
      "scene_flow": dynamic_pictures.scene_flow_report(out, params, config, examples),
    }
    if experiment.eval.video_frames > 0:
      visuals["videos"] = self._videos(experiment, config, params, examples)
    return visuals

  def _videos(self, experiment: KubricExperiment, config, params, examples) -> dict:
    """`dynamic_videos.write_scene_videos` of the first `eval.media_scenes` (0: all) of the
    evaluated `examples`, from their records in the held-out source."""
    _, test = scene_sources(experiment)
    count = experiment.eval.media_scenes
    keys = [key for key, _ in (examples if count == 0 else examples[:count])]
    return dynamic_videos.write_scene_videos(
      pathlib.Path(experiment.output_dir) / "videos",
      params,
      config,
      self.objective(experiment),
      [(key, test[test.keys.index(key)]) for key in keys],
      kubric_example_config(experiment, training=False),
      experiment.eval.video_frames,
      per_scene=count != 1,
    )
