"""Visibility loss ablation: TokenGS trained with the visibility term (`LossConfig.lambda_vis`,
1 by default) and without it (0), everything else the same.

Scored on the held-out scenes: PSNR, and the share of Gaussians whose centre lies outside every
input view (behind it, or projected outside its image): the Gaussians no input saw, which the
loss pulls back into the views (the paper: fewer such Gaussians, no loss of quality).

    python -m experiments.studies.visibility

Writes `visibility.{json,md}` and `visibility.png` (PSNR vs share outside, a point per model) to
`<output_dir>/visibility/`.
"""

from __future__ import annotations

import dataclasses
import pathlib
from collections.abc import Sequence

import numpy as np
import tyro

from experiments import data, tasks, weights
from experiments.studies import (
  StudySettings,
  in_views,
  psnr_of,
  report,
  saved_or_trained,
  scene_gaussians,
  train,
  trained_tokengs,
  write_table,
)
from tokengs_jax import evaluation, process
from tokengs_jax.objective import tokengs_loss_fn

ON, OFF = "on", "off"
TITLE = "Visibility loss"
COLUMNS = ["visibility loss", "psnr", "outside_share"]  # outside_share: outside every input view
CLAIM = (
  "Paper: the visibility loss leaves fewer Gaussians outside every view, at no cost in quality. "
  "Compared: TokenGS trained with and without it (same data, steps, seeds): the share of "
  "Gaussians whose centre lies outside every input view, and PSNR. Holds where the share drops "
  "beyond the spread and PSNR does not drop beyond it."
)


@dataclasses.dataclass(frozen=True)
class Visibility(StudySettings):
  ablation_params: str | None = None  # default <output_dir>/visibility/no_visibility_loss.msgpack


def outside_share(method: evaluation.Method, scenes, near: float) -> float:
  """Mean over scenes of the share of the method's Gaussians outside every input view."""
  shares = []
  for _, batch in scenes:
    means, _ = scene_gaussians(method, batch)
    height, width = batch["context_images"].shape[-3:-1]
    inside, _ = in_views(
      means, batch["context_c2w"][0], batch["context_intrinsics"][0], height, width, near
    )
    shares.append(float(np.mean(~inside.any(axis=0))))
  return float(np.mean(shares))


def without_visibility_loss(settings: Visibility) -> dict:
  """TokenGS trained as `trained_tokengs` trains it, with `lambda_vis = 0`."""
  out = pathlib.Path(settings.output_dir) / "visibility"
  experiment = dataclasses.replace(settings.experiment, output_dir=str(out / "no_visibility_loss"))
  task = tasks.Task()
  loss_fn = tokengs_loss_fn(
    experiment.model,
    dataclasses.replace(task.loss_config(experiment), lambda_vis=0.0),
    objective=task.objective(experiment),
    lpips_params=task.lpips_params(experiment),
  )
  return saved_or_trained(
    settings.ablation_params or out / "no_visibility_loss.msgpack",
    "TokenGS without the visibility loss",
    lambda: train(experiment, weights.initial_params(experiment, finetune=False), loss_fn),
  )


def plot(rows: list[dict]) -> report.Plot:
  """PSNR vs the share outside every input view, a point per row (per model, per seed)."""
  points = {}
  for row in rows:
    xs, ys = points.setdefault(f"visibility loss {row['visibility loss']}", ([], []))
    xs.append(row["outside_share"])
    ys.append(row["psnr"])
  return report.Plot(
    "visibility", TITLE, points, "share of Gaussians outside every input view", scatter=True
  )


def main(settings: Visibility) -> list[dict]:
  out = pathlib.Path(settings.output_dir) / "visibility"
  config, params = trained_tokengs(settings)
  models = {ON: params, OFF: without_visibility_loss(settings)}
  scenes = data.evaluation_scenes(settings.experiment)
  scorer = evaluation.Scorer(lpips=False)
  near = settings.experiment.train.loss_config().near
  rows = []
  for name, trained in models.items():
    method = evaluation.feed_forward(trained, config)
    scores, _ = psnr_of(method, scenes, scorer)
    rows.append(
      {
        "visibility loss": name,
        "psnr": float(np.mean(scores)),
        "outside_share": outside_share(method, scenes, near),
      }
    )
  steps = settings.experiment.train.steps
  note = f"{len(scenes)} held-out scenes; both trained {steps} steps, the same but for lambda_vis."
  write_table(out, "visibility", f"{TITLE} on vs off", rows, COLUMNS, notes=[note])
  plot(rows).draw(out)
  return rows


def claim(per_seed: Sequence[list[dict]]) -> report.Claim:
  """(f): with the loss, fewer Gaussians outside every view, and no PSNR loss."""
  rows = report.aggregate(per_seed, ["visibility loss"], ["psnr", "outside_share"], digits=3)
  on, off = (next(r for r in rows if r["visibility loss"] == name) for name in (ON, OFF))
  fewer = report.verdict(on["outside_share_seeds"], off["outside_share_seeds"], False)
  kept = report.no_worse(on["psnr_seeds"], off["psnr_seeds"])
  share = report.difference(on["outside_share_seeds"], off["outside_share_seeds"], 3)
  evidence = (
    f"outside share {on['outside_share']} (on) vs {off['outside_share']} (off), difference "
    f"{share}: {fewer}; PSNR {on['psnr']} vs {off['psnr']} dB, difference "
    f"{report.difference(on['psnr_seeds'], off['psnr_seeds'], 3)} dB: no loss {kept}."
  )
  figure = plot([row for seed_rows in per_seed for row in seed_rows])  # a point per seed
  verdict = report.all_of([fewer, kept])
  return report.Claim("f", TITLE, CLAIM, rows, COLUMNS, verdict, evidence, figure)


if __name__ == "__main__":
  process.setup()
  main(tyro.cli(Visibility))
