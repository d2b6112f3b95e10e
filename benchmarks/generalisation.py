"""Generalisation lever sweep: train a small TokenGS under one setting, score it on held-out rooms
of the training generator and on the gallery family it never saw, next to the copy baselines.

    python benchmarks/generalisation.py --name base    # one run -> <root>/base.json (+ .msgpack)
    python benchmarks/generalisation.py --name img64 --image-size 64 64 --steps 400
    python benchmarks/generalisation.py --table                      # every run -> <root>/levers.md

Built on the library (data, model, train, tuning) so the lever runs do not depend on the
experiments package (only `--pixel-baseline` imports `experiments/pixel_baseline.py`); the entry
point's default is what the chosen lever becomes. Every score comes from the project's one
evaluator, `tokengs_jax.evaluation` (`evaluate_sets`, PSNR and SSIM, predictions and targets
clipped to [0, 1], renders by `render_targets`).

Protocol (both test sets): two input views, targets strictly between them (never an input frame).
Rooms: the training generator's test split, inputs at frames 0 and `context_gap`, targets evenly
inside. Galleries: `tokengs_jax.data.synthetic.generate_galleries` with its `eval_index.json`
(64x64 on disk, read at `image_size`). Methods (`evaluation.Method`s): the evaluator's baselines
`mean_colour`, `input_average`, `nearest_view` (the input whose frame index is closest; the earlier
one on a tie), `trained` (feed-forward), `trained+token_tuning` (and `trained+token_tuning@<lr>`
per extra tuning rate), and optionally `pixel_aligned` (`experiments/pixel_baseline.py`) trained
with the identical data, loss and schedule. Runs written before this scored through the evaluator
called the nearest view `nearest_input`; `--table` reads both.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import sys
import time
from typing import Literal

import numpy as np

_ROOT = pathlib.Path(__file__).resolve().parents[1]


@dataclasses.dataclass(frozen=True)
class Settings:
  """One lever run. Defaults: the sessions 2-4 synthetic default (512 Gaussians, head colours,
  RE10K-like walk) at a sweep-sized step count, kept so the documented lever commands reproduce;
  the session-5 default is `--model-overrides num_gs_tokens=128 dec_patch_size=4
  clip_head_readout_std=0.3 gaussian_colours='"inputs"' --walk-pitch -0.6 0.15
  --walk-yaw-rate-std 0.03 --walk-sideways-probability 0.3 --steps 1500 --warmup-steps 100`."""

  name: str = "base"
  root: str = "outputs/generalisation"
  table: bool = False  # only collect `<root>/*.json` into `<root>/levers.md`
  # Training data (the rooms generator; cached per setting under <root>/data).
  image_size: tuple[int, int] = (32, 32)
  num_train: int = 48
  num_test: int = 8
  frames: int = 24
  walk_yaw_rate_std: float = 0.012  # rooms' camera path (domain randomisation lever)
  walk_sideways_probability: float = 0.15
  walk_pitch: tuple[float, float] = (-0.15, 0.05)  # mean camera pitch range (radians)
  # Held-out galleries.
  gallery_scenes: int = 24
  gallery_frames: int = 13
  # Model.
  model: str = "tiny"
  model_overrides: tuple[str, ...] = (
    "num_gs_tokens=128",
    "dec_patch_size=2",
    "clip_head_readout_std=0.3",
  )
  # Training.
  steps: int = 400
  batch_size: int = 4
  num_target_views: int = 2
  min_context_gap: int = 6
  max_context_gap: int = 14
  curriculum_steps: int = 0  # context-gap warm-up from (initial_min_gap, initial_max_gap)
  initial_min_gap: int = 2
  initial_max_gap: int = 6
  min_target_distance: int = 0
  learning_rate: float = 3e-3
  warmup_steps: int = 40
  schedule: Literal["warmup_cosine", "one_cycle", "constant"] = "warmup_cosine"
  lambda_ssim: float = 0.2
  lambda_vis: float = 1.0
  rgb_loss: Literal["l2", "l1"] = "l2"
  seed: int = 0
  pixel_baseline: bool = False
  # Evaluation.
  context_gap: int = 12
  num_eval_targets: int = 3
  tuning_steps: int = 50
  tuning_learning_rate: float = 1e-4
  extra_tuning_learning_rates: tuple[float, ...] = ()  # also scored, as "trained+token_tuning@lr"


# ----------------------------------------------------------------------------------------------
# Data


def rooms_dir(s: Settings) -> pathlib.Path:
  h, w = s.image_size
  return (
    pathlib.Path(s.root)
    / "data"
    / (
      f"rooms_{h}x{w}_n{s.num_train}_t{s.num_test}_f{s.frames}_yaw{s.walk_yaw_rate_std}"
      f"_side{s.walk_sideways_probability}_pitch{s.walk_pitch[0]}_{s.walk_pitch[1]}"
    )
  )


def galleries_dir(s: Settings) -> pathlib.Path:
  return pathlib.Path(s.root) / "data" / f"galleries_64x64_n{s.gallery_scenes}_f{s.gallery_frames}"


def ensure_data(s: Settings) -> dict:
  """Writes the rooms and galleries when missing (before JAX starts: the writers fork).

  Rooms go in chunks of 64 scenes: with more than 8 chunk files, `data.chunks._open_archive`'s
  LRU of open archives races between grain's reader threads (KeyError in `move_to_end`).
  """
  from tokengs_jax.data.synthetic import (
    Re10kLikeConfig,
    RoomConfig,
    WalkConfig,
    generate_galleries,
    generate_re10k_like,
  )

  seconds = {}
  rooms = rooms_dir(s)
  if not (rooms / "test" / "index.json").exists():
    start = time.perf_counter()
    walk = WalkConfig(
      yaw_rate_std=s.walk_yaw_rate_std,
      sideways_probability=s.walk_sideways_probability,
      pitch=s.walk_pitch,
    )
    generate_re10k_like(
      rooms,
      s.num_train,
      s.num_test,
      *s.image_size,
      frames=s.frames,
      seed=0,
      config=Re10kLikeConfig(room=RoomConfig(walk=walk), scenes_per_chunk=64),
      workers=2,
    )
    seconds["rooms"] = time.perf_counter() - start
  galleries = galleries_dir(s)
  if not (galleries / "eval_index.json").exists():
    start = time.perf_counter()
    generate_galleries(galleries, s.gallery_scenes, 64, 64, s.gallery_frames, seed=0, workers=2)
    seconds["galleries"] = time.perf_counter() - start
  return seconds


def example_config(s: Settings, training: bool):
  from tokengs_jax.data import DATASET_PRESETS, BoundedSamplerConfig, ExampleConfig

  if training:
    warm = s.curriculum_steps > 0
    sampler = BoundedSamplerConfig(
      2,
      s.num_target_views,
      s.min_context_gap,
      s.max_context_gap,
      s.min_target_distance,
      s.curriculum_steps,
      s.initial_min_gap if warm else s.min_context_gap,
      s.initial_max_gap if warm else s.max_context_gap,
    )
  else:
    sampler = BoundedSamplerConfig(
      2, s.num_eval_targets, s.context_gap, s.context_gap, 0, 0, s.context_gap, s.context_gap
    )
  return ExampleConfig(
    tuple(s.image_size),
    sampler,
    DATASET_PRESETS["re10k"].translation_scale,
    random_flip=training,
    deterministic=not training,
  )


def test_sets(s: Settings) -> dict[str, list[tuple[str, dict]]]:
  """name -> [(key, batch of one)] in the evaluator's contract; targets strictly between inputs.

  Each batch carries its views' frame numbers, `context_frames` [1, 2] and `target_frames`
  [1, Vt] (int64), which the evaluator's nearest-view baseline reads.
  """
  from tokengs_jax.data import (
    ChunkedSceneSource,
    evaluation_views,
    load_evaluation_index,
    make_example,
  )

  config = example_config(s, training=False)
  inner = np.linspace(0, s.context_gap, s.num_eval_targets + 2)[1:-1].round().astype(np.int64)
  index = load_evaluation_index(galleries_dir(s) / "eval_index.json")
  sources = {
    "rooms": (
      ChunkedSceneSource(rooms_dir(s) / "test"),
      lambda record: (np.array([0, s.context_gap]), inner),
    ),
    "galleries": (
      ChunkedSceneSource(galleries_dir(s) / "test", keys=list(index)),
      lambda record: evaluation_views(index, record["key"], len(record["images"])),
    ),
  }
  sets = {}
  for name, (source, views) in sources.items():
    sets[name] = []
    for position in range(len(source)):
      record = source[position]
      chosen = views(record)
      example = make_example(record, config, np.random.default_rng(position), views=chosen)
      example["context_frames"], example["target_frames"] = (
        np.asarray(f, np.int64) for f in chosen
      )
      sets[name].append((record["key"], {k: v[None] for k, v in example.items()}))
  return sets


# ----------------------------------------------------------------------------------------------
# Training and scoring (every score through `tokengs_jax.evaluation`)


def train_once(s: Settings, model_config, loss_fn, params, label: str):
  from tokengs_jax.data import ChunkedSceneSource, InputPipeline
  from tokengs_jax.train import LoopConfig, OptimConfig, train

  source = ChunkedSceneSource(rooms_dir(s) / "train")
  batches = iter(
    InputPipeline(
      source,
      example_config(s, training=True),
      batch_size=s.batch_size,
      seed=s.seed,
      shard_index=0,
      shard_count=1,
    )
  )
  optim = OptimConfig(
    learning_rate=s.learning_rate,
    schedule=s.schedule,
    total_steps=s.steps,
    warmup_steps=min(s.warmup_steps, s.steps - 1),
  )
  history = []

  def log(step, logged):
    history.append({"step": step, **{k: float(v) for k, v in logged.items() if k != "step"}})
    if step % max(s.steps // 8, 1) == 0 or step == s.steps:
      print(
        f"[{label}] step {step} loss {logged.get('loss', 0):.4f} psnr {logged.get('psnr', 0):.2f}",
        flush=True,
      )

  start = time.perf_counter()
  state, _ = train(
    loss_fn,
    params,
    batches,
    optim,
    LoopConfig(total_steps=s.steps, seed=s.seed, log_every=25, checkpoint_every=0),
    log_fn=log,
  )
  return state.params, history, time.perf_counter() - start


def setup_jax():
  """Points JAX's persistent compilation cache at the repository's (after the data writers fork)."""
  os.environ.setdefault("TOKENGS_JAX_CACHE", str(_ROOT / ".jax_cache"))
  import jax

  jax.config.update("jax_compilation_cache_dir", os.environ["TOKENGS_JAX_CACHE"])
  jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


def build_model_config(s: Settings):
  import ast

  from tokengs_jax import model

  overrides = {}
  for item in s.model_overrides:
    key, _, value = item.partition("=")
    overrides[key] = ast.literal_eval(value)
  return model.preset(s.model, image_size=tuple(s.image_size), num_input_views=2, **overrides)


def train_pixel_baseline(s: Settings, config, loss_config):
  """The pixel-aligned baseline trained like TokenGS -> (its evaluation.Method, train seconds)."""
  import jax

  from tokengs_jax import evaluation

  sys.path.insert(0, str(_ROOT))
  from experiments import pixel_baseline

  params = pixel_baseline.init_params(jax.random.key(s.seed), config)
  params, _, seconds = train_once(
    s, config, pixel_baseline.loss_fn(config, loss_config), params, s.name + "/pixel"
  )

  def predict(batch):
    return pixel_baseline.jitted_reconstruct(
      params, batch["context_images"], batch["context_c2w"], batch["context_intrinsics"], config
    )

  return evaluation.Method(reconstruct=predict), seconds


def methods(s: Settings, params, config, loss_config) -> dict:
  """name -> evaluation.Method: the evaluator's baselines, feed-forward, token tuning (one per
  tuning learning rate)."""
  from tokengs_jax import evaluation, tuning

  scored = {**evaluation.baselines(), "trained": evaluation.feed_forward(params, config)}
  if s.tuning_steps > 0:
    rates = {"trained+token_tuning": s.tuning_learning_rate}
    rates.update({f"trained+token_tuning@{r:g}": r for r in s.extra_tuning_learning_rates})
    for name, rate in rates.items():
      settings = tuning.TuningConfig(steps=s.tuning_steps, learning_rate=rate)
      scored[name] = evaluation.tuned(params, config, settings, loss_config)
  return scored


def score(sets: dict, scored: dict) -> dict:
  """method -> set -> {"psnr", "ssim": protocol means, "per_scene": [{"key", "psnr", "ssim"}],
  "seconds"}, all from `evaluation.evaluate_sets`."""
  from tokengs_jax import evaluation

  evaluations = evaluation.evaluate_sets(sets, scored, evaluation.Scorer(lpips=False))
  results = {name: {} for name in scored}
  for set_name, evaluated in evaluations.items():
    for name, method_scores in evaluated.scores.items():
      results[name][set_name] = {
        **method_scores.summary(),
        "per_scene": method_scores.per_scene,
        "seconds": method_scores.seconds,
      }
  return results


def run(s: Settings) -> dict:
  data_seconds = ensure_data(s)
  setup_jax()
  import jax
  from flax import serialization

  from tokengs_jax import model
  from tokengs_jax.losses import LossConfig
  from tokengs_jax.train import tokengs_loss_fn

  config = build_model_config(s)
  loss_config = LossConfig(rgb_loss=s.rgb_loss, lambda_ssim=s.lambda_ssim, lambda_vis=s.lambda_vis)
  params = model.init_params(jax.random.key(s.seed), config)
  params, history, train_seconds = train_once(
    s, config, tokengs_loss_fn(config, loss_config), params, s.name
  )
  (pathlib.Path(s.root) / f"{s.name}.msgpack").write_bytes(
    serialization.msgpack_serialize(jax.device_get(params))
  )
  scored, extra = methods(s, params, config, loss_config), {}
  if s.pixel_baseline:
    scored["pixel_aligned"], extra["pixel_train_seconds"] = train_pixel_baseline(
      s, config, loss_config
    )
  results = score(test_sets(s), scored)
  tail = history[-max(len(history) // 5, 1) :]
  payload = {
    "settings": dataclasses.asdict(s),
    "data_seconds": data_seconds,
    "train_seconds": train_seconds,
    **extra,
    "train_psnr_last_fifth": float(np.mean([h.get("psnr", np.nan) for h in tail])),
    "results": results,
  }
  out = pathlib.Path(s.root) / f"{s.name}.json"
  out.write_text(json.dumps(payload, indent=1))
  print(json.dumps({m: {k: round(v["psnr"], 2) for k, v in r.items()} for m, r in results.items()}))
  return payload


# Runs written before the driver scored through `tokengs_jax.evaluation` named a method otherwise.
_OLD_NAMES = {"nearest_input": "nearest_view"}


def table(root: str) -> str:
  """Markdown lever table of every run in `root`: PSNR per method on both test sets."""
  methods = (
    "mean_colour",
    "input_average",
    "nearest_view",
    "trained",
    "trained+token_tuning",
    "pixel_aligned",
  )
  short = ("mean", "avg", "nearest", "ff", "tuned", "pixel")
  head = " | ".join(f"{m} {t}" for t in ("rooms", "gal") for m in short)
  lines = [
    f"| run | steps | train s | {head} | ff - nearest (gal) |",
    "|" + "---|" * (4 + 2 * len(methods)),
  ]
  for path in sorted(pathlib.Path(root).glob("*.json")):
    p = json.loads(path.read_text())
    r = {_OLD_NAMES.get(name, name): scores for name, scores in p["results"].items()}
    cells = []
    for t in ("rooms", "galleries"):
      cells += [f"{r[m][t]['psnr']:.2f}" if m in r else "-" for m in methods]
    margin = r["trained"]["galleries"]["psnr"] - r["nearest_view"]["galleries"]["psnr"]
    lines.append(
      f"| {path.stem} | {p['settings']['steps']} | {p['train_seconds']:.0f} | "
      + " | ".join(cells)
      + f" | {margin:+.2f} |"
    )
  text = "\n".join(lines) + "\n"
  (pathlib.Path(root) / "levers.md").write_text(text)
  return text


if __name__ == "__main__":
  import tyro

  settings = tyro.cli(Settings)
  print(table(settings.root)) if settings.table else run(settings)
