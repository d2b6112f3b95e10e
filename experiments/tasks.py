"""The commands (run / train / finetune / eval) and what differs between datasets (`Task`)."""

from __future__ import annotations

import dataclasses
import json
import pathlib
import time
from collections.abc import Callable
from typing import Any, Literal

import jax

from experiments import data, pixel_baseline, results, training, weights
from experiments.config import Experiment
from tokengs_jax import evaluation, model
from tokengs_jax.data import InputPipeline
from tokengs_jax.objective import ObjectiveConfig
from tokengs_jax.tuning import TuningConfig

Command = Literal["run", "train", "finetune", "eval"]
COMMANDS: tuple[Command, ...] = ("run", "train", "finetune", "eval")


@dataclasses.dataclass(frozen=True)
class TrainedBaseline:
  """A comparison model trained with exactly TokenGS's data, loss weights, optimiser, steps and
  seed, scored beside it as the method `name` (before TokenGS's rows).

  Attributes:
    name: method name in the results; its weights are `<output_dir>/<name>.msgpack` (read from
      beside `--checkpoint` by `eval`) and its checkpoints `<output_dir>/<name>/`.
    init_params: `key -> params`.
    loss_fn: `(params, batch, key, step) -> (loss, aux)`.
    method: `params -> evaluation.Method`.
  """

  name: str
  init_params: Callable[[jax.Array], Any]
  loss_fn: Callable
  method: Callable[[Any], evaluation.Method]


