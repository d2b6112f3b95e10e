"""The paper's studies, one script each; every script writes a table (JSON + Markdown) and a plot.

    python -m experiments.studies.camera_noise         # TokenGS vs pixel-aligned baseline
    python -m experiments.studies.view_extrapolation
    python -m experiments.studies.test_time_scaling    # views, tuning steps, tuning target
    python -m experiments.studies.token_count          # PSNR and run time vs Gaussian tokens
    python -m experiments.studies.token_assignment     # Gaussians coloured by their token

By default each study starts from the synthetic default run's weights
(`outputs/re10k/tiny_synthetic/params.msgpack`, written by `python -m experiments.re10k`) and
trains that model first when they are missing; `--experiment.*` flags change data, model and
training exactly as on the entry point.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import time
from collections.abc import Callable, Sequence

import jax
import numpy as np

from experiments import common
from tokengs_jax import model


@dataclasses.dataclass(frozen=True)
class StudySettings:
  """Shared by every study.

  Attributes:
    experiment: data / model / training / evaluation settings (the re10k default preset).
    params: trained TokenGS weights; trained with `experiment` (and saved there) when missing.
    output_dir: where the study's table and plot go.
  """
  experiment: common.Experiment = dataclasses.field(default_factory=common.Experiment)
  params: str = "outputs/re10k/tiny_synthetic/params.msgpack"
  output_dir: str = "outputs/studies"


def trained_tokengs(settings: StudySettings) -> tuple[model.ModelConfig, dict]:
  """The model config and trained weights (training them with the experiment when missing)."""
  common.enable_compile_cache()
  config = common.model_config(settings.experiment)
  path = pathlib.Path(settings.params)
  if path.exists():
    return config, common.load_params(path)
  print(f"[study] {path} is missing: training the TokenGS model first", flush=True)
  experiment = dataclasses.replace(settings.experiment, output_dir=str(path.parent))
  params = model.init_params(jax.random.key(experiment.seed), config)
  params, _, _ = common.train_model(experiment, config, params)
  common.save_params(path, params)
  return config, params


def timed(function: Callable, *args) -> tuple[object, float]:
  """(result, seconds) with the result's arrays ready (device work included)."""
  start = time.perf_counter()
  result = jax.block_until_ready(function(*args))
  return result, time.perf_counter() - start


def scene_psnr(scorer: common.Scorer, rgb: np.ndarray, batch: dict) -> float:
  """Mean PSNR over a batch-of-one's target views."""
  return float(np.mean(scorer(rgb[0], batch["target_images"][0])["psnr"]))


def psnr_of(method: Callable, examples: Sequence[tuple[str, dict]], scorer: common.Scorer
            ) -> tuple[list[float], float]:
  """Per-scene PSNR of a `batch -> Gaussians` method, and its mean seconds per scene (the first
  scene's call, which compiles, is timed again after it)."""
  scores, seconds = [], []
  for position, (_, batch) in enumerate(examples):
    height, width = batch["target_images"].shape[-3:-1]
    gaussians, elapsed = timed(method, batch)
    if position == 0:  # exclude compilation from the run time
      gaussians, elapsed = timed(method, batch)
    seconds.append(elapsed)
    rgb, _, _ = common.render_views(gaussians, batch["target_c2w"], batch["target_intrinsics"],
                                    height, width)
    scores.append(scene_psnr(scorer, rgb, batch))
  return scores, float(np.mean(seconds))


def write_table(out_dir, name: str, title: str, rows: list[dict], columns: Sequence[str],
                notes: Sequence[str] = ()) -> pathlib.Path:
  """`<name>.json` (rows + notes) and `<name>.md` (a table) in `out_dir`."""
  out_dir = pathlib.Path(out_dir)
  out_dir.mkdir(parents=True, exist_ok=True)
  (out_dir / f"{name}.json").write_text(json.dumps({"title": title, "rows": rows,
                                                    "notes": list(notes)}, indent=1))
  lines = [f"# {title}\n", "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
  for row in rows:
    lines.append("| " + " | ".join(f"{row[c]:.4g}" if isinstance(row[c], float) else str(row[c])
                                   for c in columns) + " |")
  lines += [""] + [f"- {n}" for n in notes]
  path = out_dir / f"{name}.md"
  path.write_text("\n".join(lines) + "\n")
  print("\n".join(lines), flush=True)
  return path
