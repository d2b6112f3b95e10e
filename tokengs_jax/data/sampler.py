"""Which frames of a scene become context and target views.

`BoundedSampler` follows pixelSplat's bounded view sampler (a context gap drawn between a minimum
and a maximum that warm up linearly with the training step; targets inside the context span), with
the official TokenGS extension to more than two context views (the extra ones drawn at random,
sorted, strictly inside the span). `evaluation_views` reads the fixed context/target frames of the
published evaluation index JSONs (pixelSplat/MVSplat/DepthSplat key -> {context, target} maps, and
the Long-LRM list format the official TokenGS DL3DV benchmark uses).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from collections.abc import Iterable, Mapping

import numpy as np

__all__ = [
  "BoundedSamplerConfig",
  "SAMPLER_PRESETS",
  "NotEnoughFramesError",
  "MissingIndexEntryError",
  "context_gap_bounds",
  "sample_bounded",
  "load_evaluation_index",
  "evaluation_views",
  "EvaluationIndexError",
  "EvaluationIndexReport",
  "validate_evaluation_index",
]


class NotEnoughFramesError(ValueError):
  """A scene has too few frames for the sampler's context gap or number of views."""


class MissingIndexEntryError(KeyError):
  """A scene has no (or a null) entry in the evaluation index."""

  def __str__(self):  # KeyError would print the message with quotes
    return str(self.args[0])


@dataclasses.dataclass(frozen=True)
class BoundedSamplerConfig:
  """Bounded view sampling; the names follow pixelSplat's `ViewSamplerBoundedCfg`.

  Attributes:
    num_context_views: context views per example (2 in pixelSplat; more as official TokenGS).
    num_target_views: target views per example, drawn with replacement inside the context span.
    min_context_gap / max_context_gap: bounds of (last - first context frame) after warm-up.
    min_target_distance: targets keep this many frames away from the outer context frames.
    warm_up_steps: steps over which the gap bounds move linearly from the initial values.
    initial_min_context_gap / initial_max_context_gap: the gap bounds at step 0.
  """

  num_context_views: int = 2
  num_target_views: int = 4
  min_context_gap: int = 45
  max_context_gap: int = 192
  min_target_distance: int = 0
  warm_up_steps: int = 0
  initial_min_context_gap: int = 45
  initial_max_context_gap: int = 192


# Published numbers (see docs/design.md, "Sampler", for the exact source of each).
SAMPLER_PRESETS = {
  # pixelSplat config/dataset/view_sampler_dataset_specific_config/bounded_re10k.yaml
  "pixelsplat_re10k": BoundedSamplerConfig(2, 4, 45, 192, 0, 150_000, 25, 45),
  # MVSplat trains RE10K with pixelSplat's bounded sampler and the same numbers
  "mvsplat_re10k": BoundedSamplerConfig(2, 4, 45, 192, 0, 150_000, 25, 45),
  # DepthSplat bounded_re10k.yaml
  "depthsplat_re10k": BoundedSamplerConfig(2, 4, 45, 135, 0, 30_000, 25, 45),
  # DepthSplat boundedv2_dl3dv.yaml (context_gap_warm_up_steps 10000)
  "depthsplat_dl3dv": BoundedSamplerConfig(2, 4, 20, 50, 0, 10_000, 15, 30),
  # official TokenGS registry "dl3dv" (min_gap 10, max_gap 40; num_views 8 = 4 context + 4 target)
  "tokengs_dl3dv": BoundedSamplerConfig(4, 4, 10, 40, 0, 0, 10, 40),
  # ours, for the 32-frame synthetic RE10K-like walks (tokengs_jax.data.synthetic, 3-8 cm per
  # frame, median depth ~3.8 m): gaps 8-24 give context baselines of ~0.11-0.34 x the median
  # depth (measured, docs/benchmarks.md); the warm-up starts at 4-12. Fits 32 frames (max gap 31).
  # Not the experiments' synthetic default, whose sampler `experiments.data.example_config`
  # builds from the experiment's gaps, without warm-up.
  "synthetic_32_frames": BoundedSamplerConfig(2, 4, 8, 24, 0, 5_000, 4, 12),
}


def context_gap_bounds(config: BoundedSamplerConfig, step: int) -> tuple[int, int]:
  """(min, max) context gap at a training step: linear warm-up as pixelSplat's `schedule`."""
  if config.warm_up_steps <= 0:
    return config.min_context_gap, config.max_context_gap
  fraction = step / config.warm_up_steps

  def schedule(initial, final):
    return min(initial + int((final - initial) * fraction), final)

  return (
    schedule(config.initial_min_context_gap, config.min_context_gap),
    schedule(config.initial_max_context_gap, config.max_context_gap),
  )


