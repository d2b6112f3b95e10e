"""From scene records to fixed-shape training/evaluation batches, on grain.

Source-agnostic: any random-access sequence of scene records (see `tokengs_jax.data.chunked` for
the record fields) works. Per example: pick views (bounded sampler, an evaluation index, or a
caller's `select_views`), decode only those frames, resize-then-centre-crop, normalise cameras
(first_cam/mean_cam + translation scale), randomly flip, and convert images to float32 in [0, 1].
The "pointmap" scale (official Kubric preset) also reads the context views' depth maps from the
record's optional `depths` (a length-F sequence of float32 `[H, W]` arrays, TIFF bytes or
`LazyTensor`s, at the stored resolution). Kubric's hold the distance along each pixel's ray (not
planar z); `pointmap_scale` unprojects them exactly as the official provider does (as if z).

Batches are dicts of numpy arrays (docs/design.md): `context_images [B, Vc, H, W, 3]`,
`context_c2w [B, Vc, 4, 4]`, `context_intrinsics [B, Vc, 4]`, the same for `target_*`,
`scene_index [B]`, and for records with `times`: `context_times [B, Vc]`, `target_times [B, Vt]`;
`target_depths` / `target_objects` / `target_masks [B, Vt, H, W]`, `target_flows [B, Vt, H, W,
3]` where `ExampleConfig` asks for them.
"""

from __future__ import annotations

import dataclasses
import signal
from typing import Callable, Literal, Sequence

import grain
import numpy as np

from tokengs_jax import process
from tokengs_jax.data.chunks import ChunkError, LazyTensor, decode_jpeg
from tokengs_jax.data.chunks.images import check_frame_bytes, decode_image
from tokengs_jax.data import targets
from tokengs_jax.data.dl3dv import DL3DVError
from tokengs_jax.data.kubric import KubricError, pointmap_scale, sampling as kubric_sampling
from tokengs_jax.data.rejections import Rejections, summarize_rejections
from tokengs_jax.data.sampler import (
  SAMPLER_PRESETS,
  BoundedSamplerConfig,
  MissingIndexEntryError,
  NotEnoughFramesError,
  evaluation_views,
  sample_bounded,
)
from tokengs_jax.data.transforms import (
  flip_horizontal,
  normalize_cameras,
  normalize_times,
  resize_and_center_crop,
  resize_and_center_crop_depth,
  translation_scale,
)

__all__ = [
  "ExampleConfig",
  "DATASET_PRESETS",
  "TRANSLATION_SCALES",
  "make_example",
  "field_of_view",
  "InputPipeline",
  "BadExampleError",
  "NoUsableExamplesError",
]

# Paper, training details: camera translations scaled so that mean depths are roughly 1. The
# synthetic RE10K-like rooms have a median depth of ~3.8 m (measured, docs/benchmarks.md), so RE10K's
# 0.25 also brings them to ~1. (Kubric scales by its depth maps instead: "pointmap".)
TRANSLATION_SCALES = {"re10k": 0.25, "dl3dv": 0.15, "synthetic": 0.25}


class BadExampleError(ValueError):
  """An example could not be built; the message names the file and scene."""


class NoUsableExamplesError(RuntimeError):
  """The pipeline rejected `max_consecutive_bad` examples in a row: the data (or the sampler's
  settings for it) yields nothing, and waiting longer would hang the run."""