class Task:
  """What differs between datasets: batches, held-out scenes, loss, methods, extra pictures.

  The default is the static chunked datasets (RE10K, DL3DV and the synthetic set); Kubric
  overrides it (`experiments.kubric_task.KubricTask`).
  """

  name: str | None = None  # results title; default the experiment's dataset

  def prepare(self, experiment: Experiment) -> None:
    """Writes the synthetic data if needed: called before any JAX work, because the generator's
    worker processes are forked and forking after JAX has started threads is unsafe."""
    data.data_root(experiment)
    data.held_out_families(experiment)

  def check_evaluation(self, experiment: Experiment) -> dict | None:
    """Raises before any work if the held-out data cannot be evaluated (index vs data); returns
    facts for metrics.json (how the index matched), None when there is nothing to report."""
    return data.check_evaluation_data(experiment)

  def training_batches(self, experiment: Experiment) -> InputPipeline:
    """This process's training pipeline (iterated by the loop; its `rejection_summary()` is
    printed and kept in metrics.json after training)."""
    return data.training_batches(experiment)

  def evaluation_scenes(self, experiment: Experiment) -> list[evaluation.Scene]:
    return data.evaluation_scenes(experiment)

  def test_sets(self, experiment: Experiment) -> dict[str, list[evaluation.Scene]]:
    """Named held-out sets, all scored with the same methods; the first is the primary one
    (top of metrics.json, grids/, PLY and fly-through). Synthetic runs add the
    out-of-distribution galleries and the frozen courtyards (`data.held_out_families`)."""
    sets = {"test": self.evaluation_scenes(experiment)}
    for name, held_out in data.held_out_families(experiment).items():
      sets[name] = data.evaluation_scenes(experiment, held_out=held_out)
    return sets

  def loss_config(self, experiment: Experiment):
    """The training loss weights (`TrainSettings.loss_config`): the photometric, LPIPS, depth,
    coverage and opacity terms of `experiment.train`, the library's defaults (official base) for
    the rest. The depth term never applies to tuning: the input views it supervises carry no
    depth."""
    return experiment.train.loss_config()

  def tuning_loss_config(self, experiment: Experiment):
    """Token tuning's loss: the training loss, its LPIPS term included (as the official
    test-time training's `compute_loss`; `--train.lambda-lpips 0` on `eval` tunes without it),
    with the official dynamic auxiliary term: the input views it tunes on are their own nearest
    views, so no pixel of theirs moved, and carry no segmentation, mask or scene flow (official
    token tuning scores no mask either: `to_ttt` has none)."""
    return dataclasses.replace(
      self.loss_config(experiment),
      lambda_mask=0.0,
      lambda_flow=0.0,
      dyn_aux_on_motion=False,
      dyn_aux_on_objects=False,
    )

  def lpips_params(self, experiment: Experiment):
    """The VGG weights the training and tuning losses need (None when `train.lambda_lpips` is 0)."""
    if self.loss_config(experiment).lambda_lpips <= 0:
      return None
    from tokengs_jax.lpips import load_vgg_params

    return load_vgg_params()

  def objective(self, experiment: Experiment) -> ObjectiveConfig:
    return ObjectiveConfig(
      view_chunk_size=experiment.train.view_chunk_size,
      use_input_supervision=experiment.train.use_input_supervision,
      cross_view_renders=experiment.train.cross_view_renders,
      eps2d=experiment.train.eps2d,
    )

  def loss_fn(self, experiment: Experiment, config: model.ModelConfig):
    from tokengs_jax.objective import tokengs_loss_fn

    return tokengs_loss_fn(
      config,
      self.loss_config(experiment),
      objective=self.objective(experiment),
      lpips_params=self.lpips_params(experiment),
    )

  def methods(
    self, experiment: Experiment, params, include_untrained: bool
  ) -> dict[str, evaluation.Method]:
    """The image baselines, (untrained,) trained and trained + token tuning; the models'
    Gaussians rendered (and tuned) with the run's objective."""
    config, e = experiment.model, experiment.eval
    objective = self.objective(experiment)
    methods = evaluation.baselines()
    if include_untrained:
      methods["untrained"] = evaluation.feed_forward(
        model.init_params(jax.random.key(experiment.seed), config), config, objective
      )
    methods["trained"] = evaluation.feed_forward(params, config, objective)
    if e.tuning_steps > 0:
      methods[evaluation.TUNED_METHODS[e.tuning_target]] = evaluation.tuned(
        params,
        config,
        TuningConfig(
          target=e.tuning_target,
          steps=e.tuning_steps,
          learning_rate=e.tuning_learning_rate,
          gaussian_learning_rate=e.tuning_gaussian_learning_rate,
          schedule=e.tuning_schedule,
        ),
        loss_config=self.tuning_loss_config(experiment),
        objective=objective,
        lpips_params=self.lpips_params(experiment),
      )
    return methods

  def trained_baselines(self, experiment: Experiment) -> list[TrainedBaseline]:
    """The comparison models the run trains and scores: the pixel-aligned (GS-LRM-style) model
    when `eval.pixel_baseline` is set."""
    if not experiment.eval.pixel_baseline:
      return []
    config = experiment.model

    def init_params(key):
      # trained the same way: from its own weights beside --checkpoint where TokenGS starts
      # from a checkpoint (`run pretrain` writes both), else from scratch
      start = experiment.checkpoint and weights.beside(experiment.checkpoint, "pixel_aligned")
      if not start:
        return pixel_baseline.init_params(key, config)
      print(f"[pixel_aligned] starting from {start}", flush=True)
      return weights.load_params(start)

    return [
      TrainedBaseline(
        "pixel_aligned",
        init_params,
        pixel_baseline.loss_fn(
          config,
          self.loss_config(experiment),
          objective=self.objective(experiment),
          lpips_params=self.lpips_params(experiment),
        ),
        lambda params: pixel_baseline.method(params, config, self.objective(experiment)),
      )
    ]

  def extra_visuals(
    self,
    experiment: Experiment,
    config: model.ModelConfig,
    params,
    examples: list[evaluation.Scene],
    writer,
    step: int,
  ) -> dict:
    """Task-specific pictures (called on the writing process only); returns facts to add to
    metrics.json."""
    return {}