def sample_bounded(
  config: BoundedSamplerConfig,
  num_frames: int,
  rng: np.random.Generator,
  *,
  step: int = 0,
  deterministic: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
  """Draws context and target frame indices for a scene of `num_frames` frames.

  Training (`deterministic=False`): gap uniform in the warmed-up [min, max] (max clipped to
  num_frames - 1), first context frame uniform, targets uniform (with replacement) in
  [first + d, last - d], d = `min_target_distance`. `deterministic` (pixelSplat's test stage):
  the largest gap (clipped to the scene), starting at frame 0, and targets evenly spaced over the span (pixelSplat takes
  every frame of the span; evenly spaced keeps the batch shape fixed).

  Returns (context [num_context_views] int64 sorted, target [num_target_views] int64).
  Raises `NotEnoughFramesError` when the scene is too short.
  """
  if deterministic:  # pixelSplat's test stage: always the full final gap, no warm-up
    min_gap = max_gap = config.max_context_gap
  else:
    min_gap, max_gap = context_gap_bounds(config, step)
  max_gap = min(num_frames - 1, max_gap)
  if deterministic:  # a shorter scene uses all of its frames
    min_gap = min(min_gap, max_gap)
  min_gap = max(min_gap, 2 * config.min_target_distance, config.num_context_views - 1)
  if max_gap < min_gap:
    raise NotEnoughFramesError(
      f"{num_frames} frames cannot hold a context gap of at least {min_gap}"
    )
  gap = max_gap if deterministic else int(rng.integers(min_gap, max_gap + 1))
  first = 0 if deterministic else int(rng.integers(0, num_frames - gap))
  last = first + gap
  inner = np.arange(first + 1, last)
  if deterministic:
    middle = (
      inner[np.linspace(0, len(inner) - 1, config.num_context_views - 2).round().astype(int)]
      if config.num_context_views > 2
      else inner[:0]
    )
  else:
    middle = np.sort(rng.choice(inner, config.num_context_views - 2, replace=False))
  context = np.concatenate([[first], middle, [last]]).astype(np.int64)
  low, high = first + config.min_target_distance, last - config.min_target_distance
  if deterministic:
    target = np.linspace(low, high, config.num_target_views).round().astype(np.int64)
  else:
    target = rng.integers(low, high + 1, size=config.num_target_views).astype(np.int64)
  return context, target


# Long-LRM / official TokenGS DL3DV benchmark list entries: context frames under this key.
_LIST_CONTEXT_KEY = "fold_8_kmeans_{}_input"


def load_evaluation_index(
  path: str | os.PathLike, *, num_context: int | None = None
) -> dict[str, tuple[tuple[int, ...], tuple[int, ...] | None]]:
  """Reads an evaluation index JSON: fixed context/target frames per scene.

  Two formats:
  - pixelSplat/MVSplat/DepthSplat (e.g. `evaluation_index_re10k.json`,
    `dl3dv_start_0_distance_50_ctx_6v_tgt_8v.json`): scene key -> {"context": [...],
    "target": [...]} or null; null entries (scenes the benchmark leaves out) are dropped.
  - Long-LRM list (official TokenGS `DL3DVEval` with a list JSON): [{"scene_name": key,
    "fold_8_kmeans_16_input": [...], "fold_8_kmeans_32_input": [...]}, ...]; the context is the
    `fold_8_kmeans_{num_context}_input` list and the targets are every frame of the scene (as
    official), returned as `None` and expanded by `evaluation_views`.

  Args:
    num_context: which context list of the list format to read (16 or 32 in the released file);
      required for that format, ignored for the other.

  Returns:
    key -> (context frames, target frames or None = all frames), in file order.
  """
  with open(path) as handle:
    raw = json.load(handle)
  if isinstance(raw, dict):
    return _read_keyed_index(path, raw)
  if isinstance(raw, list):
    return _read_list_index(path, raw, num_context)
  raise ValueError(
    f"{path}: an evaluation index is a key -> entry map or a list of scene entries, "
    f"found {type(raw).__name__}"
  )


def _frame_list(path, key: str, field: str, value) -> tuple[int, ...]:
  if not (
    isinstance(value, list) and all(isinstance(i, int) and not isinstance(i, bool) for i in value)
  ):
    raise ValueError(f"{path}: entry for scene '{key}' needs '{field}' as a list of frame numbers")
  return tuple(value)


def _read_keyed_index(path, raw: dict) -> dict:
  index = {}
  for key, entry in raw.items():
    if entry is None:
      continue
    if not isinstance(entry, dict):
      raise ValueError(f"{path}: entry for scene '{key}' needs 'context' and 'target' lists")
    index[key] = (
      _frame_list(path, key, "context", entry.get("context")),
      _frame_list(path, key, "target", entry.get("target")),
    )
  return index


def _read_list_index(path, raw: list, num_context: int | None) -> dict:
  if num_context is None:
    raise ValueError(
      f"{path}: a list-format (Long-LRM) index needs num_context to pick "
      f"'{_LIST_CONTEXT_KEY.format('N')}'"
    )
  field = _LIST_CONTEXT_KEY.format(num_context)
  index = {}
  for position, entry in enumerate(raw):
    if entry is None:
      continue
    if not (isinstance(entry, dict) and isinstance(entry.get("scene_name"), str)):
      raise ValueError(f"{path}: list entry {position} needs a 'scene_name' string")
    key = entry["scene_name"]
    if field not in entry:
      raise ValueError(
        f"{path}: entry for scene '{key}' has no '{field}' "
        f"(has {sorted(k for k in entry if k != 'scene_name')})"
      )
    index[key] = (_frame_list(path, key, field, entry[field]), None)
  return index


def evaluation_views(index: dict, key: str, num_frames: int) -> tuple[np.ndarray, np.ndarray]:
  """The index's (context [Vc], target [Vt]) frames of scene `key`, checked against its length.

  A `None` target (list-format index) means every frame of the scene, as official.
  """
  if key not in index:
    raise MissingIndexEntryError(f"scene '{key}' has no entry in the evaluation index")
  context, target = index[key]
  context = np.asarray(context, np.int64)
  target = np.arange(num_frames, dtype=np.int64) if target is None else np.asarray(target, np.int64)
  frames = np.concatenate([context, target])
  if frames.size and (frames.min() < 0 or frames.max() >= num_frames):
    bad = int(frames.max()) if frames.max() >= num_frames else int(frames.min())
    raise NotEnoughFramesError(
      f"evaluation index asks for frame {bad} of a {num_frames}-frame scene"
    )
  return context, target


class EvaluationIndexError(ValueError):
  """An evaluation index does not fit the data (nothing matches, or frames out of range)."""


@dataclasses.dataclass(frozen=True)
class EvaluationIndexReport:
  """How an evaluation index matches the scenes available.

  Attributes:
    matched: index keys with a scene in the data, in index order (what gets evaluated).
    missing: index keys with no scene in the data, in index order.
    unindexed: number of available scenes the index does not name.
  """

  matched: tuple[str, ...]
  missing: tuple[str, ...]
  unindexed: int

  def as_dict(self) -> dict:
    """For metrics.json: what the scores cover and what was left out."""
    return {
      "requested": len(self.matched) + len(self.missing),
      "evaluated": len(self.matched),
      "missing": list(self.missing),
    }

  def summary(self) -> str:
    text = f"evaluation index: {len(self.matched)} of {len(self.matched) + len(self.missing)} scenes found"
    if self.missing:
      text += f"; missing {len(self.missing)}: {_listing(self.missing)}"
    return text


def _listing(keys, limit: int = 20) -> str:
  keys = list(keys)
  shown = ", ".join(repr(k) for k in keys[:limit])
  return shown + (f", ... ({len(keys) - limit} more)" if len(keys) > limit else "")


def validate_evaluation_index(
  index: Mapping,
  available: Iterable[str] | Mapping[str, int],
  *,
  where: str = "evaluation index",
  allow_missing: bool = True,
) -> EvaluationIndexReport:
  """Checks an evaluation index against the data before any work is done.

  Args:
    index: key -> (context, target) frames (`load_evaluation_index`).
    available: the keys of the scenes in the data (e.g. a source's `keys`), or key -> number of
      frames, which also checks every matched entry's frames are inside its scene.
    where: names the index (its file) in messages.
    allow_missing: False raises when any index key is missing; True (default) reports them (a
      warning on the `tokengs_jax.data` logger and in the returned report).

  Returns:
    The report (put `report.as_dict()` next to the metrics, so a subset is never silent).

  Raises:
    EvaluationIndexError: no index key matches the data (listing some of each, so a key-format
      mismatch is visible), any key is missing with `allow_missing=False`, or frames are out of
      range.
  """
  frames = available if isinstance(available, Mapping) else None
  available = list(available)
  present = set(available)
  matched = tuple(key for key in index if key in present)
  missing = tuple(key for key in index if key not in present)
  report = EvaluationIndexReport(matched, missing, len(present - set(index)))
  if not matched:
    raise EvaluationIndexError(
      f"{where}: none of its {len(index)} scenes is in the data ({len(present)} scenes). "
      f"Index keys: {_listing(index, 5)}; data keys: {_listing(sorted(present), 5)}"
    )
  if missing and not allow_missing:
    raise EvaluationIndexError(f"{where}: {report.summary()}")
  if frames is not None:
    bad = []
    for key in matched:
      try:
        evaluation_views(index, key, int(frames[key]))
      except NotEnoughFramesError as error:
        bad.append(f"'{key}': {error}")
    if bad:
      raise EvaluationIndexError(
        f"{where}: {len(bad)} entries ask for frames their scene does not "
        f"have: {'; '.join(bad[:10])}"
      )
  if missing:
    logging.getLogger("tokengs_jax.data").warning("%s: %s", where, report.summary())
  return report