@dataclasses.dataclass(frozen=True)
class ExampleConfig:
  """How one example is built from a scene record.

  Attributes:
    image_shape: (H, W) of every output view.
    sampler: bounded view sampling (ignored when an evaluation index or `select_views` is given).
    translation_scale: base camera translation scale (RE10K 0.25, DL3DV 0.15; the official
      Kubric preset uses 1.0 with `pointmap`).
    normalization: `first_cam` (official default) or `mean_cam`.
    scale_method: `constant` (official default), `distance`, `bound`, or `pointmap`
      (`translation_scale` / mean distance from the origin of the context views' depth points
      between quantiles `pointmap_trim_lo` / `_hi`, 0 / 1: all; official Kubric; needs `depths`).
    random_flip: flip each example left-right with probability 1/2 (training).
    deterministic: pixelSplat's test-stage sampling, no flip (validation without an index).
    max_fov_degrees: reject the scene (`BadExampleError`) if any of its frames (all of the record's
      frames, not only the chosen views) has a horizontal or vertical field of view strictly above
      this, in degrees. The FOV is the angle between the rays through the middles of opposite image
      edges, so an off-centre principal point counts. None: off (default).
    min_context_baseline: reject the example if its two context camera centres, in the record's
      raw world units (before normalisation and translation scaling), are strictly closer than
      this. Not checked with more or fewer than 2 context views. None: off (default).
    target_depths: also return `target_depths [Vt, H, W]`, the record's true depth maps of the
      target views (`depths`, as `pointmap` reads them; 0 where nothing was hit) resized and
      cropped as the images and scaled as the cameras, so that they compare with rendered depth
      (the evaluation's geometry scores; synthetic test sets record them).
    target_objects: also return `target_objects [Vt, H, W]` float32, 1 on the target pixels
      where the record's `segmentations` show an object (instance number > 0), resized and
      cropped as the images (`resize_and_center_crop_mask`) and flipped with them (the dynamic
      auxiliary loss on the objects, `losses.LossConfig.dyn_aux_on_objects`).
    target_masks: also return `target_masks [Vt, H, W]` float32 in [0, 1], the targets'
      foreground masks (the record's `alphas`: Kubric's PNG alpha / 255), resized and cropped as
      the images and flipped with them (the official mask loss, `losses.LossConfig.lambda_mask`).
    target_flows: also return `target_flows [Vt, H, W, 3]` float32, the velocity each target pixel
      sees (`targets.target_flows`; the scene-flow loss, `losses.LossConfig.lambda_flow`).

  The last two reproduce pixelSplat/MVSplat's RE10K filters (`src/dataset/dataset_re10k.py`:
  `max_fov: 100.0` and, with `make_baseline_1`, `baseline_epsilon: 1e-3` in
  `config/dataset/re10k.yaml`). They are off in `DATASET_PRESETS`: the official TokenGS pipeline
  normalises cameras itself and is not known to filter (not checked against its code).
  """

  image_shape: tuple[int, int] = (256, 256)
  sampler: BoundedSamplerConfig = SAMPLER_PRESETS["depthsplat_re10k"]
  translation_scale: float = TRANSLATION_SCALES["re10k"]
  normalization: Literal["first_cam", "mean_cam"] = "first_cam"
  scale_method: Literal["constant", "distance", "bound", "pointmap"] = "constant"
  random_flip: bool = True
  deterministic: bool = False
  max_fov_degrees: float | None = None
  min_context_baseline: float | None = None
  target_depths: bool = False
  target_objects: bool = False
  target_masks: bool = False
  target_flows: bool = False
  pointmap_trim_lo: float = 0.0
  pointmap_trim_hi: float = 1.0

  def __post_init__(self):
    kubric_sampling.check_pointmap_trim(self.pointmap_trim_lo, self.pointmap_trim_hi)


DATASET_PRESETS = {
  "re10k": ExampleConfig(
    (256, 256), SAMPLER_PRESETS["depthsplat_re10k"], TRANSLATION_SCALES["re10k"]
  ),
  "dl3dv": ExampleConfig((256, 448), SAMPLER_PRESETS["tokengs_dl3dv"], TRANSLATION_SCALES["dl3dv"]),
  # the embedded generator's set (`tokengs_jax.data.synthetic`: 32-frame walks at 64x64 by
  # default); the experiments' synthetic default builds its own (`experiments.data`)
  "synthetic": ExampleConfig(
    (64, 64), SAMPLER_PRESETS["synthetic_32_frames"], TRANSLATION_SCALES["synthetic"]
  ),
  # official `finetune_dl3dv_kubric_dyn` + registry: 256x256, mean_cam, pointmap scale 1.0.
  # Pass `kubric_view_selector(4, 4, 3, 23)` as `select_views`: the bounded sampler, here only
  # a record of the official view counts and gaps, would mix cameras. Needs the records' `depths`.
  "kubric": ExampleConfig(
    (256, 256), BoundedSamplerConfig(4, 4, 3, 23, 0, 0, 3, 23), 1.0, "mean_cam", "pointmap"
  ),
}

