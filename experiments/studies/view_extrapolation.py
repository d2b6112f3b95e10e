"""View extrapolation: PSNR of targets inside the context span and at growing distances outside it.

Each held-out scene gets context frames (s, s + gap), s = `start`, and one target per offset: the
frame `s + gap + offset` (offset > 0: beyond the last input view, extrapolation) or `s + offset`
(offset <= 0 would be before the first one; offsets inside are reported as "inside"). The camera
normalisation is the example's own (first context camera), so every target of a scene is scored
in one reconstruction. The pixel-aligned baseline (`camera_noise`'s) is scored beside TokenGS: its
Gaussians lie on the input pixels' rays, so it cannot cover what no input saw (the paper's "scene
completion beyond input views").

    python -m experiments.studies.view_extrapolation [--offsets 1 2 4 6 8] [--no-with-pixel-baseline]

Writes `view_extrapolation.{json,md,png}` to `<output_dir>/view_extrapolation/`.
"""

from __future__ import annotations

import dataclasses
import pathlib
from collections.abc import Sequence

import numpy as np
import tyro

from experiments import data, pixel_baseline
from experiments.studies import (
  PIXEL_ALIGNED,
  StudySettings,
  report,
  trained_pixel_baseline,
  trained_tokengs,
  write_table,
)
from tokengs_jax import evaluation, process
from tokengs_jax.tuning import TuningConfig


TITLE = "View extrapolation"
METHODS = ("TokenGS", PIXEL_ALIGNED)  # the claim's
CLAIM = (
  "Paper: TokenGS completes the scene beyond the input views, where pixel-aligned Gaussians "
  "cannot reach. Compared: PSNR of targets outside the inputs' span ('+k' after the last input "
  "frame, '-k' before the first), TokenGS vs the pixel-aligned baseline."
)


@dataclasses.dataclass(frozen=True)
class ViewExtrapolation(StudySettings):
  gap: int = 8  # frames between the two input views
  start: int = 2  # first input frame (leaves room for targets before it)
  offsets: tuple[int, ...] = (1, 2, 4, 6, 8)  # frames beyond the span (both ends)
  with_tuning: bool = True  # also score after token tuning (experiment.eval settings)
  with_pixel_baseline: bool = True  # also score the pixel-aligned baseline


def target_frames(settings: ViewExtrapolation, num_frames: int) -> dict[str, int]:
  """Label -> frame: the span's midpoint ("inside") and each offset before / after the span."""
  first, last = settings.start, settings.start + settings.gap
  if last >= num_frames:
    raise ValueError(
      f"inputs at frames {first} and {last} need {last + 1} frames; the scene has "
      f"{num_frames} (lower --start / --gap)"
    )
  frames = {"inside": first + settings.gap // 2}
  for offset in settings.offsets:
    if last + offset < num_frames:
      frames[f"+{offset}"] = last + offset
    if first - offset >= 0:
      frames[f"-{offset}"] = first - offset
  return frames


def by_distance(rows: list[dict], methods: Sequence[str]) -> list[dict]:
  """One row per distance outside the span (0: inside), nearest first: each method's mean PSNR
  over the targets at that distance (before and after the span)."""
  distances = sorted({row["frames_outside_span"] for row in rows})
  return [
    {
      "frames": d,
      **{
        name: float(np.mean([r[name] for r in rows if r["frames_outside_span"] == d]))
        for name in methods
      },
    }
    for d in distances
  ]


def plot(rows: list[dict], methods: Sequence[str]) -> report.Plot:
  """PSNR vs distance outside the span (`by_distance`), one line per method."""
  return report.Plot(
    "view_extrapolation",
    TITLE,
    report.series(by_distance(rows, methods), "frames", methods),
    "frames outside the input span (0 = inside)",
  )


def main(settings: ViewExtrapolation) -> list[dict]:
  out = pathlib.Path(settings.output_dir) / "view_extrapolation"
  config, params = trained_tokengs(settings)
  scene_labels: dict[str, list[str]] = {}  # a short scene lacks some far offsets

  def views(record, position):
    frames = target_frames(settings, len(record["images"]))
    scene_labels[record["key"]] = list(frames)
    return (
      np.array([settings.start, settings.start + settings.gap]),
      np.array(list(frames.values())),
    )

  examples = data.evaluation_scenes(settings.experiment, views=views)
  methods = {"TokenGS": evaluation.feed_forward(params, config)}
  if settings.with_pixel_baseline:
    methods[PIXEL_ALIGNED] = pixel_baseline.method(trained_pixel_baseline(settings), config)
  if settings.with_tuning:
    e = settings.experiment.eval
    methods["TokenGS + token tuning"] = evaluation.tuned(
      params, config, TuningConfig(steps=e.tuning_steps, learning_rate=e.tuning_learning_rate)
    )
  scored = evaluation.evaluate(examples, methods, evaluation.Scorer(lpips=False)).scores
  labels = list(dict.fromkeys(label for key, _ in examples for label in scene_labels[key]))
  per_label = {name: {label: [] for label in labels} for name in methods}
  for position, (key, _) in enumerate(examples):
    for name in methods:
      scores = scored[name].per_view[position]["psnr"]
      for label, score in zip(scene_labels[key], scores, strict=True):
        per_label[name][label].append(float(score))
  rows = []
  for label in labels:
    distance = 0 if label == "inside" else int(label[1:])
    rows.append(
      {
        "target": label,
        "frames_outside_span": distance,
        "scenes": len(per_label[next(iter(methods))][label]),
        **{name: float(np.mean(per_label[name][label])) for name in methods},
      }
    )
  write_table(
    out,
    "view_extrapolation",
    "PSNR (dB) of targets inside vs outside the input span",
    rows,
    ["target", "frames_outside_span", "scenes"] + list(methods),
    notes=[
      (
        f"{len(examples)} held-out scenes; inputs at frames {settings.start} and "
        f"{settings.start + settings.gap}; '+k' after the last, '-k' before the first."
      )
    ],
  )
  plot(rows, list(methods)).draw(out)
  return rows


def claim(per_seed: Sequence[list[dict]]) -> report.Claim:
  """(b): on the targets outside the inputs' span, TokenGS beats the pixel-aligned baseline."""
  rows = report.aggregate(per_seed, ["target", "frames_outside_span"], METHODS)
  outside = {  # per seed: the mean over the targets outside the span
    name: [
      float(np.mean([row[name] for row in seed_rows if row["frames_outside_span"] > 0]))
      for seed_rows in per_seed
    ]
    for name in METHODS
  }
  verdict = report.verdict(outside["TokenGS"], outside[PIXEL_ALIGNED])
  evidence = (
    f"targets outside the span: {report.mean_std(outside['TokenGS'])} dB (TokenGS) vs "
    f"{report.mean_std(outside[PIXEL_ALIGNED])} dB (pixel-aligned); difference "
    f"{report.difference(outside['TokenGS'], outside[PIXEL_ALIGNED])} dB."
  )
  columns = ["target", "frames_outside_span", *METHODS]
  return report.Claim(
    "b", TITLE, CLAIM, rows, columns, verdict, evidence, plot(report.means(rows), METHODS)
  )


if __name__ == "__main__":
  process.setup()
  main(tyro.cli(ViewExtrapolation))
