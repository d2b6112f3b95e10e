"""Test-time scaling: PSNR vs number of input views (context extension) and vs tuning steps, for
token tuning, Gaussian tuning and joint tuning.

Every point uses the same targets: the evenly spaced frames of the evaluation span. Context
extension keeps the span's two end frames and adds evenly spaced frames between them; the
Gaussian count does not change. The tuning curves start from the 2-view reconstruction.

    python -m experiments.studies.test_time_scaling [--views 2 3 4 6] [--steps 10 25 50]

Writes `test_time_scaling.{json,md}`, `views.png` and `tuning_steps.png` to
`<output_dir>/test_time_scaling/`. Each (target, steps) pair compiles its own tuning program.
"""

from __future__ import annotations

import dataclasses
import pathlib
from collections.abc import Sequence

import numpy as np
import tyro

from experiments import data
from experiments.config import Experiment
from experiments.studies import StudySettings, psnr_of, report, trained_tokengs, write_table
from tokengs_jax import evaluation, process
from tokengs_jax.tuning import TuningConfig


VIEWS, UNTUNED = "input views", "no tuning (2 views)"  # the axes of the rows without tuning
TITLE = "Token tuning vs Gaussian tuning"
CLAIM = (
  "Paper: tuning the Gaussian tokens on the input views beats tuning the Gaussians themselves, at "
  "equal steps and at equal wall time. Compared: PSNR after the most steps run; and at equal "
  "time, token tuning at the most steps whose seconds per scene the Gaussian curve reaches "
  "against that curve read there (linearly between its points, from the untuned one)."
)


@dataclasses.dataclass(frozen=True)
class TestTimeScaling(StudySettings):
  views: tuple[int, ...] = (2, 3, 4, 6)
  steps: tuple[int, ...] = (10, 25, 50)
  targets: tuple[str, ...] = ("tokens", "gaussians", "tokens+gaussians")
  learning_rate: float = 1e-4  # token rate (paper); Gaussian offsets use the library default


def context_frames(num_context: int, gap: int) -> np.ndarray:
  """`num_context` input frames evenly over [0, gap] (both ends kept)."""
  return np.linspace(0, gap, num_context).round().astype(np.int64)


def shared_targets(view_counts: tuple[int, ...], gap: int, num_targets: int) -> np.ndarray:
  """`num_targets` frames strictly inside [0, gap] that no context size in `view_counts` uses as
  an input, as evenly spread as the free frames allow: every point of the views curve scores the
  same novel views."""
  used = set(np.concatenate([context_frames(count, gap) for count in view_counts]).tolist())
  free = np.array([f for f in range(1, gap) if f not in used], np.int64)
  if len(free) < num_targets:
    raise ValueError(
      f"a context gap of {gap} frames leaves {len(free)} frames that are not inputs "
      f"for {view_counts} views; {num_targets} targets need a larger gap"
    )
  return free[np.linspace(0, len(free) - 1, num_targets).round().astype(np.int64)]


def spaced_views(num_context: int, gap: int, targets: np.ndarray):
  """(record, position) -> (context, target): `context_frames` and the given target frames."""

  def views(record, position):
    return context_frames(num_context, gap), targets

  return views


def _row(axis: str, value: int, scores: list[float], seconds: float) -> dict:
  return {
    "axis": axis,
    "value": value,
    "psnr": float(np.mean(scores)),
    "seconds_per_scene": seconds,
  }


def _curve(rows: list[dict]) -> tuple[list, list]:
  """(values, PSNRs) of table rows, for a line plot."""
  return [row["value"] for row in rows], [row["psnr"] for row in rows]


def context_extension_rows(
  experiment: Experiment,
  view_counts: Sequence[int],
  method,
  scorer: evaluation.Scorer,
  targets: np.ndarray,
) -> list[dict]:
  """One row per context size in `view_counts`: the method scored on the same `targets`."""
  gap = experiment.eval.context_gap
  rows = []
  for count in view_counts:
    examples = data.evaluation_scenes(
      experiment.with_views(count), views=spaced_views(count, gap, targets)
    )
    rows.append(_row(VIEWS, count, *psnr_of(method, examples, scorer)))
  return rows


def tuning_rows(
  settings: TestTimeScaling, params, config, examples, scorer: evaluation.Scorer
) -> dict[str, list[dict]]:
  """Tuning target -> one row per step count in `settings.steps` (each its own compilation)."""
  by_target = {}
  for target in settings.targets:
    by_target[target] = []
    for steps in settings.steps:
      tuning = TuningConfig(target=target, steps=steps, learning_rate=settings.learning_rate)
      method = evaluation.tuned(params, config, tuning)
      by_target[target].append(
        _row(f"{target} tuning steps", steps, *psnr_of(method, examples, scorer))
      )
  return by_target


def views_plot(rows: list[dict]) -> report.Plot:
  """`views.png`: PSNR vs input views."""
  return report.Plot(
    "views",
    "Context extension",
    {"TokenGS (feed-forward)": _curve([r for r in rows if r["axis"] == VIEWS])},
    "input views",
  )


