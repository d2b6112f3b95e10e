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

import jax
import numpy as np
import tyro

from experiments import data, figures, weights
from experiments.studies import StudySettings, psnr_of, train, trained_tokengs, write_table
from tokengs_jax import evaluation, model, process
from tokengs_jax.tuning import TuningConfig


@dataclasses.dataclass(frozen=True)
class TokenCount(StudySettings):
  tokens: tuple[int, ...] = (32, 64, 128, 256, 512)
  tuning_steps: tuple[int, ...] = (0, 25)
  retrain: bool = False


def model_for(settings: TokenCount, config, params, count: int, out: pathlib.Path):
  """(config, params) of a K-token model (resampled or retrained)."""
  config_k = config.replace(num_gs_tokens=count)
  fresh = model.init_params(jax.random.key(settings.experiment.seed), config_k)
  if not settings.retrain:
    from tokengs_jax.train import transplant_params

    return config_k, transplant_params(jax.random.key(count), params, fresh)[0]
  path = out / f"tokens_{count}.msgpack"
  if path.exists():
    return config_k, weights.load_params(path)
  experiment = dataclasses.replace(
    settings.experiment, model=config_k, output_dir=str(out / f"tokens_{count}")
  )
  trained = train(experiment, fresh)
  weights.save_params(path, trained)
  return config_k, trained


def main(settings: TokenCount) -> list[dict]:
  out = pathlib.Path(settings.output_dir) / "token_count"
  config, params = trained_tokengs(settings)
  examples = data.evaluation_scenes(settings.experiment)
  scorer = evaluation.Scorer(lpips=False)
  lr = settings.experiment.eval.tuning_learning_rate
  rows = []
  psnr_curves = {f"{s} tuning steps": ([], []) for s in settings.tuning_steps}
  runtime_curves = {f"{s} tuning steps": ([], []) for s in settings.tuning_steps}
  for count in settings.tokens:
    config_k, params_k = model_for(settings, config, params, count, out)
    for steps in settings.tuning_steps:
      method = (
        evaluation.feed_forward(params_k, config_k)
        if steps == 0
        else evaluation.tuned(params_k, config_k, TuningConfig(steps=steps, learning_rate=lr))
      )
      scores, seconds = psnr_of(method, examples, scorer)
      psnr = float(np.mean(scores))
      rows.append(
        {
          "tokens": count,
          "gaussians": config_k.num_gaussians,
          "tuning_steps": steps,
          "psnr": psnr,
          "seconds_per_scene": seconds,
        }
      )
      name = f"{steps} tuning steps"
      psnr_curves[name][0].append(count)
      psnr_curves[name][1].append(psnr)
      runtime_curves[name][0].append(seconds)
      runtime_curves[name][1].append(psnr)
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
  figures.line_plot(
    out / "psnr_vs_tokens.png",
    psnr_curves,
    title="PSNR vs Gaussian tokens",
    xlabel="Gaussian tokens",
    ylabel="PSNR (dB)",
    log_x=True,
  )
  figures.line_plot(
    out / "runtime_vs_psnr.png",
    runtime_curves,
    title="Run time vs PSNR",
    xlabel="seconds per scene",
    ylabel="PSNR (dB)",
  )
  return rows


if __name__ == "__main__":
  process.setup()
  main(tyro.cli(TokenCount))
