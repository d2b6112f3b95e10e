"""The experiments' data: the synthetic set, training batches and the held-out evaluation scenes."""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import json
import os
import pathlib
import shutil
import time
from collections.abc import Callable

import jax
import numpy as np

from experiments.config import Experiment, SyntheticSettings
from tokengs_jax.data import (
  DATASET_PRESETS,
  BoundedSamplerConfig,
  ChunkedSceneSource,
  ExampleConfig,
  InputPipeline,
  evaluation_views,
  load_evaluation_index,
  make_example,
  sample_bounded,
)
from tokengs_jax.data import dl3dv, mixing
from tokengs_jax.data.sampler import EvaluationIndexReport, validate_evaluation_index
from tokengs_jax.data.synthetic.generate import read_true_depths

# (record, scene position) -> (context frames, target frames)
ViewChooser = Callable[[dict, int], tuple[np.ndarray, np.ndarray]]


_REFUSING_GENERATION: contextvars.ContextVar[str | None] = contextvars.ContextVar(
  "refusing_generation", default=None
)


class GenerationRefused(FileNotFoundError):
  """A synthetic set is missing (or stale) where writing one was refused (`refusing_generation`)."""


@contextlib.contextmanager
def refusing_generation(advice: str):
  """Within, a synthetic set that would be written (missing, or a Kubric subset with other
  settings) raises `GenerationRefused`, one line naming it and ending with `advice`, instead:
  for a program that reads another run's settings (the viewer), which must not write where those
  settings point unless asked."""
  token = _REFUSING_GENERATION.set(advice)
  try:
    yield
  finally:
    _REFUSING_GENERATION.reset(token)


def _may_write(what: str) -> None:
  advice = _REFUSING_GENERATION.get()
  if advice is not None:
    raise GenerationRefused(f"not writing {what}: {advice}")


def _publish(root: pathlib.Path, parts: tuple[str, ...], write: Callable[[pathlib.Path], object]):
  """Writes a generated set into a private sibling folder, then renames each part into `root`.

  Every process of a multi-process run prepares its data before `jax.distributed` starts (the
  generator forks), so several may write the same set at once: none ever reads a half-written
  part, and a part another process published first is kept (this process's copy is dropped).
  """
  staging = root.parent / f".{root.name}.{os.getpid()}.partial"
  shutil.rmtree(staging, ignore_errors=True)
  write(staging)
  root.mkdir(parents=True, exist_ok=True)
  for part in parts:
    try:
      os.rename(staging / part, root / part)
    except OSError:  # published by another process meanwhile
      pass
  shutil.rmtree(staging, ignore_errors=True)


def _discard(path: pathlib.Path) -> None:
  """Removes a published part, renamed aside first so no process reads it half-deleted (one that
  another process discarded meanwhile is skipped)."""
  aside = path.with_name(f".{path.name}.{os.getpid()}.stale")
  try:
    os.rename(path, aside)
  except FileNotFoundError:
    return
  if aside.is_dir():
    shutil.rmtree(aside)
  else:
    aside.unlink()


def ensure_generated_set(
  root: pathlib.Path,
  parts: tuple[str, ...],
  settings: dict,
  write: Callable[[pathlib.Path], object],
  *,
  stamp: str,
  what: str,
  replace_other_settings: bool = False,
) -> None:
  """Makes `root` hold the generated set `settings` describes, unless it holds it already.

  `write(staging_root)` writes every part; the settings are recorded in the stamp (`stamp`,
  relative to `root`: a part, or a file inside one) and the set is published whole (`_publish`),
  so an interrupted run never leaves a set that is later taken as complete. The set is there
  when every part but the stamp exists.

  Raises ValueError if it is there without a stamp (written by a version that did not record its
  settings, or not by this code at all) or, unless `replace_other_settings` (then it is written
  anew), with other settings: using it would silently not be the experiment asked for; and
  GenerationRefused where it would write under `refusing_generation`.
  """
  wanted = json.loads(json.dumps(settings))  # tuples -> lists, as read back
  there = all((root / part).exists() for part in parts if part != stamp)
  found = json.loads((root / stamp).read_text()) if there and (root / stamp).exists() else None
  if there and found == wanted:
    return
  if there and (found is None or not replace_other_settings):
    raise ValueError(
      f"{(root / stamp).parent} holds a synthetic set written with other settings "
      f"({found or 'not recorded'}; this experiment needs {wanted}): delete it or pass "
      "another --synthetic-dir"
    )
  _may_write(what)
  if there:
    for part in parts:
      _discard(root / part)
  print(f"[data] writing {what}", flush=True)
  start = time.perf_counter()

  def write_stamped(staging: pathlib.Path):
    write(staging)
    (staging / stamp).write_text(json.dumps(wanted, indent=1))

  _publish(root, parts, write_stamped)
  print(f"[data] written in {time.perf_counter() - start:.1f} s", flush=True)