# Errors that mean "this scene cannot make an example" (raised, or skipped with `skip_bad`).
_DATA_ERRORS = (ChunkError, DL3DVError, KubricError, NotEnoughFramesError, MissingIndexEntryError)

ViewSelector = Callable[[dict, np.random.Generator, int], tuple[np.ndarray, np.ndarray]]


def _where(record: dict) -> str:
  return f"{record.get('source', '<memory>')} scene '{record['key']}'"


def _frame(record: dict, index: int) -> np.ndarray:
  """Frame `index` of a record as uint8 [H, W, 3], decoding JPEG bytes if needed."""
  frame = record["images"][index]
  if isinstance(frame, LazyTensor):
    frame = frame.load()
  if isinstance(frame, np.ndarray) and frame.ndim != 1:  # decoded pixels, not encoded bytes
    if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[-1] != 3:
      raise BadExampleError(
        f"{_where(record)} frame {index}: decoded frames must be uint8 "
        f"[H, W, 3] RGB, got {frame.dtype} {list(frame.shape)}"
      )
    return frame
  return decode_jpeg(frame, where=f"{_where(record)} frame {index}")


def _depth(record: dict, index: int) -> np.ndarray:
  """Depth map `index` of a record as float32 [H, W] (TIFF bytes read with PIL, as official)."""
  if "depths" not in record:
    raise BadExampleError(
      f"{_where(record)}: scale_method 'pointmap' needs depth maps, and the record has no 'depths'"
    )
  depth = record["depths"][index]
  if isinstance(depth, LazyTensor):
    depth = depth.load()
  if not isinstance(depth, np.ndarray):
    where = f"{_where(record)} depth {index}"
    check_frame_bytes(len(depth), where=where, error=BadExampleError)
    depth = decode_image(bytes(depth), where=where, error=BadExampleError).astype(np.float32)
  depth = depth[..., 0] if depth.ndim == 3 else depth
  if depth.shape != (record["height"], record["width"]):
    raise BadExampleError(
      f"{_where(record)} depth {index}: {depth.shape}, frames are "
      f"{(record['height'], record['width'])}"
    )
  return depth.astype(np.float32)


def field_of_view(intrinsics: np.ndarray, height: int, width: int) -> np.ndarray:
  """Horizontal and vertical field of view in degrees, as pixelSplat's `get_fov`.
  intrinsics: [..., 4] pixels (fx, fy, cx, cy) of `height` x `width` frames -> [..., 2] (x, y)."""
  fx, fy, cx, cy = np.moveaxis(np.asarray(intrinsics, np.float64), -1, 0)

  def ray(u, v):  # direction through pixel (u, v), unit length
    direction = np.stack(np.broadcast_arrays((u - cx) / fx, (v - cy) / fy, np.ones_like(fx)), -1)
    return direction / np.linalg.norm(direction, axis=-1, keepdims=True)

  # Rays through the middles of opposite edges, not 2 atan(W / 2 fx): pixelSplat's definition also
  # counts an off-centre principal point.
  left, right = ray(0.0, height / 2), ray(float(width), height / 2)
  top, bottom = ray(width / 2, 0.0), ray(width / 2, float(height))
  cosines = np.stack([(left * right).sum(-1), (top * bottom).sum(-1)], -1)
  return np.degrees(np.arccos(np.clip(cosines, -1.0, 1.0)))


