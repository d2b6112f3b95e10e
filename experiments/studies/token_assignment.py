"""Token assignment: the Gaussians of each token drawn in that token's colour.

Gaussian i comes from token i // p² (p = decoder patch size). The picture shows whether a token's
Gaussians form a spatially coherent group (the paper's figure: tokens specialise to regions). The
table gives per-token statistics over the held-out scenes: spatial spread of a token's Gaussian
centres (mean distance to their centroid) relative to the whole scene's spread, and mean opacity.

    python -m experiments.studies.token_assignment

Writes `token_assignment.{json,md}`, `spread.png` and `scenes/<key>.png` (rows: input views |
targets | renders | token colours at the targets | token colours at the inputs; the key made a
safe file name by `results.data_path`) to `<output_dir>/token_assignment/`.
"""

from __future__ import annotations

import colorsys
import dataclasses
import pathlib

import jax
import numpy as np
import tyro

from experiments import data, figures, results
from experiments.studies import StudySettings, trained_tokengs, write_table
from tokengs_jax import evaluation, export, process
from tokengs_jax.gaussians import Gaussians


@dataclasses.dataclass(frozen=True)
class TokenAssignment(StudySettings):
  num_scenes: int = 4  # scenes drawn (statistics use every evaluated scene)


def token_colours(num_tokens: int) -> np.ndarray:
  """Distinct colours: hues spaced by the golden ratio, alternating value.  -> [T, 3] in [0, 1]."""
  return np.array(
    [
      colorsys.hsv_to_rgb((0.618034 * t) % 1.0, 0.85, 0.95 if t % 2 else 0.7)
      for t in range(num_tokens)
    ],
    np.float32,
  )


def per_token_statistics(gaussians: Gaussians, per_token: int) -> dict[str, np.ndarray]:
  """Spread and opacity per token of one scene ([N] Gaussians) -> arrays [T]."""
  means = np.asarray(gaussians.means).reshape(-1, per_token, 3)
  centroid = means.mean(axis=1, keepdims=True)
  spread = np.linalg.norm(means - centroid, axis=-1).mean(axis=1)
  scene_spread = np.linalg.norm(means.reshape(-1, 3) - means.reshape(-1, 3).mean(0), axis=-1).mean()
  opacity = np.asarray(gaussians.opacities).reshape(-1, per_token).mean(axis=1)
  return {"relative_spread": spread / max(scene_spread, 1e-12), "opacity": opacity}


def scene_picture(gaussians: Gaussians, coloured: Gaussians, batch: dict) -> np.ndarray:
  """inputs | targets | renders | token colours at the targets | token colours at the inputs."""
  height, width = batch["target_images"].shape[-3:-1]

  def render(g, prefix):
    return list(
      evaluation.render_targets(
        g, batch[f"{prefix}_c2w"], batch[f"{prefix}_intrinsics"], height=height, width=width
      ).rgb[0]
    )

  return figures.labelled_grid(
    [
      ("inputs", list(batch["context_images"][0])),
      ("targets", list(batch["target_images"][0])),
      ("render", render(gaussians, "target")),
      ("tokens (targets)", render(coloured, "target")),
      ("tokens (inputs)", render(coloured, "context")),
    ]
  )


def main(settings: TokenAssignment) -> list[dict]:
  out = pathlib.Path(settings.output_dir) / "token_assignment"
  config, params = trained_tokengs(settings)
  per_token = config.gaussians_per_token
  palette = np.repeat(token_colours(config.num_tokens), per_token, axis=0)  # [N, 3]
  examples = data.evaluation_scenes(settings.experiment)
  spreads, opacities = [], []
  for position, (key, batch) in enumerate(examples):
    gaussians = jax.device_get(evaluation.gaussians_for_batch(params, batch, config))
    stats = per_token_statistics(jax.tree.map(lambda x: x[0], gaussians), per_token)
    spreads.append(stats["relative_spread"])
    opacities.append(stats["opacity"])
    if position < settings.num_scenes and evaluation.writes_results():
      export.save_png(
        results.data_path(out / "scenes", key, ".png"),
        scene_picture(gaussians, dataclasses.replace(gaussians, colors=palette[None]), batch),
      )
  spreads, opacities = np.stack(spreads), np.stack(opacities)  # [S, T]
  mean_spread = spreads.mean(axis=0)
  order = np.argsort(mean_spread)
  rows = [
    {
      "token": int(t),
      "relative_spread": float(mean_spread[t]),
      "opacity": float(opacities.mean(axis=0)[t]),
    }
    for t in order
  ]
  write_table(
    out,
    "token_assignment",
    "Per-token spatial spread (token Gaussians vs whole scene)",
    rows,
    ["token", "relative_spread", "opacity"],
    notes=[
      (
        f"{len(examples)} held-out scenes; relative_spread < 1: a token's Gaussians "
        "are more compact than the scene (1 = spread like random Gaussians)."
      )
    ],
  )
  figures.line_plot(
    out / "spread.png",
    {"tokens (sorted)": (np.arange(len(order)), mean_spread[order])},
    title="Spatial spread of each token's Gaussians / scene spread",
    xlabel="token rank",
    ylabel="relative spread",
  )
  return rows


if __name__ == "__main__":
  process.setup()
  main(tyro.cli(TokenAssignment))