def _generator_settings(experiment: Experiment) -> dict:
  """What the synthetic set's content depends on (`generator.json` beside `train/`, `test/`)."""
  s = experiment.synthetic
  return {
    "num_train": s.num_train,
    "num_test": s.num_test,
    "frames": s.frames,
    "family": s.family,
    "true_depths": "every split",  # sets from before the depth files lack them
    "walk": dataclasses.asdict(s.walk),
    "image_size": list(experiment.image_size),
    "seed": experiment.seed,
  }


def _room_family(settings: SyntheticSettings):
  """The writer's settings of the training family `settings.family`."""
  from tokengs_jax.data.synthetic import Re10kLikeConfig, RoomConfig, VariedRoomConfig

  if settings.family == "varied":
    return Re10kLikeConfig(fov_x_degrees=(45.0, 95.0), room=VariedRoomConfig())
  return Re10kLikeConfig(room=RoomConfig(walk=settings.walk))


def ensure_synthetic(experiment: Experiment) -> pathlib.Path:
  """Writes the synthetic RE10K-format set unless it is already there; returns its root.

  Raises ValueError if `synthetic_dir` holds a set written with other settings (or by a version
  that did not record them): training on it would silently not be the experiment asked for.
  """
  root = pathlib.Path(experiment.synthetic_dir)
  s = experiment.synthetic

  def write(staging: pathlib.Path):
    from tokengs_jax.data.synthetic import generate_re10k_like  # only needed to write the set

    generate_re10k_like(
      staging,
      s.num_train,
      s.num_test,
      *experiment.image_size,
      frames=s.frames,
      seed=experiment.seed,
      config=_room_family(s),
      workers=s.workers,
    )

  ensure_generated_set(
    root,
    ("generator.json", "train", "test"),
    _generator_settings(experiment),
    write,
    stamp="generator.json",
    what=(
      f"the synthetic RE10K-format set to {root} ({s.num_train} train + {s.num_test} test "
      f"scenes, {s.frames} frames of {experiment.image_size})"
    ),
  )
  return root


def _ensure_test_family(experiment: Experiment, name: str, generate) -> pathlib.Path | None:
  """Writes a held-out test family of a synthetic run unless it is there; returns its root
  (`<synthetic_dir>/<name>`: `test/` chunks + `eval_index.json`), None for real data or
  `synthetic.num_ood = 0`. `generate(staging_root)` writes it."""
  s = experiment.synthetic
  if experiment.data_dir or s.num_ood <= 0:
    return None
  root = pathlib.Path(experiment.synthetic_dir) / name
  if (root / "eval_index.json").exists():
    return root
  what = f"{s.num_ood} held-out {name} scenes to {root}"
  _may_write(what)
  print(f"[data] writing {what}", flush=True)
  start = time.perf_counter()
  # The index last: its presence is what marks the set complete.
  _publish(root, ("test", "eval_index.json"), generate)
  print(f"[data] written in {time.perf_counter() - start:.1f} s", flush=True)
  return root


