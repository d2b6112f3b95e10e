"""Generalisation lever sweep: train a small TokenGS under one setting, score it on held-out rooms
of the training generator and on the gallery family it never saw, next to the copy baselines.

    python benchmarks/generalisation.py --name base    # one run -> <root>/base.json (+ .msgpack)
    python benchmarks/generalisation.py --name img64 --image-size 64 64 --steps 400
    python benchmarks/generalisation.py --table                      # every run -> <root>/levers.md

Self-contained on the library (data, model, train, tuning, metrics) so the lever runs do not
depend on the experiments package; the entry point's default is what the chosen lever becomes.

Protocol (both test sets): two input views, targets strictly between them (never an input frame).
Rooms: the training generator's test split, inputs at frames 0 and `context_gap`, targets evenly
inside. Galleries: `tokengs_jax.data.synthetic.generate_galleries` with its `eval_index.json`
(64x64 on disk, read at `image_size`). Methods: mean colour of the inputs, input average (pixelwise
mean of the input views), nearest input (the input whose frame index is closest; the earlier one
on a tie), trained feed-forward, trained + token tuning, and optionally the pixel-aligned baseline
(`experiments/pixel_baseline.py`) trained with the identical data, loss and schedule.
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
  """One lever run. Defaults: the synthetic default preset at a sweep-sized step count."""

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
    "num_gs_tokens=128", "dec_patch_size=2", "clip_head_readout_std=0.3")
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
  return pathlib.Path(s.root) / "data" / (
    f"rooms_{h}x{w}_n{s.num_train}_t{s.num_test}_f{s.frames}_yaw{s.walk_yaw_rate_std}"
    f"_side{s.walk_sideways_probability}_pitch{s.walk_pitch[0]}_{s.walk_pitch[1]}")


def galleries_dir(s: Settings) -> pathlib.Path:
  return pathlib.Path(s.root) / "data" / f"galleries_64x64_n{s.gallery_scenes}_f{s.gallery_frames}"


def ensure_data(s: Settings) -> dict:
  """Writes the rooms and galleries when missing (before JAX starts: the writers fork).

  Rooms go in chunks of 64 scenes: with more than 8 chunk files, `data.chunks._open_archive`'s
  LRU of open archives races between grain's reader threads (KeyError in `move_to_end`).
  """
  from tokengs_jax.data.synthetic import (
    Re10kLikeConfig, RoomConfig, WalkConfig, generate_galleries, generate_re10k_like)

  seconds = {}
  rooms = rooms_dir(s)
  if not (rooms / "test" / "index.json").exists():
    start = time.perf_counter()
    walk = WalkConfig(yaw_rate_std=s.walk_yaw_rate_std,
                      sideways_probability=s.walk_sideways_probability, pitch=s.walk_pitch)
    generate_re10k_like(rooms, s.num_train, s.num_test, *s.image_size, frames=s.frames, seed=0,
                        config=Re10kLikeConfig(room=RoomConfig(walk=walk), scenes_per_chunk=64),
                        workers=2)
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
      2, s.num_target_views, s.min_context_gap, s.max_context_gap, s.min_target_distance,
      s.curriculum_steps, s.initial_min_gap if warm else s.min_context_gap,
      s.initial_max_gap if warm else s.max_context_gap)
  else:
    sampler = BoundedSamplerConfig(2, s.num_eval_targets, s.context_gap, s.context_gap, 0, 0,
                                   s.context_gap, s.context_gap)
  return ExampleConfig(tuple(s.image_size), sampler, DATASET_PRESETS["re10k"].translation_scale,
                       random_flip=training, deterministic=not training)


def test_sets(s: Settings) -> dict[str, list[tuple[str, dict, tuple[np.ndarray, np.ndarray]]]]:
  """name -> [(key, batch of one, (context, target) frames)]; targets strictly between inputs."""
  from tokengs_jax.data import (
    ChunkedSceneSource, evaluation_views, load_evaluation_index, make_example)

  config = example_config(s, training=False)
  inner = np.linspace(0, s.context_gap, s.num_eval_targets + 2)[1:-1].round().astype(np.int64)
  index = load_evaluation_index(galleries_dir(s) / "eval_index.json")
  sources = {
    "rooms": (ChunkedSceneSource(rooms_dir(s) / "test"),
              lambda record: (np.array([0, s.context_gap]), inner)),
    "galleries": (ChunkedSceneSource(galleries_dir(s) / "test", keys=list(index)),
                  lambda record: evaluation_views(index, record["key"], len(record["images"]))),
  }
  sets = {}
  for name, (source, views) in sources.items():
    sets[name] = []
    for position in range(len(source)):
      record = source[position]
      chosen = views(record)
      example = make_example(record, config, np.random.default_rng(position), views=chosen)
      sets[name].append((record["key"], {k: v[None] for k, v in example.items()}, chosen))
  return sets


# ----------------------------------------------------------------------------------------------
# Baselines that copy the inputs


def nearest_input(batch: dict, context: np.ndarray, target: np.ndarray) -> np.ndarray:
  """Each target replaced by the input view with the closest frame index (earlier on a tie).
  -> [Vt, H, W, 3]."""
  distance = np.abs(np.asarray(target)[:, None] - np.asarray(context)[None, :])
  return batch["context_images"][0][np.argmin(distance, axis=1)]


def input_average(batch: dict) -> np.ndarray:
  """Each target replaced by the pixelwise mean of the input views.  -> [Vt, H, W, 3]."""
  mean = batch["context_images"][0].mean(0)
  return np.broadcast_to(mean, batch["target_images"][0].shape)


def mean_colour(batch: dict) -> np.ndarray:
  mean = batch["context_images"][0].mean((0, 1, 2))
  return np.broadcast_to(mean, batch["target_images"][0].shape)


# ----------------------------------------------------------------------------------------------
# Training and scoring


def train_once(s: Settings, model_config, loss_fn, params, label: str):
  from tokengs_jax.data import ChunkedSceneSource, InputPipeline
  from tokengs_jax.train import LoopConfig, OptimConfig, train

  source = ChunkedSceneSource(rooms_dir(s) / "train")
  batches = iter(InputPipeline(source, example_config(s, training=True), batch_size=s.batch_size,
                               seed=s.seed, shard_index=0, shard_count=1))
  optim = OptimConfig(learning_rate=s.learning_rate, schedule=s.schedule, total_steps=s.steps,
                      warmup_steps=min(s.warmup_steps, s.steps - 1))
  history = []

  def log(step, logged):
    history.append({"step": step, **{k: float(v) for k, v in logged.items() if k != "step"}})
    if step % max(s.steps // 8, 1) == 0 or step == s.steps:
      print(f"[{label}] step {step} loss {logged.get('loss', 0):.4f} "
            f"psnr {logged.get('psnr', 0):.2f}", flush=True)

  start = time.perf_counter()
  state, _ = train(loss_fn, params, batches, optim,
                   LoopConfig(total_steps=s.steps, seed=s.seed, log_every=25, checkpoint_every=0),
                   log_fn=log)
  return state.params, history, time.perf_counter() - start


def score(s: Settings, sets, predictors: dict) -> dict:
  """name -> set -> {"psnr": mean over scenes of per-scene mean PSNR, "per_scene": [...]}."""
  import jax
  import jax.numpy as jnp

  from tokengs_jax import metrics

  psnr = jax.jit(metrics.psnr)
  results = {}
  for method, predict in predictors.items():
    results[method] = {}
    for set_name, examples in sets.items():
      start, per_scene = time.perf_counter(), []
      for _, batch, (context, target) in examples:
        rgb = np.asarray(predict(batch, context, target), np.float32)
        value = np.asarray(psnr(jnp.asarray(rgb), jnp.asarray(batch["target_images"][0])))
        per_scene.append(float(np.mean(value)))
      results[method][set_name] = {"psnr": float(np.mean(per_scene)), "per_scene": per_scene,
                                   "seconds": time.perf_counter() - start}
  return results


def renderer(model_config, reconstruct):
  """(batch, context, target) -> target renders [Vt, H, W, 3] of the model's Gaussians."""
  import jax
  import jax.numpy as jnp

  from tokengs_jax import splatting
  from tokengs_jax.camera import invert_rigid
  from tokengs_jax.train import ObjectiveConfig

  objective = ObjectiveConfig()

  @jax.jit
  def render(gaussians, c2w, intrinsics):
    h, w = model_config.image_size
    return splatting.render(gaussians, invert_rigid(c2w), intrinsics, height=h, width=w,
                            background=jnp.asarray(objective.background), near=objective.near,
                            far=objective.far).rgb

  def predict(batch, context, target):
    del context, target
    gaussians = reconstruct(batch)
    return render(gaussians, jnp.asarray(batch["target_c2w"]),
                  jnp.asarray(batch["target_intrinsics"]))[0]
  return predict