def tuning_plot(rows: list[dict], targets: Sequence[str]) -> report.Plot:
  """`tuning_steps.png`: each target's curve, from the untuned 2-view score at step 0."""
  start = [r for r in rows if r["axis"] == UNTUNED]
  return report.Plot(
    "tuning_steps",
    "Test-time tuning",
    {t: _curve(start + [r for r in rows if r["axis"] == f"{t} tuning steps"]) for t in targets},
    "tuning steps",
    dashed=("gaussians",),
  )


def main(settings: TestTimeScaling) -> list[dict]:
  out = pathlib.Path(settings.output_dir) / "test_time_scaling"
  config, params = trained_tokengs(settings)
  e = settings.experiment.eval
  scorer = evaluation.Scorer(lpips=False)
  feed_forward = evaluation.feed_forward(params, config)
  targets = shared_targets(settings.views, e.context_gap, e.num_target_views)
  view_rows = context_extension_rows(
    settings.experiment, settings.views, feed_forward, scorer, targets
  )
  examples = data.evaluation_scenes(
    settings.experiment, views=spaced_views(2, e.context_gap, targets)
  )
  base = _row(UNTUNED, 0, *psnr_of(feed_forward, examples, scorer))
  by_target = tuning_rows(settings, params, config, examples, scorer)
  rows = [*view_rows, base, *(row for target_rows in by_target.values() for row in target_rows)]
  write_table(
    out,
    "test_time_scaling",
    "Test-time scaling (PSNR dB, seconds per scene)",
    rows,
    ["axis", "value", "psnr", "seconds_per_scene"],
    notes=[
      (
        f"{len(examples)} held-out scenes, span {e.context_gap} frames, "
        f"targets at frames {targets.tolist()} (inputs at no view count); token lr "
        f"{settings.learning_rate}."
      )
    ],
  )
  views_plot(rows).draw(out)
  tuning_plot(rows, settings.targets).draw(out)
  return rows


TOKENS, GAUSSIANS = "tokens tuning steps", "gaussians tuning steps"  # the claim's axes


def psnr_at_time(rows: Sequence[dict], seconds: float) -> float:
  """A tuning curve's PSNR at `seconds` per scene: linear between its points (rows with
  "seconds_per_scene" and "psnr"); NaN beyond its longest point (not measured)."""
  ordered = sorted(rows, key=lambda row: row["seconds_per_scene"])
  times = [r["seconds_per_scene"] for r in ordered]
  if seconds > times[-1]:
    return float("nan")
  return float(np.interp(seconds, times, [r["psnr"] for r in ordered]))


def equal_time(rows: Sequence[dict]) -> tuple[float, float]:
  """One seed's (token tuning's PSNR, Gaussian tuning's at the same seconds per scene): token
  tuning at the most steps whose time the Gaussian curve (from the untuned point) reaches, and
  that curve read there; NaNs where no token run is that short."""
  curve = [r for r in rows if r["axis"] in (UNTUNED, GAUSSIANS)]
  reach = max(r["seconds_per_scene"] for r in curve)
  runs = [r for r in rows if r["axis"] == TOKENS and r["seconds_per_scene"] <= reach]
  if not runs:
    return float("nan"), float("nan")
  run = max(runs, key=lambda r: r["value"])
  return run["psnr"], psnr_at_time(curve, run["seconds_per_scene"])


def claim(per_seed: Sequence[list[dict]]) -> report.Claim:
  """(d): token tuning beats Gaussian tuning at equal steps (the most steps run) and at equal
  wall time (`equal_time`)."""
  rows = report.aggregate(
    [[r for r in seed_rows if r["axis"] != VIEWS] for seed_rows in per_seed],
    ["axis", "value"],
    ["psnr", "seconds_per_scene"],
    digits=3,
  )
  last = {
    axis: max((r for r in rows if r["axis"] == axis), key=lambda r: r["value"])
    for axis in (TOKENS, GAUSSIANS)
  }
  tuned, timed = np.array([equal_time(seed_rows) for seed_rows in per_seed]).T
  steps = report.verdict(last[TOKENS]["psnr_seeds"], last[GAUSSIANS]["psnr_seeds"])
  time = report.verdict(tuned, timed)
  evidence = (
    f"{last[TOKENS]['value']} steps: {last[TOKENS]['psnr']} dB (tokens) vs "
    f"{last[GAUSSIANS]['psnr']} dB (Gaussians), difference "
    f"{report.difference(last[TOKENS]['psnr_seeds'], last[GAUSSIANS]['psnr_seeds'], 3)} dB: "
    f"{steps}; at equal time, {report.mean_std(tuned, 3)} dB (tokens) vs "
    f"{report.mean_std(timed, 3)} dB (Gaussians), difference "
    f"{report.difference(tuned, timed, 3)} dB: {time}."
  )
  figure = tuning_plot(report.means(rows), ("tokens", "gaussians"))
  columns = ["axis", "value", "psnr", "seconds_per_scene"]
  verdict = report.all_of([steps, time])
  return report.Claim("d", TITLE, CLAIM, rows, columns, verdict, evidence, figure)


if __name__ == "__main__":
  process.setup()
  main(tyro.cli(TestTimeScaling))