def ensure_galleries(experiment: Experiment) -> pathlib.Path | None:
  """The out-of-distribution gallery family (`generate_galleries`: polygonal rooms, other
  textures, objects, light and orbit cameras, 64x64 on disk; drawn with the experiment's seed).
  A validation family: the synthetic default's levers were chosen while looking at it."""
  from tokengs_jax.data.synthetic import generate_galleries

  s = experiment.synthetic
  return _ensure_test_family(
    experiment,
    "galleries",
    lambda staging: generate_galleries(staging, s.num_ood, seed=experiment.seed, workers=s.workers),
  )


def ensure_courtyards(experiment: Experiment) -> pathlib.Path | None:
  """The frozen test family (`generate_courtyards`: open courtyards, held-out photographs, a
  sideways tracking camera; the same scenes whatever the experiment's seed). No lever was chosen
  by looking at it (`tokengs_jax.data.synthetic.courtyards`)."""
  from tokengs_jax.data.synthetic import generate_courtyards

  s = experiment.synthetic
  return _ensure_test_family(
    experiment,
    "courtyards",
    lambda staging: generate_courtyards(staging, s.num_ood, workers=s.workers),
  )


def held_out_families(experiment: Experiment) -> dict[str, HeldOutSet]:
  """The synthetic run's extra test sets by name (their own index's views; every scene): the
  galleries (validation) and the frozen courtyards; empty for real data."""
  families = {
    "ood_galleries": ensure_galleries(experiment),
    "frozen_courtyards": ensure_courtyards(experiment),
  }
  return {
    name: HeldOutSet(root / "test", str(root / "eval_index.json"), 0)
    for name, root in families.items()
    if root is not None
  }


def data_root(experiment: Experiment) -> pathlib.Path:
  """`--data-dir` (its format checked now, before any work: `data_format`) or the synthetic set."""
  if experiment.data_dir and data_format(experiment):
    return pathlib.Path(experiment.data_dir)
  return ensure_synthetic(experiment)


def data_format(experiment: Experiment) -> str:
  """How `--data-dir` is read (`data_folder_format`): "chunks" (also the synthetic set) or
  "zips" (DL3DV scenes as they ship); ValueError for DL3DV scenes under another dataset's sampler
  and translation scale (the synthetic presets' `re10k`)."""
  if not experiment.data_dir:
    return "chunks"
  found = dl3dv.data_folder_format(experiment.data_dir, where="--data-dir ")
  if found == "zips" and experiment.dataset != "dl3dv":
    raise ValueError(
      f"--data-dir {experiment.data_dir} holds DL3DV scenes: pass --dataset dl3dv (this preset "
      f"has {experiment.dataset}'s sampler and translation scale)"
    )
  return found


def example_config(experiment: Experiment, *, training: bool) -> ExampleConfig:
  """Real data: the dataset's published preset; synthetic: a sampler sized for its short walks."""
  t, e = experiment.train, experiment.eval
  num_targets = t.num_target_views if training else e.num_target_views
  if experiment.data_dir:
    base = DATASET_PRESETS[experiment.dataset]
    sampler = dataclasses.replace(
      base.sampler, num_context_views=experiment.num_context_views, num_target_views=num_targets
    )
    config = dataclasses.replace(base, image_shape=experiment.image_size, sampler=sampler)
  else:
    low, high = (
      (t.min_context_gap, t.max_context_gap) if training else (e.context_gap, e.context_gap)
    )
    sampler = BoundedSamplerConfig(  # the gaps hold from step 0: no warm-up
      num_context_views=experiment.num_context_views,
      num_target_views=num_targets,
      min_context_gap=low,
      max_context_gap=high,
      min_target_distance=0,
      warm_up_steps=0,
      initial_min_context_gap=low,
      initial_max_context_gap=high,
    )
    config = ExampleConfig(
      experiment.image_size, sampler, DATASET_PRESETS["re10k"].translation_scale
    )
  if experiment.normalization is not None:  # None: the preset's camera frame
    config = dataclasses.replace(config, normalization=experiment.normalization)
  if not training:
    config = dataclasses.replace(config, random_flip=False, deterministic=True)
  elif t.lambda_depth > 0:
    config = dataclasses.replace(config, target_depths=True)
  return config


