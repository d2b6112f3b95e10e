"""Gaussian distribution: Gaussians per unit scene area vs distance from the cameras, TokenGS vs
the pixel-aligned baseline (the paper: TokenGS spreads its Gaussians more evenly).

Measured in the held-out scenes' target views, which both models reconstruct and neither takes
as input. Distance is depth in a target view; the bins hold equal shares of the targets' pixels
with a true depth (quantiles of the synthetic sets' depth maps). A bin's scene area is the area
its pixels cover, depth² / (fx fy) each (a fronto-parallel surface); its Gaussians are those
whose centre projects into the view at a depth in the bin, each weighted by its opacity. The
relative density of a bin is its Gaussians per unit area over that of all bins (1 everywhere:
perfectly even); the Gini coefficient of the density over the scene area (weighted by area) sums
it up: 0 even, towards 1 all Gaussians in a sliver of the scene. A pixel-aligned model puts one
Gaussian on each input pixel, so its density falls with depth² as the pixels' footprint grows.

    python -m experiments.studies.distribution [--bins 8]

Writes `distribution.{json,md}` and `distribution.png` (relative density per depth bin) to
`<output_dir>/distribution/`. Needs true depth maps (the synthetic sets).
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
  in_views,
  report,
  scene_gaussians,
  trained_pixel_baseline,
  trained_tokengs,
  write_table,
)
from tokengs_jax import evaluation, process

GINI = "Gini"  # the `bin` of the summary row
TITLE = "Gaussian distribution"
METHODS = ("TokenGS", PIXEL_ALIGNED)
CLAIM = (
  "Paper: TokenGS distributes its Gaussians more evenly than pixel-aligned models. Compared: "
  "Gaussians (opacity-weighted) per unit scene area in depth bins of the held-out target views, "
  "relative to the mean (1 = even), and its Gini coefficient over the scene area (lower: more "
  "even)."
)


@dataclasses.dataclass(frozen=True)
class Distribution(StudySettings):
  bins: int = 8


def gini(values: np.ndarray, weights: np.ndarray) -> float:
  """Weighted Gini coefficient: sum_ij w_i w_j |x_i - x_j| / (2 (sum w)² mean_w(x)); 0 when
  every value is equal."""
  values, weights = np.asarray(values, np.float64), np.asarray(weights, np.float64)
  mean = np.sum(weights * values) / np.sum(weights)
  pairs = np.abs(values[:, None] - values[None, :]) * weights[:, None] * weights[None, :]
  return float(pairs.sum() / (2.0 * np.sum(weights) ** 2 * max(mean, 1e-12)))


def area_per_bin(depths: np.ndarray, intrinsics: np.ndarray, edges: np.ndarray) -> np.ndarray:
  """Scene area seen in each depth bin: sum over pixels of depth² / (fx fy).
  depths [V, H, W] (0: no surface), intrinsics [V, 4] -> [bins]."""
  area = np.zeros(len(edges) - 1)
  for depth, (fx, fy, _, _) in zip(depths, intrinsics):
    valid = depth[depth > 0]
    area += np.histogram(valid, edges, weights=valid**2 / (fx * fy))[0]
  return area


def gaussians_per_bin(inside: np.ndarray, depth: np.ndarray, opacities, edges) -> np.ndarray:
  """Opacity-weighted Gaussians per depth bin, over views: inside / depth [V, N] (`in_views`)."""
  return sum(
    np.histogram(d[seen], edges, weights=opacities[seen])[0] for seen, d in zip(inside, depth)
  )


def relative_density(counts: np.ndarray, area: np.ndarray) -> np.ndarray:
  """Per bin, (counts / area) over (total count / total area); 0 in a bin without area."""
  per_area = np.divide(counts, area, out=np.zeros_like(counts, np.float64), where=area > 0)
  return per_area / max(counts.sum() / max(area.sum(), 1e-12), 1e-12)


def plot(rows: list[dict]) -> report.Plot:
  """Relative density per depth bin (the histogram), a line per method."""
  bins = [row for row in rows if row["bin"] != GINI]
  return report.Plot(
    "distribution",
    "Gaussians per unit area / their mean, per depth bin",
    report.series(bins, "bin", METHODS),
    "depth bin (equal pixel counts, near to far)",
    ylabel="relative density",
  )


def main(settings: Distribution) -> list[dict]:
  out = pathlib.Path(settings.output_dir) / "distribution"
  config, params = trained_tokengs(settings)
  baseline = trained_pixel_baseline(settings)
  methods = dict(
    zip(
      METHODS,
      (evaluation.feed_forward(params, config), pixel_baseline.method(baseline, config)),
      strict=True,
    )
  )
  scenes = data.evaluation_scenes(settings.experiment)
  if "target_depths" not in scenes[0][1]:
    raise ValueError("the distribution study needs true depth maps (the synthetic sets)")
  pooled = np.concatenate([batch["target_depths"][0].ravel() for _, batch in scenes])
  edges = np.quantile(pooled[pooled > 0], np.linspace(0, 1, settings.bins + 1))
  edges[-1] = np.nextafter(edges[-1], np.inf)  # the deepest pixel inside the last bin
  near = settings.experiment.train.loss_config().near
  area = np.zeros(settings.bins)
  counts = {name: np.zeros(settings.bins) for name in methods}
  for _, batch in scenes:
    height, width = batch["target_images"].shape[-3:-1]
    area += area_per_bin(batch["target_depths"][0], batch["target_intrinsics"][0], edges)
    for name, method in methods.items():
      means, opacities = scene_gaussians(method, batch)
      inside, depth = in_views(
        means, batch["target_c2w"][0], batch["target_intrinsics"][0], height, width, near
      )
      counts[name] += gaussians_per_bin(inside, depth, opacities, edges)
  density = {name: relative_density(c, area) for name, c in counts.items()}
  rows = [
    {
      "bin": b + 1,
      "depth_from": float(edges[b]),
      "depth_to": float(edges[b + 1]),
      **{name: float(density[name][b]) for name in methods},
    }
    for b in range(settings.bins)
  ]
  rows.append({"bin": GINI, **{name: gini(density[name], area) for name in methods}})
  write_table(
    out,
    "distribution",
    "Relative Gaussian density (per unit scene area; 1 = even) per depth bin, and its Gini",
    rows,
    ["bin", "depth_from", "depth_to", *methods],
    notes=[
      f"{len(scenes)} held-out scenes, their target views; bins of equal pixel counts; "
      "Gaussians weighted by opacity; Gini over the scene area (0: even)."
    ],
  )
  plot(rows).draw(out)
  return rows


def claim(per_seed: Sequence[list[dict]]) -> report.Claim:
  """(g): TokenGS's density is more even (lower Gini) than the pixel-aligned model's."""
  rows = report.aggregate(per_seed, ["bin"], ["depth_from", "depth_to", *METHODS])
  gini_row = next(r for r in rows if r["bin"] == GINI)
  tokengs, baseline = gini_row["TokenGS_seeds"], gini_row[f"{PIXEL_ALIGNED}_seeds"]
  verdict = report.verdict(tokengs, baseline, higher_is_better=False)
  evidence = (
    f"Gini {gini_row['TokenGS']} (TokenGS) vs {gini_row[PIXEL_ALIGNED]} (pixel-aligned); "
    f"difference {report.difference(tokengs, baseline)}."
  )
  columns = ["bin", "depth_from", "depth_to", *METHODS]
  return report.Claim("g", TITLE, CLAIM, rows, columns, verdict, evidence, plot(report.means(rows)))


if __name__ == "__main__":
  process.setup()
  main(tyro.cli(Distribution))