def _check_filters(
  record: dict, config: ExampleConfig, context: np.ndarray, height: int, width: int
):
  """pixelSplat/MVSplat's RE10K example filters (see `ExampleConfig`); raises `BadExampleError`."""
  where = _where(record)
  if config.max_fov_degrees is not None:
    # All frames, as pixelSplat (it tests the scene's intrinsics, not the sampled views'). NaN in an
    # unused frame compares False there and here.
    with np.errstate(invalid="ignore"):
      fov = field_of_view(np.asarray(record["intrinsics"]), height, width)
      wide = fov > config.max_fov_degrees
    if wide.any():
      frame, axis = np.argwhere(wide)[0]
      raise BadExampleError(
        f"{where}: {('horizontal', 'vertical')[axis]} field of view "
        f"{fov[frame, axis]:.4f} deg of frame {frame} exceeds max_fov_degrees "
        f"{config.max_fov_degrees}"
      )
  if config.min_context_baseline is not None and len(context) == 2:
    # Raw record cameras: pixelSplat measures before it rescales the world.
    centres = np.asarray(record["c2w"], np.float64)[context, :3, 3]
    baseline = float(np.linalg.norm(centres[0] - centres[1]))
    if baseline < config.min_context_baseline:
      raise BadExampleError(
        f"{where}: context baseline {baseline:.6g} (frames {context.tolist()}) is "
        f"below min_context_baseline {config.min_context_baseline}"
      )