class _WithTrueDepths:
  """A chunk source whose records also carry their scenes' true depth maps (`depths` [F, H, W],
  from the files the synthetic writer keeps beside each chunk), for the depth loss."""

  def __init__(self, source: ChunkedSceneSource):
    if not isinstance(source, ChunkedSceneSource):
      raise ValueError("train.lambda_depth > 0 needs true depths: DL3DV scenes have none")
    self.source, self.rejections = source, source.rejections

  def __len__(self) -> int:
    return len(self.source)

  def __getitem__(self, index: int) -> dict:
    record = self.source[index]
    depths = read_true_depths(self.source.entries[index].chunk, record["key"])
    if depths is None:
      raise FileNotFoundError(
        f"{self.source.entries[index].chunk} scene '{record['key']}': no true depth recorded "
        "(train.lambda_depth > 0 needs a synthetic set that wrote them)"
      )
    return {**record, "depths": depths}


def local_batch_size(batch_size: int) -> int:
  """This process's share of the global batch of `batch_size` examples; raises ValueError
  unless every process gets the same share."""
  processes = jax.process_count()
  if batch_size % processes:
    raise ValueError(f"batch_size {batch_size} is not divisible by {processes} processes")
  return batch_size // processes


def training_batches(experiment: Experiment) -> InputPipeline:
  """This process's share of the global batch, forever, from `<root>/train` or the `data_mode`
  mix (`mixing.training_mix`), with the scenes' true depths when `train.lambda_depth > 0`."""
  local = local_batch_size(experiment.train.batch_size)  # before any data is written
  root, config = data_root(experiment), example_config(experiment, training=True)
  wrap = _WithTrueDepths if experiment.train.lambda_depth > 0 else (lambda source: source)
  if experiment.data_mode:  # several datasets, each repeated: the official data_mode
    source = mixing.training_mix(experiment.data_mode, config, experiment.eval_index, wrap)
  elif data_format(experiment) == "zips":  # held-out scenes left out, as test/ is for chunks
    source = dl3dv.dl3dv_training_source(root, held_out_index=experiment.eval_index, skip_bad=True)
  else:
    source = ChunkedSceneSource(root / "train", skip_bad=bool(experiment.data_dir))
  return InputPipeline(
    source if experiment.data_mode else wrap(source),
    config,
    batch_size=local,
    seed=experiment.seed,
    num_workers=experiment.train.num_workers,
    skip_bad=bool(experiment.data_dir or experiment.data_mode),
  )


@dataclasses.dataclass(frozen=True)
class HeldOutSet:
  """Where a held-out set's scenes are.

  Attributes:
    folder: the chunk folder (`*.torch` + `index.json`), or of DL3DV scenes (`data_format`).
    index_path: its evaluation index JSON (fixed views), or None: deterministic views.
    num_scenes: scenes scored (the first ones); 0 = all.
  """

  folder: pathlib.Path
  index_path: str | None
  num_scenes: int


def held_out_set(experiment: Experiment) -> HeldOutSet:
  """The experiment's own test split (`<root>/test`, `--eval-index`, `eval.num_scenes`); DL3DV
  scenes: `dl3dv_split`'s held-out root, which for one folder of scenes needs the index."""
  root, index = data_root(experiment), experiment.eval_index
  zips = data_format(experiment) == "zips"
  folder = dl3dv.dl3dv_held_out_root(root, indexed=bool(index)) if zips else root / "test"
  return HeldOutSet(folder, index, experiment.eval.num_scenes)


def _test_source(
  experiment: Experiment, held_out: HeldOutSet, index: dict | None
) -> tuple[ChunkedSceneSource, EvaluationIndexReport | None]:
  """The held-out folder (only the index's scenes when there is one) and, with an index, how it
  matches the data (`validate_evaluation_index`: unknown keys listed, an error when none matches
  or a frame is out of range), before any scene is decoded."""
  root = held_out.folder
  if data_format(experiment) == "zips":  # readable scenes only, counted as they are listed
    source = dl3dv.DL3DVSceneSource(root, keys=index and list(index), skip_bad=True)
    available = source.frame_counts() or dl3dv.DL3DVSceneSource(root).keys  # none: name them
    if index is None:
      return source, None
    return source, validate_evaluation_index(index, available, where=str(held_out.index_path))
  if index is None:
    return ChunkedSceneSource(root, skip_bad=bool(experiment.data_dir)), None
  source = ChunkedSceneSource(root, keys=list(index), skip_bad=True)
  available = {entry.key: entry.num_frames for entry in source.entries}
  if not available:  # name the split's scenes in the error, whatever their state
    available = list(json.loads((root / "index.json").read_text()))
  report = validate_evaluation_index(index, available, where=str(held_out.index_path))
  return source, report


