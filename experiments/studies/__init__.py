"""The paper's studies, one script each; every script writes a table (JSON + Markdown) and a plot.

    python -m experiments.studies all [--quick] [--seeds N]   # every claim, seeds, docs/studies.md
    python -m experiments.studies.camera_noise         # TokenGS vs pixel-aligned baseline
    python -m experiments.studies.view_extrapolation   # targets outside the inputs' span
    python -m experiments.studies.context_extension    # a model trained with 2-4 input views
    python -m experiments.studies.test_time_scaling    # views, tuning steps, tuning target
    python -m experiments.studies.token_count          # PSNR and run time vs Gaussian tokens
    python -m experiments.studies.visibility           # the visibility loss on vs off
    python -m experiments.studies.distribution         # Gaussians per unit area vs depth
    python -m experiments.studies.token_assignment     # Gaussians coloured by their token

On its own, each study runs on the RE10K default (`python -m experiments.re10k`'s preset
`synthetic-tiny`): its weights are `params` when that file exists, else the experiment's starting
weights (the shipped ones; fresh ones without a checkpoint) trained for `train.steps` (0 by
default) and saved there; a pixel-aligned baseline the same way (`baseline_params`, from the
shipped `pixel_aligned.msgpack`). `--experiment.*` flags change data, model and training exactly as
on the entry point. The models a study trains beside it (`context_extension`'s, `visibility`'s,
`token_count --retrain`'s) train the same way, so with the default's 0 steps they are the start:
compare trained arms with `--experiment.train.steps N` (and `--experiment.checkpoint None`: from
scratch) and `params` trained so. `all` (`__main__.py`) trains every model from scratch per seed.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from experiments import re10k, tasks, training, weights
from experiments.config import Experiment
from experiments.results import markdown_table
from tokengs_jax import camera, evaluation, model

PIXEL_ALIGNED = "pixel-aligned (GS-LRM-style)"  # the baseline's name in every study's table


@dataclasses.dataclass(frozen=True)
class StudySettings:
  """Shared by every study.

  Attributes:
    experiment: data / model / training / evaluation settings (the RE10K default preset).
    params: trained TokenGS weights; trained with `experiment` (and saved there) when missing.
    baseline_params: the pixel-aligned baseline's weights, for the studies that compare with it;
      trained the same way when missing; default `<output_dir>/pixel_baseline.msgpack`.
    output_dir: where the study's table and plot go.
  """

  experiment: Experiment = re10k.PRESETS["synthetic-tiny"]
  params: str = "outputs/re10k/tiny_synthetic/params.msgpack"
  baseline_params: str | None = None
  output_dir: str = "outputs/studies"


def train(experiment: Experiment, params, loss_fn=None) -> dict:
  """Trains with the experiment's settings (default loss: TokenGS's); returns the weights."""
  task = tasks.Task()
  loss_fn = task.loss_fn(experiment, experiment.model) if loss_fn is None else loss_fn
  params, history, seconds = training.train_model(
    experiment, params, loss_fn, iter(task.training_batches(experiment))
  )
  final = f", final loss {history[-1]['loss']:.4f}" if history else ""
  print(f"[study] trained in {seconds:.0f} s{final}", flush=True)
  return params


def saved_or_trained(path, what: str, fit: Callable[[], dict]) -> dict:
  """The weights at `path`, or `fit()`'s (a training run) saved there first."""
  path = pathlib.Path(path)
  if path.exists():
    return weights.load_params(path)
  print(f"[study] {path} is missing: training {what}", flush=True)
  params = fit()
  if evaluation.writes_results():
    weights.save_params(path, params)
  return params


def trained_tokengs(settings: StudySettings) -> tuple[model.ModelConfig, dict]:
  """The model config and trained weights (training them with the experiment when missing:
  from its checkpoint, else from fresh weights; checkpoints beside `params`)."""
  path = pathlib.Path(settings.params)
  experiment = dataclasses.replace(settings.experiment, output_dir=str(path.parent))
  return settings.experiment.model, saved_or_trained(
    path,
    "the TokenGS model",
    lambda: train(experiment, weights.initial_params(experiment, finetune=False)),
  )