def _write_pictures(
  experiment: Experiment, scored: dict[str, evaluation.Evaluation], methods, writer, step: int
) -> list[str]:
  """grids/ of the first `eval.grid_scenes` (grids/<set>/ for the non-primary sets); PLY and
  fly-through of the primary set's first `eval.media_scenes`, from the last method with
  Gaussians (`results.write_scene_media`). Each is a `results.media_step`: returns the one-line
  reasons of those that failed."""
  out, failures = pathlib.Path(experiment.output_dir), []
  for position, (name, result) in enumerate(scored.items()):
    folder = out / "grids" if position == 0 else out / "grids" / name
    with results.media_step(f"grids of test set {name}", failures):
      results.write_grids(
        folder,
        result.kept[: experiment.eval.grid_scenes],
        list(methods),
        writer,
        step,
        tag="eval" if position == 0 else f"eval/{name}",
      )
  primary = next(iter(scored.values()))
  splatted = [name for name, m in methods.items() if m.gaussians is not None]
  if splatted:
    results.write_scene_media(out, primary.kept, splatted[-1], experiment.eval, failures)
  return failures


def run_eval(
  experiment: Experiment,
  params,
  *,
  task: Task,
  writer=None,
  step: int = 0,
  include_untrained: bool = True,
  extra_info: dict | None = None,
  started: float | None = None,
  baseline_params: dict | None = None,
) -> dict:
  """Evaluates `params` (and the baselines) on every test set and writes the results folder.

  started: `time.perf_counter()` at the start of the command (for `total_seconds`).
  baseline_params: name -> weights of `task.trained_baselines` (`_trained_baselines`), each
    scored as its method.
  """
  e = experiment.eval
  start = time.perf_counter()
  test_sets = task.test_sets(experiment)
  methods = task.methods(experiment, params, include_untrained)
  if baseline_params:  # baselines: before TokenGS's rows, whose last one is exported
    trained = {name: methods.pop(name) for name in list(methods) if name.startswith("trained")}
    compared = {b.name: b for b in task.trained_baselines(experiment)}
    methods = {
      **methods,
      **{name: compared[name].method(p) for name, p in baseline_params.items()},
      **trained,
    }
  print(
    f"[eval] {', '.join(f'{name}: {len(s)} scenes' for name, s in test_sets.items())}; "
    f"methods: {', '.join(methods)}",
    flush=True,
  )
  scored = evaluation.evaluate_sets(
    test_sets, methods, evaluation.Scorer(e.lpips), keep=e.kept_scenes
  )
  kind = "real" if experiment.data_dir else "synthetic"
  info = {
    "title": f"{task.name or experiment.dataset} evaluation ({kind} data)",
    "experiment": dataclasses.asdict(experiment),
    "devices": [str(d) for d in jax.devices()],
    **(extra_info or {}),
  }
  # the scores before any picture (then again with the pictures' facts and the timings)
  results.write_metrics(experiment.output_dir, scored, info)
  failures = _write_pictures(experiment, scored, methods, writer, step)
  if evaluation.writes_results():  # pictures only: the other processes write nothing
    with results.media_step("the task's pictures", failures):
      info.update(
        task.extra_visuals(
          experiment, experiment.model, params, next(iter(test_sets.values())), writer, step
        )
      )
  if failures:
    info["media_failures"] = failures
  info["eval_seconds"] = time.perf_counter() - start
  info["total_seconds"] = time.perf_counter() - (start if started is None else started)
  payload = results.write_metrics(experiment.output_dir, scored, info)
  results.write_scalars(writer, scored, step)
  print(results.summary_text(scored), flush=True)
  return payload


