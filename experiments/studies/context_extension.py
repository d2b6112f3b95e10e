"""Context extension: a model trained with a variable number of input views (2-4, as the paper's
RE10K training), scored with 2, 3 and 4 views on the same targets, beside the model trained with
2 views only.

The library loop compiles one step for the first batch's shapes, so the variable-view model is
trained by `train_variable_views`: the same jitted step (`make_train_step`), loss, optimiser and
schedule (`config.optim_config`), data and seed, with the number of input views drawn uniformly
per step (one compiled program per count; no checkpoints). Targets and views as
`test_time_scaling`'s context extension (`shared_targets`, `spaced_views`).

    python -m experiments.studies.context_extension [--views 2 3 4] [--train-views 2 3 4]

Writes `context_extension.{json,md,png}` to `<output_dir>/context_extension/`.
"""

from __future__ import annotations

import dataclasses
import pathlib
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
import tyro
from jax.sharding import NamedSharding, PartitionSpec

from experiments import tasks, weights
from experiments.config import Experiment, optim_config
from experiments.studies import (
  StudySettings,
  report,
  saved_or_trained,
  trained_tokengs,
  write_table,
)
from experiments.studies.test_time_scaling import context_extension_rows, shared_targets
from tokengs_jax import evaluation, process
from tokengs_jax.train import create_train_state, make_mesh, make_optimizer, make_train_step
from tokengs_jax.train import replicate, shard_batch


TITLE = "Context extension"
CLAIM = (
  "Paper: a model trained with a variable number of views (2-4) improves with more test views."
)


@dataclasses.dataclass(frozen=True)
class ContextExtension(StudySettings):
  views: tuple[int, ...] = (2, 3, 4)  # input views at test time
  train_views: tuple[int, ...] = (2, 3, 4)  # drawn uniformly at each training step
  variable_params: str | None = (
    None  # default <output_dir>/context_extension/variable_views.msgpack
  )


def view_schedule(seed: int, steps: int, counts: Sequence[int]) -> np.ndarray:
  """The number of input views of each training step: uniform draws from `counts`, seeded."""
  return np.random.default_rng([seed, 25]).choice(np.asarray(counts), size=steps)


def train_variable_views(experiment: Experiment, params, counts: Sequence[int]) -> dict:
  """Trains `params` as `studies.train` does, each step on a batch of `view_schedule`'s count."""
  task = tasks.Task()
  mesh = make_mesh()
  optimizer = make_optimizer(optim_config(experiment))
  state = jax.jit(
    lambda p: create_train_state(p, optimizer, experiment.seed),
    out_shardings=NamedSharding(mesh, PartitionSpec()),
  )(replicate(jax.device_get(params), mesh))
  step = make_train_step(task.loss_fn(experiment, experiment.model), optimizer, mesh)
  key = jnp.copy(state.rng)
  batches = {n: iter(task.training_batches(experiment.with_views(n))) for n in set(counts)}
  schedule = view_schedule(experiment.seed, experiment.train.steps, counts)
  metrics = {}
  for count in schedule:
    state, metrics = step(state, shard_batch(next(batches[int(count)]), mesh), key)
  if metrics:
    print(f"[study] variable views: final loss {float(metrics['loss']):.4f}", flush=True)
  return jax.device_get(state.params)


def plot(rows: list[dict], models: Sequence[str]) -> report.Plot:
  """PSNR vs input views at test time, a line per model."""
  return report.Plot(
    "context_extension", TITLE, report.series(rows, "views", models), "input views"
  )


def main(settings: ContextExtension) -> list[dict]:
  out = pathlib.Path(settings.output_dir) / "context_extension"
  config, params = trained_tokengs(settings)
  experiment = settings.experiment
  low, high = min(settings.train_views), max(settings.train_views)
  variable = saved_or_trained(
    settings.variable_params or out / "variable_views.msgpack",
    f"the model with {low}-{high} input views",
    lambda: train_variable_views(
      experiment, weights.initial_params(experiment, finetune=False), settings.train_views
    ),
  )
  e = experiment.eval
  targets = shared_targets(settings.views, e.context_gap, e.num_target_views)
  scorer = evaluation.Scorer(lpips=False)
  models = {
    f"trained with {experiment.num_context_views} views": params,
    f"trained with {low}-{high} views": variable,
  }
  scored = {
    name: context_extension_rows(
      experiment, settings.views, evaluation.feed_forward(trained, config), scorer, targets
    )
    for name, trained in models.items()
  }
  rows = [
    {"views": count, **{name: scored[name][i]["psnr"] for name in models}}
    for i, count in enumerate(settings.views)
  ]
  write_table(
    out,
    "context_extension",
    "PSNR (dB) vs input views at test time",
    rows,
    ["views", *models],
    notes=[
      f"{e.num_scenes or 'all'} held-out scenes, span {e.context_gap} frames, targets at "
      f"frames {targets.tolist()} (inputs at no view count); "
      f"{experiment.train.steps} training steps each."
    ],
  )
  plot(rows, list(models)).draw(out)
  return rows


def claim(per_seed: Sequence[list[dict]]) -> report.Claim:
  """(c): the variable-view model's PSNR with the most views beats its PSNR with the fewest."""
  models = [name for name in per_seed[0][0] if name != "views"]
  rows = report.aggregate(per_seed, ["views"], models)
  fewest, most = rows[0], rows[-1]
  variable = models[-1]
  verdict = report.verdict(most[f"{variable}_seeds"], fewest[f"{variable}_seeds"])
  statement = (
    f"{CLAIM} Compared: PSNR with {most['views']} input views vs with {fewest['views']} (the "
    f"same targets) of the model {variable}; the model trained with 2 views for reference."
  )
  gain = report.difference(most[f"{variable}_seeds"], fewest[f"{variable}_seeds"])
  evidence = (
    f"{variable}: {most[variable]} dB with {most['views']} views vs {fewest[variable]} dB "
    f"with {fewest['views']}; difference {gain} dB."
  )
  figure = plot(report.means(rows), models)
  return report.Claim("c", TITLE, statement, rows, ["views", *models], verdict, evidence, figure)


if __name__ == "__main__":
  process.setup()
  main(tyro.cli(ContextExtension))
