"""Camera-noise robustness: rotate the non-reference input cameras by 0-10 degrees.

TokenGS against the pixel-aligned GS-LRM-style baseline (`experiments.pixel_baseline`), trained
with the same data, objective, optimiser, steps and seed. Each scene's perturbation axis is drawn
once (per scene and view) and only its angle grows, so the curves differ only in the angle. Target
cameras are exact: the score measures how much a wrong input pose hurts the reconstruction.

    python -m experiments.studies.camera_noise [--angles 0 1 2 5 10]

Writes `camera_noise.{json,md,png}` to `<output_dir>/camera_noise/`.
"""

from __future__ import annotations

import dataclasses
import pathlib

import jax
import numpy as np
import tyro

from experiments import data, figures, pixel_baseline, weights
from experiments.studies import StudySettings, psnr_of, train, trained_tokengs, write_table
from tokengs_jax import evaluation, process


@dataclasses.dataclass(frozen=True)
class CameraNoise(StudySettings):
  angles: tuple[float, ...] = (0.0, 1.0, 2.0, 5.0, 10.0)
  baseline_params: str | None = (
    None  # trained baseline weights; default <out>/pixel_baseline.msgpack
  )

  def __post_init__(self):
    if 0.0 not in self.angles:
      raise ValueError(f"angles {self.angles} must include 0: the drops are measured from it")


def rotate_cameras(c2w: np.ndarray, axes: np.ndarray, degrees: float) -> np.ndarray:
  """Rotates every camera but the first about its own centre.

  c2w: [V, 4, 4]; axes: [V, 3] unit axes in camera coordinates -> [V, 4, 4].
  """
  out = np.array(c2w, np.float64)
  angle = np.deg2rad(degrees)
  for v in range(1, len(out)):
    k = np.array(
      [[0, -axes[v, 2], axes[v, 1]], [axes[v, 2], 0, -axes[v, 0]], [-axes[v, 1], axes[v, 0], 0]]
    )
    rotation = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
    out[v, :3, :3] = out[v, :3, :3] @ rotation
  return out.astype(np.float32)


def noisy(examples, degrees: float, seed: int):
  """The examples with their non-reference context cameras rotated by `degrees`."""
  result = []
  for position, (key, batch) in enumerate(examples):
    axes = np.random.default_rng([seed, position]).normal(size=(batch["context_c2w"].shape[1], 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    result.append(
      (key, {**batch, "context_c2w": rotate_cameras(batch["context_c2w"][0], axes, degrees)[None]})
    )
  return result


def baseline_params(settings: CameraNoise, config, out: pathlib.Path):
  path = pathlib.Path(settings.baseline_params or out / "pixel_baseline.msgpack")
  if path.exists():
    return weights.load_params(path)
  experiment = dataclasses.replace(settings.experiment, output_dir=str(out / "pixel_baseline"))
  print("[study] training the pixel-aligned baseline with the TokenGS settings", flush=True)
  params = train(
    experiment,
    pixel_baseline.init_params(jax.random.key(experiment.seed), config),
    loss_fn=pixel_baseline.loss_fn(config),
  )
  weights.save_params(path, params)
  return params


def main(settings: CameraNoise) -> list[dict]:
  out = pathlib.Path(settings.output_dir) / "camera_noise"
  config, params = trained_tokengs(settings)
  baseline = baseline_params(settings, config, out)
  examples = data.evaluation_scenes(settings.experiment)
  scorer = evaluation.Scorer(lpips=False)
  methods = {
    "TokenGS": evaluation.feed_forward(params, config),
    "pixel-aligned (GS-LRM-style)": pixel_baseline.method(baseline, config),
  }
  rows, curves = [], {name: ([], []) for name in methods}
  for degrees in settings.angles:
    perturbed = noisy(examples, degrees, settings.experiment.seed)
    row = {"angle_deg": float(degrees)}
    for name, method in methods.items():
      scores, _ = psnr_of(method, perturbed, scorer)
      row[name] = float(np.mean(scores))
      curves[name][0].append(degrees)
      curves[name][1].append(row[name])
    rows.append(row)
  clean = next(row for row in rows if row["angle_deg"] == 0.0)
  for name in methods:  # drop relative to the clean inputs: the robustness figure
    for row in rows:
      row[f"{name} drop"] = row[name] - clean[name]
  columns = ["angle_deg"] + list(methods) + [f"{name} drop" for name in methods]
  write_table(
    out,
    "camera_noise",
    "PSNR (dB) vs rotation noise on the non-reference input views",
    rows,
    columns,
    notes=[
      (
        f"{len(examples)} held-out scenes; models trained "
        f"{settings.experiment.train.steps} steps each, same settings."
      )
    ],
  )
  figures.line_plot(
    out / "camera_noise.png",
    curves,
    title="Camera noise robustness",
    xlabel="rotation of non-reference input camera (deg)",
    ylabel="PSNR (dB)",
  )
  return rows


if __name__ == "__main__":
  process.setup()
  main(tyro.cli(CameraNoise))