def _train(experiment: Experiment, task: Task, command: Command, writer, info: dict):
  """Trains (from scratch or the given weights); saves params and the log; returns params."""
  out = pathlib.Path(experiment.output_dir)
  config = experiment.model
  params = weights.initial_params(experiment, finetune=command == "finetune")
  print(
    f"[model] {model.count_params(config):,} parameters, {config.num_gaussians} Gaussians; "
    f"devices: {jax.devices()}",
    flush=True,
  )
  pipeline = task.training_batches(experiment)

  def held_out_scenes():
    return task.evaluation_scenes(experiment)

  def first_scene():  # the first of held_out_scenes(), without reading the others
    first = dataclasses.replace(experiment.eval, num_scenes=1)
    return task.evaluation_scenes(dataclasses.replace(experiment, eval=first))

  def feed_forward(trained):
    return evaluation.feed_forward(trained, config, task.objective(experiment))

  # The model's feed-forward score on the first test scenes (`train.eval_every`) and its pictures
  # on the first one (`train.log_image_every`), during training.
  evaluate = training.held_out_metrics(experiment, held_out_scenes, feed_forward)
  pictures = training.training_pictures(experiment, first_scene, feed_forward, writer)
  # The loop's history covers the whole run, resumed or not: the checkpoints carry its log.
  params, history, seconds = training.train_model(
    experiment, params, task.loss_fn(experiment, config), iter(pipeline), writer, evaluate, pictures
  )
  rejected = pipeline.rejection_summary()
  print(f"[data] training data rejected:\n{rejected}", flush=True)
  info.update(
    train_seconds=seconds,
    train_steps=experiment.train.steps,
    final_train_loss=history[-1].get("loss") if history else None,
    training_data_rejections=rejected,
  )
  if evaluation.writes_results():
    weights.save_params(out / "params.msgpack", params)
    (out / "train_history.json").write_text(json.dumps(history, indent=1))
  return params


def _trained_baselines(experiment: Experiment, task: Task, command: Command) -> dict:
  """name -> weights of each of `task.trained_baselines`: trained with TokenGS's data, loss,
  optimiser, steps and seed (checkpoints in `<output_dir>/<name>/`) and saved as
  `<output_dir>/<name>.msgpack`, or, for `eval`, read from beside `--checkpoint`."""
  out = pathlib.Path(experiment.output_dir)
  trained = {}
  for baseline in task.trained_baselines(experiment):
    if command == "eval":
      path = weights.beside(experiment.checkpoint or out / "params.msgpack", baseline.name)
      if path is None:
        raise FileNotFoundError(
          f"baseline {baseline.name}: no {baseline.name}.msgpack beside the checkpoint "
          "(written by `run`)"
        )
      trained[baseline.name] = weights.load_params(path)
      continue
    print(f"[{baseline.name}] training the baseline the same way", flush=True)
    params, _, seconds = training.train_model(
      dataclasses.replace(experiment, output_dir=str(out / baseline.name)),
      baseline.init_params(jax.random.key(experiment.seed)),
      baseline.loss_fn,
      iter(task.training_batches(experiment)),
    )
    print(f"[{baseline.name}] trained in {seconds:.0f} s", flush=True)
    if evaluation.writes_results():
      weights.save_params(out / f"{baseline.name}.msgpack", params)
    trained[baseline.name] = params
  return trained


def execute(
  command: Command, experiment: Experiment, task: Task | None = None, invocation: str = ""
) -> dict | None:
  """Runs one command; returns the metrics payload when it evaluated."""
  from tokengs_jax.train import initialize

  task = Task() if task is None else task
  task.prepare(experiment)  # synthetic data only (real data is never written), before JAX starts
  initialize()  # multi-host runs (no-op otherwise); before any other JAX call
  info = {"command": invocation, "commit": weights.source_commit()}
  if command in ("run", "eval"):  # a bad index fails now, not after training
    info["evaluation_index"] = task.check_evaluation(experiment)
  out = pathlib.Path(experiment.output_dir)
  out.mkdir(parents=True, exist_ok=True)
  writer = results.tensorboard_writer(out)
  started = time.perf_counter()
  try:
    if command == "eval":
      if not (experiment.checkpoint or experiment.official_checkpoint):
        print(
          "[eval] no --checkpoint / --official-checkpoint: scoring freshly initialised weights",
          flush=True,
        )
      params = weights.initial_params(experiment, finetune=False)
      return run_eval(
        experiment,
        params,
        task=task,
        writer=writer,
        extra_info=info,
        include_untrained=not experiment.official_checkpoint,
        baseline_params=_trained_baselines(experiment, task, command),
      )
    params = _train(experiment, task, command, writer, info)
    baseline_params = _trained_baselines(experiment, task, command)
    if command in ("train", "finetune"):
      return None
    return run_eval(
      experiment,
      params,
      task=task,
      writer=writer,
      step=experiment.train.steps,
      extra_info=info,
      started=started,
      baseline_params=baseline_params,
    )
  finally:
    if writer is not None:
      writer.close()
