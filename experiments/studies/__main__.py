"""`python -m experiments.studies all`: every claim of the paper re-run with seeds, one report.

    python -m experiments.studies all                  # the full run -> docs/studies.md
    python -m experiments.studies all --quick          # smoke test: small, 2 seeds, <= 10 min
    python -m experiments.studies all --seeds 5 --output-dir /tmp/report

Per seed s, a synthetic set of the RE10K default's family (`<work_dir>/data/seed<s>`: the seed
draws the scenes, the initialisation and the data order) and every model the claims need, each
trained from scratch with one recipe (the `pretrain` preset's optimiser at `Scale.steps`):
TokenGS (the default model), the pixel-aligned baseline (trained exactly as TokenGS, colours
from the input views as TokenGS's), TokenGS with 2-4 input views, TokenGS without the visibility
loss and TokenGS per token count. Each study then runs on that seed's models, and each claim's
section of the report aggregates the seeds (`report`). Weights stay in the work folder, so a
rerun at the same scale only evaluates; a work folder of another scale is refused.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import time

import jax
import tyro

from experiments import data, re10k, weights
from experiments.studies import (
  camera_noise,
  context_extension,
  distribution,
  report,
  test_time_scaling,
  token_count,
  view_extrapolation,
  visibility,
)
from tokengs_jax import process

# The claims' studies, in the report's order (a)-(g); each has `main(settings)` and `claim`.
STUDIES = (
  camera_noise,
  view_extrapolation,
  context_extension,
  test_time_scaling,
  token_count,
  visibility,
  distribution,
)


@dataclasses.dataclass(frozen=True)
class Scale:
  """How big a run is: seeds, training, data and each study's sweep."""

  seeds: int
  steps: int  # training steps of every model
  train_scenes: int
  test_scenes: int
  angles: tuple[float, ...]  # camera noise (degrees)
  offsets: tuple[int, ...]  # extrapolation (frames outside the span)
  # tuning steps of both targets: a Gaussian step is cheaper, so equal time reads its longer runs
  tuning_steps: tuple[int, ...]
  tokens: tuple[int, ...]  # token counts, one model each (the default's 128 among them)
  bins: int  # depth bins of the distribution


FULL = Scale(
  3, 1500, 240, 8, (0.0, 1.0, 2.0, 5.0, 10.0), (1, 2, 4), (10, 25, 50, 100), (32, 128, 512), 8
)
QUICK = Scale(2, 40, 12, 3, (0.0, 5.0), (2,), (5, 20), (64, 128), 4)


@dataclasses.dataclass(frozen=True)
class All:
  """Runs every study of issue 25's claims (a)-(g) with seeds and writes the report.

  Attributes:
    quick: the smoke-test scale (`QUICK`: its verdicts are not findings) instead of `FULL`.
    seeds: seeds 0..N-1 (default: the scale's).
    steps: training steps of every model (default: the scale's).
    output_dir: the report is `<output_dir>/studies.md`, its plots `<output_dir>/studies/*.png`.
    work_dir: data, weights and the per-seed tables (default `outputs/studies/all`, or
      `all_quick`).
  """

  quick: bool = False
  seeds: int | None = None
  steps: int | None = None
  output_dir: str = "docs"
  work_dir: str | None = None

  def scale(self) -> Scale:
    scale = QUICK if self.quick else FULL
    return dataclasses.replace(
      scale,
      seeds=scale.seeds if self.seeds is None else self.seeds,
      steps=scale.steps if self.steps is None else self.steps,
    )

  def work(self) -> pathlib.Path:
    default = "outputs/studies/all_quick" if self.quick else "outputs/studies/all"
    return pathlib.Path(self.work_dir or default)