def run(s: Settings) -> dict:
  data_seconds = ensure_data(s)
  os.environ.setdefault("TOKENGS_JAX_CACHE", str(_ROOT / ".jax_cache"))
  import jax

  jax.config.update("jax_compilation_cache_dir", os.environ["TOKENGS_JAX_CACHE"])
  jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
  import ast

  from tokengs_jax import model, tuning
  from tokengs_jax.losses import LossConfig
  from tokengs_jax.train import tokengs_loss_fn

  overrides = {}
  for item in s.model_overrides:
    key, _, value = item.partition("=")
    overrides[key] = ast.literal_eval(value)
  config = model.preset(s.model, image_size=tuple(s.image_size), num_input_views=2, **overrides)
  loss_config = LossConfig(rgb_loss=s.rgb_loss, lambda_ssim=s.lambda_ssim, lambda_vis=s.lambda_vis)
  params = model.init_params(jax.random.key(s.seed), config)
  params, history, train_seconds = train_once(
    s, config, tokengs_loss_fn(config, loss_config), params, s.name)
  from flax import serialization

  (pathlib.Path(s.root) / f"{s.name}.msgpack").write_bytes(
    serialization.msgpack_serialize(jax.device_get(params)))
  sets = test_sets(s)

  forward = jax.jit(lambda p, b: model.reconstruct(
    p, b["context_images"], b["context_c2w"], b["context_intrinsics"], config=config))
  predictors = {
    "mean_colour": lambda b, c, t: mean_colour(b),
    "input_average": lambda b, c, t: input_average(b),
    "nearest_input": lambda b, c, t: nearest_input(b, c, t),
    "trained": renderer(config, lambda b: forward(params, b)),
  }
  def tuned(learning_rate):
    settings = tuning.TuningConfig(steps=s.tuning_steps, learning_rate=learning_rate)
    return renderer(config, lambda b: tuning.tune(
      params, b["context_images"], b["context_c2w"], b["context_intrinsics"],
      model_config=config, tuning=settings, loss_config=loss_config).gaussians)

  if s.tuning_steps > 0:
    predictors["trained+token_tuning"] = tuned(s.tuning_learning_rate)
    for rate in s.extra_tuning_learning_rates:
      predictors[f"trained+token_tuning@{rate:g}"] = tuned(rate)
  extra = {}
  if s.pixel_baseline:
    sys.path.insert(0, str(_ROOT))
    from experiments import pixel_baseline

    pixel_params = pixel_baseline.init_params(jax.random.key(s.seed), config)
    pixel_params, _, extra["pixel_train_seconds"] = train_once(
      s, config, pixel_baseline.loss_fn(config, loss_config), pixel_params, s.name + "/pixel")
    predictors["pixel_aligned"] = renderer(config, lambda b: pixel_baseline.jitted_reconstruct(
      pixel_params, b["context_images"], b["context_c2w"], b["context_intrinsics"], config))
  results = score(s, sets, predictors)
  tail = history[-max(len(history) // 5, 1):]
  payload = {"settings": dataclasses.asdict(s), "data_seconds": data_seconds,
             "train_seconds": train_seconds, **extra,
             "train_psnr_last_fifth": float(np.mean([h.get("psnr", np.nan) for h in tail])),
             "results": results}
  out = pathlib.Path(s.root) / f"{s.name}.json"
  out.write_text(json.dumps(payload, indent=1))
  print(json.dumps({m: {k: round(v["psnr"], 2) for k, v in r.items()} for m, r in results.items()}))
  return payload


def table(root: str) -> str:
  """Markdown lever table of every run in `root`: PSNR per method on both test sets."""
  methods = ("mean_colour", "input_average", "nearest_input", "trained", "trained+token_tuning",
             "pixel_aligned")
  short = ("mean", "avg", "nearest", "ff", "tuned", "pixel")
  head = " | ".join(f"{m} {t}" for t in ("rooms", "gal") for m in short)
  lines = [f"| run | steps | train s | {head} | ff - nearest (gal) |",
           "|" + "---|" * (4 + 2 * len(methods))]
  for path in sorted(pathlib.Path(root).glob("*.json")):
    p = json.loads(path.read_text())
    r = p["results"]
    cells = []
    for t in ("rooms", "galleries"):
      cells += [f"{r[m][t]['psnr']:.2f}" if m in r else "-" for m in methods]
    margin = r["trained"]["galleries"]["psnr"] - r["nearest_input"]["galleries"]["psnr"]
    lines.append(f"| {path.stem} | {p['settings']['steps']} | {p['train_seconds']:.0f} | "
                 + " | ".join(cells) + f" | {margin:+.2f} |")
  text = "\n".join(lines) + "\n"
  (pathlib.Path(root) / "levers.md").write_text(text)
  return text


if __name__ == "__main__":
  import tyro

  settings = tyro.cli(Settings)
  print(table(settings.root)) if settings.table else run(settings)