def make_example(
  record: dict,
  config: ExampleConfig,
  rng: np.random.Generator,
  *,
  step: int = 0,
  views: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict:
  """One example (no batch axis) from a scene record; keys as the batch without the leading `B`.

  views: fixed (context [Vc], target [Vt]) frame indices; default: the bounded sampler.
  Raises `BadExampleError` (naming file and scene) for any unusable scene.
  """
  where = _where(record)
  c2w_all = np.asarray(record["c2w"])
  try:
    if views is None:
      views = sample_bounded(
        config.sampler, c2w_all.shape[0], rng, step=step, deterministic=config.deterministic
      )
    context, target = views
    frames = np.concatenate([context, target])
    c2w = c2w_all[frames]
    intrinsics = np.asarray(record["intrinsics"])[frames]
    if not (np.isfinite(c2w).all() and np.isfinite(intrinsics).all()):
      raise BadExampleError(f"{where}: NaN/inf in the cameras of frames {frames.tolist()}")
    if intrinsics.shape != (len(frames), 4) or (intrinsics[:, :2] <= 0).any():
      raise BadExampleError(
        f"{where}: intrinsics of frames {frames.tolist()} must be [V, 4] "
        f"(fx, fy, cx, cy) pixels with fx, fy > 0, got {intrinsics.tolist()}"
      )
    images = np.stack([_frame(record, int(i)) for i in frames])
    depths = (
      np.stack([_depth(record, int(i)) for i in context])
      if config.scale_method == "pointmap"
      else None
    )
  except _DATA_ERRORS as error:
    raise BadExampleError(f"{where}: {error}") from error
  if images.shape[1:3] != (
    record.get("height", images.shape[1]),
    record.get("width", images.shape[2]),
  ):
    raise BadExampleError(
      f"{where}: frames are {images.shape[1:3]}, cameras are for "
      f"{(record['height'], record['width'])}"
    )
  _check_filters(record, config, np.asarray(context), images.shape[1], images.shape[2])
  raw_intrinsics = intrinsics
  images, intrinsics = resize_and_center_crop(images, intrinsics, config.image_shape)
  num_context = len(context)
  c2w = normalize_cameras(c2w, num_context, config.normalization)
  if config.scale_method == "pointmap":  # official: stored-resolution depth, normalised cameras
    trim = (config.pointmap_trim_lo, config.pointmap_trim_hi)
    scale = config.translation_scale / pointmap_scale(
      depths, c2w[:num_context], raw_intrinsics[:num_context], trim
    )
  else:
    scale = translation_scale(c2w, num_context, config.translation_scale, config.scale_method)
  flipped = config.random_flip and not config.deterministic and rng.random() < 0.5
  if flipped:
    images, c2w, intrinsics = flip_horizontal(images, c2w, intrinsics)
  c2w[:, :3, 3] *= scale
  images = images.astype(np.float32) / 255.0
  example = {
    "context_images": images[:num_context],
    "context_c2w": c2w[:num_context],
    "context_intrinsics": intrinsics[:num_context],
    "target_images": images[num_context:],
    "target_c2w": c2w[num_context:],
    "target_intrinsics": intrinsics[num_context:],
  }
  frame_times = np.asarray(record.get("times", np.zeros(len(c2w_all))), np.float64)[frames]
  if "times" in record:
    times = normalize_times(frame_times)
    example["context_times"], example["target_times"] = times[:num_context], times[num_context:]
  frame = (c2w[num_context:], scale, float(np.ptp(frame_times)))
  example.update(_target_maps(record, target, config, frame, flipped))
  return example


def _target_maps(record: dict, target, config: ExampleConfig, frame, flipped: bool):
  """The targets' truth `config` asks for, transformed as their images and cameras (`frame`: their
  example c2w [Vt, 4, 4], translation scale, span of frames): "target_depths" (float32 [Vt, H, W],
  0: unknown), "target_flows" and `targets.target_fields`."""
  target_c2w, scale, span = frame
  try:
    maps = targets.target_fields(record, target, config, flipped)
    if config.target_flows:
      maps["target_flows"] = targets.target_flows(
        record, target, target_c2w, scale, span, config, flipped
      )
    if config.target_depths:
      depths = np.stack([_depth(record, int(i)) for i in target])
      depths = resize_and_center_crop_depth(depths, config.image_shape) * scale
      maps["target_depths"] = (depths[:, :, ::-1] if flipped else depths).astype(np.float32)
  except (*_DATA_ERRORS, targets.MissingTargetField) as error:
    raise BadExampleError(f"{_where(record)}: {error}") from error
  return maps


@dataclasses.dataclass(frozen=True)
class _Skipped:
  reason: str
  message: str


class _BuildExample:
  """The per-index map (picklable, runs in the workers): a seeded example or a `_Skipped`."""

  def __init__(self, source, config, seed, batch_size, evaluation_index, select_views, skip_bad):
    self.source, self.config, self.seed, self.batch_size = source, config, seed, batch_size
    self.evaluation_index, self.select_views = evaluation_index, select_views
    self.skip_bad = skip_bad
    self.config_at = getattr(source, "example_config", None)  # per scene (`mixing.MixedSource`)

  def __call__(self, position: int, scene_index: int):
    rng = np.random.default_rng([self.seed, position])  # same example for the same position
    step = position // self.batch_size
    config = self.config_at(scene_index, self.config) if self.config_at else self.config
    try:
      record = self.source[scene_index]
      views = None
      if self.evaluation_index is not None:
        views = evaluation_views(self.evaluation_index, record["key"], len(record["images"]))
      elif self.select_views is not None:
        views = self.select_views(record, rng, step)
      example = make_example(record, config, rng, step=step, views=views)
    except (BadExampleError, *_DATA_ERRORS) as error:
      if not self.skip_bad:
        raise
      cause = error.__cause__ if isinstance(error, BadExampleError) else None
      return _Skipped(type(cause or error).__name__, str(error))  # the reason: the root cause
    example["scene_index"] = np.int64(scene_index)
    return example


class InputPipeline:
  """A grain pipeline of fixed-shape batches from a random-access source of scene records.

  Args:
    source: `len()` + `[i]` -> scene record; one with `example_config(i, config)` (a
      `mixing.MixedSource`) builds scene `i`'s example with the config that returns.
    config: how examples are built.
    batch_size: examples per batch on this process.
    seed: shuffling and per-example randomness (views, flips) derive from it and the position.
    shuffle / num_epochs: reshuffled every epoch; `num_epochs=None` repeats forever.
    shard_index / shard_count: this process's disjoint share of the scenes (default: JAX process
      index and count), for multi-host training.
    num_workers: decoding processes (0: in this process).
    evaluation_index: key -> (context, target) frames (see `sampler.load_evaluation_index`).
    select_views: custom `(record, rng, step) -> (context, target)`, e.g. for dynamic scenes.
    skip_bad: drop bad examples, counting and logging each in `rejections`, instead of raising.
    max_consecutive_bad: with `skip_bad`, raise `NoUsableExamplesError` after this many rejected
      examples in a row (e.g. every clip too short for the sampler) instead of waiting forever.

  Iterate it (or `iterator()`); the iterator's `get_state()` / `set_state()` checkpoint the
  position exactly. `rejection_summary()` reports what the source and the pipeline rejected.
  """

  def __init__(
    self,
    source: Sequence[dict],
    config: ExampleConfig,
    *,
    batch_size: int,
    seed: int = 0,
    shuffle: bool = True,
    num_epochs: int | None = None,
    shard_index: int | None = None,
    shard_count: int | None = None,
    num_workers: int = 0,
    evaluation_index: dict | None = None,
    select_views: ViewSelector | None = None,
    skip_bad: bool = False,
    drop_remainder: bool = True,
    max_consecutive_bad: int = 256,
  ):
    if shard_index is None or shard_count is None:
      import jax  # only for the process topology

      shard_index, shard_count = jax.process_index(), jax.process_count()
    self.source = source
    self.rejections = Rejections("pipeline")
    self.max_consecutive_bad = max_consecutive_bad
    self._consecutive_bad = 0
    scenes = grain.MapDataset.range(len(source))[shard_index::shard_count]
    if len(scenes) == 0:
      raise NoUsableExamplesError(
        f"no scenes for shard {shard_index} of {shard_count}: the source has {len(source)}"
        + (f" ({self.rejection_summary()})" if _source_rejections(source) else "")
      )
    if shuffle:
      scenes = scenes.shuffle(seed=seed)
    scenes = scenes.repeat(num_epochs)
    build = _BuildExample(
      source, config, seed, batch_size, evaluation_index, select_views, skip_bad
    )
    examples = scenes.map_with_index(build).to_iter_dataset()
    if num_workers > 0:
      from absl import flags  # grain's worker pool reads absl flags; outside absl.app use defaults

      if not flags.FLAGS.is_parsed():
        flags.FLAGS.mark_as_parsed()
      examples = examples.mp_prefetch(
        grain.MultiprocessingOptions(num_workers=num_workers), worker_init_fn=_start_worker
      )
    self.dataset = examples.filter(self._keep).batch(batch_size, drop_remainder=drop_remainder)

  def _keep(self, example) -> bool:
    if not isinstance(example, _Skipped):
      self._consecutive_bad = 0
      return True
    self.rejections.add(example.reason, example.message)
    self._consecutive_bad += 1
    if self._consecutive_bad >= self.max_consecutive_bad:
      raise NoUsableExamplesError(
        f"the last {self._consecutive_bad} examples were all rejected (max_consecutive_bad); "
        f"nothing to train on.\n{self.rejection_summary()}"
      )
    return False

  def rejection_summary(self) -> str:
    """What the source (when it keeps a `rejections` log) and the pipeline rejected so far."""
    logs = {}
    if _source_rejections(self.source) is not None:
      logs["source"] = _source_rejections(self.source)
    logs["pipeline"] = self.rejections
    return summarize_rejections(logs)

  def iterator(self):
    return iter(self.dataset)

  def __iter__(self):
    return self.iterator()


def _start_worker(worker_index: int, worker_count: int) -> None:
  """Runs first in each decoding process. Ctrl-C reaches the whole foreground process group: the
  main process handles SIGINT (the training loop stops between steps) and then ends its workers,
  so a worker ignores it instead of dying under a batch the main process still waits for. A
  worker also ends with its main process when that one is killed."""
  del worker_index, worker_count
  signal.signal(signal.SIGINT, signal.SIG_IGN)
  process.exit_with_parent()


def _source_rejections(source) -> Rejections | None:
  return getattr(source, "rejections", None)