def trained_pixel_baseline(settings: StudySettings) -> dict:
  """The pixel-aligned (GS-LRM-style) baseline's weights (`settings.baseline_params`), trained
  when missing exactly as `run --eval.pixel-baseline` trains it: TokenGS's data, loss, optimiser,
  steps and seed, from the weights beside the experiment's checkpoint where it has one."""
  experiment = dataclasses.replace(
    settings.experiment, eval=dataclasses.replace(settings.experiment.eval, pixel_baseline=True)
  )
  path = pathlib.Path(
    settings.baseline_params or pathlib.Path(settings.output_dir) / "pixel_baseline.msgpack"
  )
  (baseline,) = tasks.Task().trained_baselines(experiment)
  experiment = dataclasses.replace(experiment, output_dir=str(path.with_suffix("")))
  return saved_or_trained(
    path,
    "the pixel-aligned baseline the same way",
    lambda: train(
      experiment, baseline.init_params(jax.random.key(experiment.seed)), baseline.loss_fn
    ),
  )


def psnr_of(
  method: evaluation.Method, scenes: Sequence[evaluation.Scene], scorer: evaluation.Scorer
) -> tuple[list[float], float]:
  """Per-scene PSNR of a method and its mean seconds per scene of reconstruction (+ tuning),
  compilation excluded: the first scene is evaluated once before the timed pass."""
  evaluation.evaluate(scenes[:1], {"method": method}, scorer)
  scores = evaluation.evaluate(scenes, {"method": method}, scorer).scores["method"]
  return [s["psnr"] for s in scores.per_scene], float(np.mean(scores.predict_seconds))


def scene_gaussians(method: evaluation.Method, batch: dict) -> tuple[np.ndarray, np.ndarray]:
  """(centres [N, 3], opacities [N]) of a method's Gaussians for a batch of one (the first set
  where colours depend on the viewer: the centres and opacities are every set's)."""
  gaussians = jax.device_get(method.gaussians(batch))
  means = np.asarray(gaussians.means)
  return means.reshape(-1, *means.shape[-2:])[0], np.asarray(gaussians.opacities).reshape(
    -1, means.shape[-2]
  )[0]


def in_views(
  means: np.ndarray, c2w: np.ndarray, intrinsics: np.ndarray, height: int, width: int, near: float
) -> tuple[np.ndarray, np.ndarray]:
  """(inside [V, N]: centre in front of view v (depth > near) and projected into its image;
  depth [V, N] in that view) of centres [N, 3] in cameras c2w [V, 4, 4], intrinsics [V, 4]."""
  uv, depth = camera.project_points(
    jnp.asarray(means), camera.invert_rigid(jnp.asarray(c2w)), jnp.asarray(intrinsics)
  )
  uv, depth = np.asarray(uv), np.asarray(depth)
  inside = (
    (depth > near)
    & (uv[..., 0] >= 0)
    & (uv[..., 0] < width)
    & (uv[..., 1] >= 0)
    & (uv[..., 1] < height)
  )
  return inside, depth


def write_table(
  out_dir,
  name: str,
  title: str,
  rows: list[dict],
  columns: Sequence[str],
  notes: Sequence[str] = (),
) -> pathlib.Path:
  """`<name>.json` (rows + notes) and `<name>.md` (a table) in `out_dir` (process 0 only)."""
  out_dir = pathlib.Path(out_dir)
  lines = [f"# {title}\n", markdown_table(rows, columns, float_format=".4g")]
  lines += [f"- {n}" for n in notes]
  path = out_dir / f"{name}.md"
  print("\n".join(lines), flush=True)
  if evaluation.writes_results():
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / f"{name}.json").write_text(
      json.dumps({"title": title, "rows": rows, "notes": list(notes)}, indent=1)
    )
    path.write_text("\n".join(lines) + "\n")
  return path
