"""The paper's studies, one script each; every script writes a table (JSON + Markdown) and a plot.

    python -m experiments.studies.camera_noise         # TokenGS vs pixel-aligned baseline
    python -m experiments.studies.view_extrapolation
    python -m experiments.studies.test_time_scaling    # views, tuning steps, tuning target
    python -m experiments.studies.token_count          # PSNR and run time vs Gaussian tokens
    python -m experiments.studies.token_assignment     # Gaussians coloured by their token

By default each study starts from the synthetic default run's weights
(`outputs/re10k/tiny_synthetic/params.msgpack`, written by `python -m experiments.re10k`) and
trains that model first when they are missing; `--experiment.*` flags change data, model and
training exactly as on the entry point.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
from collections.abc import Sequence

import jax
import numpy as np

from experiments import tasks, training, weights
from experiments.config import Experiment
from experiments.results import markdown_table
from tokengs_jax import evaluation, model


@dataclasses.dataclass(frozen=True)
class StudySettings:
  """Shared by every study.

  Attributes:
    experiment: data / model / training / evaluation settings (the re10k default preset).
    params: trained TokenGS weights; trained with `experiment` (and saved there) when missing.
    output_dir: where the study's table and plot go.
  """

  experiment: Experiment = dataclasses.field(default_factory=Experiment)
  params: str = "outputs/re10k/tiny_synthetic/params.msgpack"
  output_dir: str = "outputs/studies"


def train(experiment: Experiment, params, loss_fn=None) -> dict:
  """Trains with the experiment's settings (default loss: TokenGS's); returns the weights."""
  task = tasks.Task()
  loss_fn = task.loss_fn(experiment, experiment.model) if loss_fn is None else loss_fn
  params, history, seconds = training.train_model(
    experiment, params, loss_fn, iter(task.training_batches(experiment))
  )
  print(f"[study] trained in {seconds:.0f} s, final loss {history[-1]['loss']:.4f}", flush=True)
  return params


def trained_tokengs(settings: StudySettings) -> tuple[model.ModelConfig, dict]:
  """The model config and trained weights (training them with the experiment when missing)."""
  config = settings.experiment.model
  path = pathlib.Path(settings.params)
  if path.exists():
    return config, weights.load_params(path)
  print(f"[study] {path} is missing: training the TokenGS model first", flush=True)
  experiment = dataclasses.replace(settings.experiment, output_dir=str(path.parent))
  params = train(experiment, model.init_params(jax.random.key(experiment.seed), config))
  weights.save_params(path, params)
  return config, params


def psnr_of(
  method: evaluation.Method, scenes: Sequence[evaluation.Scene], scorer: evaluation.Scorer
) -> tuple[list[float], float]:
  """Per-scene PSNR of a method and its mean seconds per scene of reconstruction (+ tuning),
  compilation excluded: the first scene is evaluated once before the timed pass."""
  evaluation.evaluate(scenes[:1], {"method": method}, scorer)
  scores = evaluation.evaluate(scenes, {"method": method}, scorer).scores["method"]
  return [s["psnr"] for s in scores.per_scene], float(np.mean(scores.predict_seconds))


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