def seed_experiment(scale: Scale, seed: int, work: pathlib.Path):
  """The RE10K default (`synthetic-tiny`: model, data family, evaluation) trained from scratch
  with the `pretrain` preset's optimiser for `scale.steps`, on this seed's data."""
  base, pretrain = re10k.PRESETS["synthetic-tiny"], re10k.PRESETS["pretrain"]
  return dataclasses.replace(
    base,
    checkpoint=None,
    seed=seed,
    synthetic_dir=str(work / "data" / f"seed{seed}"),
    output_dir=str(work / f"seed{seed}"),
    synthetic=dataclasses.replace(
      base.synthetic, num_train=scale.train_scenes, num_test=scale.test_scenes, num_ood=0
    ),
    train=dataclasses.replace(
      pretrain.train,
      steps=scale.steps,
      warmup_steps=min(pretrain.train.warmup_steps, scale.steps // 10),
      checkpoint_every=0,
      log_every=max(1, scale.steps // 10),
    ),
    eval=dataclasses.replace(base.eval, num_scenes=scale.test_scenes, lpips=False),
  )


def study_settings(scale: Scale, experiment) -> dict:
  """Study module -> its settings for one seed's experiment (weights in its output folder)."""
  root = pathlib.Path(experiment.output_dir)
  common = {
    "experiment": experiment,
    "params": str(root / "tokengs.msgpack"),
    "baseline_params": str(root / "pixel_aligned.msgpack"),
    "output_dir": str(root),
  }
  return {
    camera_noise: camera_noise.CameraNoise(**common, angles=scale.angles),
    view_extrapolation: view_extrapolation.ViewExtrapolation(
      **common, offsets=scale.offsets, with_tuning=False
    ),
    context_extension: context_extension.ContextExtension(**common),
    test_time_scaling: test_time_scaling.TestTimeScaling(
      **common, views=(2,), steps=scale.tuning_steps, targets=("tokens", "gaussians")
    ),
    token_count: token_count.TokenCount(
      **common, tokens=scale.tokens, tuning_steps=(0,), retrain=True
    ),
    visibility: visibility.Visibility(**common),
    distribution: distribution.Distribution(**common, bins=scale.bins),
  }


def check_work_dir(work: pathlib.Path, scale: Scale) -> None:
  """Records the scale in `<work>/scale.json`; refuses a folder holding another scale's models."""
  stamp, wanted = work / "scale.json", json.loads(json.dumps(dataclasses.asdict(scale)))
  if stamp.exists() and json.loads(stamp.read_text()) != wanted:
    raise SystemExit(
      f"{work} holds the models of another scale ({stamp.read_text().strip()}): delete it or "
      "pass another --work-dir"
    )
  work.mkdir(parents=True, exist_ok=True)
  stamp.write_text(json.dumps(wanted, indent=1))


def header(settings: All, scale: Scale, seconds: float) -> list[str]:
  command = "python -m experiments.studies all" + (" --quick" if settings.quick else "")
  model = re10k.PRESETS["synthetic-tiny"].model
  return [
    f"Written by `{command}` (seeds {scale.seeds}, {scale.steps} training steps) at commit "
    f"`{weights.source_commit()}`: **wall time {seconds / 60:.1f} min** on "
    f"{jax.devices()[0].platform} ({os.cpu_count()} cores visible).",
    "",
    f"Setting: the RE10K default (`python -m experiments.re10k`, preset `synthetic-tiny`): "
    f"model `tiny`, {model.num_gs_tokens} tokens x {model.gaussians_per_token} Gaussians, "
    f"{model.image_size[0]}x{model.image_size[1]}, colours read from the input views; but "
    f"every model trained from scratch per seed ({scale.steps} steps, the `pretrain` preset's "
    f"optimiser: batch 4, lr 3e-3 cosine) on {scale.train_scenes} synthetic scenes of the "
    f"default family, scored on {scale.test_scenes} held-out ones. A seed draws the scenes, "
    "the initialisation and the data order; cells are mean ± sample standard deviation over "
    "seeds.",
    "",
    "The pixel-aligned (GS-LRM-style) baseline is trained exactly as TokenGS (same data, loss, "
    "optimiser, steps and seeds; `Task.trained_baselines`) and reads its colours from the input "
    'views as TokenGS does (`gaussian_colours="inputs"`); its '
    f"{model.num_input_views} views x {model.image_size[0]}x{model.image_size[1]} pixels give "
    f"{model.num_input_views * model.image_size[0] * model.image_size[1]} Gaussians, TokenGS "
    f"{model.num_gaussians}. Each study runs on its own too "
    "(`python -m experiments.studies.<study>`, `experiments/studies/__init__.py`).",
  ]


def main(settings: All) -> pathlib.Path:
  start = time.perf_counter()
  scale, work = settings.scale(), settings.work()
  check_work_dir(work, scale)
  experiments = [seed_experiment(scale, seed, work) for seed in range(scale.seeds)]
  for experiment in experiments:  # the generator forks: before any JAX computation
    data.ensure_synthetic(experiment)
  per_seed = {study: [] for study in STUDIES}
  for experiment in experiments:
    for study, study_setting in study_settings(scale, experiment).items():
      print(f"[studies] seed {experiment.seed}: {study.__name__}", flush=True)
      per_seed[study].append(study.main(study_setting))
  out = pathlib.Path(settings.output_dir)
  claims = [study.claim(per_seed[study]) for study in STUDIES]
  (work / "per_seed.json").write_text(
    json.dumps({study.__name__: rows for study, rows in per_seed.items()}, indent=1)
  )
  path = report.write_report(
    out / "studies.md", claims, header(settings, scale, time.perf_counter() - start), settings.quick
  )
  print(f"[studies] wrote {path} in {(time.perf_counter() - start) / 60:.1f} min", flush=True)
  return path


if __name__ == "__main__":
  process.setup()
  main(tyro.extras.subcommand_cli_from_dict({"all": All}, prog="python -m experiments.studies"))