def check_evaluation_data(experiment: Experiment) -> dict | None:
  """Raises before any training or scoring if the evaluation index cannot be used (or DL3DV
  scenes have no held-out ones, `held_out_set`); returns how it matches the data (for
  metrics.json), None without an index."""
  held_out = held_out_set(experiment) if experiment.data_dir or experiment.eval_index else None
  if not experiment.eval_index:
    return None
  return _test_source(experiment, held_out, _load_index(experiment, held_out))[1].as_dict()


def novel_targets(context: np.ndarray, num_targets: int) -> np.ndarray:
  """`num_targets` frames strictly inside the context span that are not input frames, as evenly
  spread as those free frames allow.  -> [num_targets] int64.

  The evaluation's targets without an index: the bounded sampler's deterministic targets span
  [first, last] and so include the two input frames themselves, which scores copying.
  """
  free = np.setdiff1d(np.arange(int(np.min(context)) + 1, int(np.max(context))), context)
  if len(free) < num_targets:
    raise ValueError(
      f"a context span {np.min(context)}-{np.max(context)} leaves {len(free)} "
      f"non-input frames for {num_targets} targets; widen eval.context_gap"
    )
  return free[np.linspace(0, len(free) - 1, num_targets).round().astype(np.int64)]


def _load_index(experiment: Experiment, held_out: HeldOutSet) -> dict | None:
  if not held_out.index_path:
    return None
  return load_evaluation_index(held_out.index_path, num_context=experiment.num_context_views)


def evaluation_scenes(
  experiment: Experiment, views: ViewChooser | None = None, held_out: HeldOutSet | None = None
) -> list[tuple[str, dict]]:
  """(scene key, batch of one) for the held-out scenes, with fixed views.

  Each batch also carries the frame numbers of its views, `context_frames` [1, Vc] and
  `target_frames` [1, Vt] (the nearest-input-view baseline reads them).

  views: optional chooser (studies use it for, e.g., extrapolated targets); default: the
    evaluation index, else the deterministic sampler's inputs and `novel_targets`.
  held_out: the scenes to read (default: the experiment's test split, `held_out_set`).
  """
  held_out = held_out_set(experiment) if held_out is None else held_out
  index = _load_index(experiment, held_out)
  source, _ = _test_source(experiment, held_out, index)
  count = len(source) if held_out.num_scenes <= 0 else min(held_out.num_scenes, len(source))
  config = example_config(experiment, training=False)
  scenes = []
  for position in range(count):
    record = source[position]
    if views is not None:
      chosen = views(record, position)
    elif index is not None:
      chosen = evaluation_views(index, record["key"], len(record["images"]))
    else:
      context, _ = sample_bounded(config.sampler, len(record["images"]), None, deterministic=True)
      chosen = context, novel_targets(context, config.sampler.num_target_views)
    entries = getattr(source, "entries", None)  # chunks only: DL3DV scenes have no true depth
    depths = entries and read_true_depths(entries[position].chunk, record["key"])
    if depths is not None:  # synthetic test sets: the evaluation also scores geometry
      record = {**record, "depths": depths}
    example = make_example(
      record,
      dataclasses.replace(config, target_depths=depths is not None),
      np.random.default_rng([experiment.seed, position]),
      views=chosen,
    )
    example["context_frames"], example["target_frames"] = (np.asarray(f, np.int64) for f in chosen)
    scenes.append((record["key"], {k: v[None] for k, v in example.items()}))
  return scenes
