"""PSNR vs number of Gaussian tokens, and run time vs PSNR across tokens x tuning steps.

Two ways to get a model per token count:
- default: the trained model's token table resampled to K rows (`train.transplant_params`:
  evenly spaced rows when shrinking, noisy cyclic copies when growing; the paper's finetuning
  initialisation), no retraining: what the learnt decoder does with more or fewer queries;
- `--retrain`: one model trained per K with the experiment's settings (the paper's protocol;
  K times the training cost).

Run time is the measured seconds per scene of reconstruction (+ tuning), compilation excluded.

    python -m experiments.studies.token_count [--tokens 32 64 128 256 512] [--retrain]

Writes `token_count.{json,md}`, `psnr_vs_tokens.png`, `runtime_vs_psnr.png` to
`<output_dir>/token_count/`.
"""

from __future__ import annotations

import dataclasses
import pathlib
from collections.abc import Sequence

import jax
import numpy as np
import tyro

from experiments import data
from experiments.studies import (
  StudySettings,
  psnr_of,
  report,
  saved_or_trained,
  train,
  trained_tokengs,
  write_table,
)
from tokengs_jax import evaluation, model, process
from tokengs_jax.tuning import TuningConfig


CLAIM = (
  "Paper: more Gaussian tokens reconstruct better. Compared: one model trained per token count "
  "(same data, steps, seeds), feed-forward PSNR of the most tokens vs the fewest."
)


@dataclasses.dataclass(frozen=True)
class TokenCount(StudySettings):
  tokens: tuple[int, ...] = (32, 64, 128, 256, 512)
  tuning_steps: tuple[int, ...] = (0, 25)
  retrain: bool = False


def model_for(settings: TokenCount, config, params, count: int, out: pathlib.Path):
  """(config, params) of a K-token model (resampled or retrained; retrained at the trained
  model's own count: that model, trained with the same settings and seed)."""
  config_k = config.replace(num_gs_tokens=count)
  fresh = model.init_params(jax.random.key(settings.experiment.seed), config_k)
  if not settings.retrain:
    from tokengs_jax.train import transplant_params

    return config_k, transplant_params(jax.random.key(count), params, fresh)[0]
  if count == config.num_gs_tokens:
    return config_k, params
  experiment = dataclasses.replace(
    settings.experiment, model=config_k, output_dir=str(out / f"tokens_{count}")
  )
  return config_k, saved_or_trained(
    out / f"tokens_{count}.msgpack", f"the {count}-token model", lambda: train(experiment, fresh)
  )


def by_tuning_steps(rows: list[dict], x: str) -> dict[str, tuple[list, list]]:
  """Chart series, one per tuning step count: (the rows' `x`, their PSNR)."""
  steps = dict.fromkeys(row["tuning_steps"] for row in rows)
  return {
    f"{s} tuning steps": report.series([r for r in rows if r["tuning_steps"] == s], x, ["psnr"])[
      "psnr"
    ]
    for s in steps
  }


def psnr_plot(rows: list[dict]) -> report.Plot:
  """`psnr_vs_tokens.png`: PSNR vs tokens, a line per tuning step count."""
  return report.Plot(
    "psnr_vs_tokens",
    "PSNR vs Gaussian tokens",
    by_tuning_steps(rows, "tokens"),
    "Gaussian tokens",
    log_x=True,
  )


def main(settings: TokenCount) -> list[dict]:
  out = pathlib.Path(settings.output_dir) / "token_count"
  config, params = trained_tokengs(settings)
  examples = data.evaluation_scenes(settings.experiment)
  scorer = evaluation.Scorer(lpips=False)
  lr = settings.experiment.eval.tuning_learning_rate
  rows = []
  for count in settings.tokens:
    config_k, params_k = model_for(settings, config, params, count, out)
    for steps in settings.tuning_steps:
      method = (
        evaluation.feed_forward(params_k, config_k)
        if steps == 0
        else evaluation.tuned(params_k, config_k, TuningConfig(steps=steps, learning_rate=lr))
      )
      scores, seconds = psnr_of(method, examples, scorer)
      rows.append(
        {
          "tokens": count,
          "gaussians": config_k.num_gaussians,
          "tuning_steps": steps,
          "psnr": float(np.mean(scores)),
          "seconds_per_scene": seconds,
        }
      )
  how = (
    f"one model trained {settings.experiment.train.steps} steps per count"
    if settings.retrain
    else f"the {config.num_gs_tokens}-token table resampled (no retraining)"
  )
  write_table(
    out,
    "token_count",
    "PSNR (dB) and run time vs Gaussian tokens",
    rows,
    ["tokens", "gaussians", "tuning_steps", "psnr", "seconds_per_scene"],
    notes=[
      (f"{len(examples)} held-out scenes; models: {how}; run time on {jax.devices()[0].platform}.")
    ],
  )
  psnr_plot(rows).draw(out)
  report.Plot(
    "runtime_vs_psnr",
    "Run time vs PSNR",
    by_tuning_steps(rows, "seconds_per_scene"),
    "seconds per scene",
  ).draw(out)
  return rows


def claim(per_seed: Sequence[list[dict]]) -> report.Claim:
  """(e): with models retrained per count, the most tokens beat the fewest (feed-forward)."""
  rows = report.aggregate(
    [[r for r in seed_rows if r["tuning_steps"] == 0] for seed_rows in per_seed],
    ["tokens", "gaussians", "tuning_steps"],
    ["psnr", "seconds_per_scene"],
    digits=3,
  )
  fewest, most = (f(rows, key=lambda row: row["tokens"]) for f in (min, max))
  evidence = (
    f"{most['tokens']} tokens: {most['psnr']} dB vs {fewest['tokens']} tokens: {fewest['psnr']} "
    f"dB; difference {report.difference(most['psnr_seeds'], fewest['psnr_seeds'], 3)} dB."
  )
  verdict = report.verdict(most["psnr_seeds"], fewest["psnr_seeds"])
  columns = ["tokens", "gaussians", "psnr", "seconds_per_scene"]
  return report.Claim(
    "e", "Token count", CLAIM, rows, columns, verdict, evidence, psnr_plot(report.means(rows))
  )


if __name__ == "__main__":
  process.setup()
  main(tyro.cli(TokenCount))
