"""Kubric evaluation views: novel views at novel times, fixed by an index or by the default
protocol, the moving-pixel masks the evaluation scores on, and the object motion truth the
scene-flow metric (`tokengs_jax.scene_flow`) compares with.

A view is a (camera, frame) pair: `camera` numbers the tar `output_{camera:03d}.tar`, `frame` the
member `rgba_{frame:05d}.png`; pairs are int arrays [V, 2].

**Index** (`load_kubric_evaluation_index`): JSON `{"<scene>": {"context": [[camera, frame], ...],
"target": [[camera, frame], ...]}, ...}`; a null entry is a scene the benchmark leaves out.
Context views may be at different times (bullet time). `validate_kubric_evaluation_index` checks
it against the scenes before any work: unknown keys reported, an error when none matches, a camera
or frame outside its scene an error naming scene and entry.

**Default protocol** (`default_evaluation_views`, no index): the inputs are distinct cameras at
frames evenly spaced over a span of `max_gap` frames (the widest span training samples; at most
the clip); every target is at a frame strictly inside the span that is no input's frame, from the
cameras no input uses and the input cameras in turn. So no target is an input view, every target
is at an in-between time, and both a new viewpoint and an input viewpoint are scored there.

**Moving pixels**: where the scene changed between the nearest input time and the target, seen by
the target's own camera, whose frame at the nearest input time is the reference. From the
generator's truth where the scene has it (segmentations and object poses, as Kubric writes them;
`truth_motion_mask`): the pixels of the target or of the reference where an object is whose pose
differs between the two frames. Otherwise (data without that truth) an image rule,
`motion_mask`: each target pixel's surface point (its stored depth along the pixel-centre ray) is
projected into the reference camera, which may have moved, and the pixel is moving when the
reference colour there (bilinear) differs by more than `MOTION_THRESHOLD` in any channel; see
`MOTION_THRESHOLD` for its accuracy against the truth.

**Scene-flow truth** (`evaluation_fields`, scenes with that truth): each object's rigid motion
between the example's first and last frames (its times 0 and 1), points on its surface at the
first frame (every camera's depth and segmentation there) and its pixels in each target view, all
in the data's world; `tokengs_jax.scene_flow` carries them into the example's frame.
"""

from __future__ import annotations

import itertools
import json
import os
from collections.abc import Mapping

import numpy as np

from tokengs_jax.data.kubric.camera_tar import unproject_ray_depth
from tokengs_jax.data.kubric.source import KubricSceneSource
from tokengs_jax.data.sampler import (
  EvaluationIndexError,
  EvaluationIndexReport,
  NotEnoughFramesError,
  validate_evaluation_index,
)
from tokengs_jax.data.transforms import resize_and_center_crop_mask

# Colour change (any channel, images in [0, 1]) above which a pixel is moving. Measured on 36
# views of the synthetic Kubric-like scenes at 32x32, whose cameras drift along their orbit,
# against the truth (the target's own pose rendered at both times, a change above 4/255):
# reprojected at 16/255, IoU 0.70, 80 % of the moving pixels found, 15 % of the marked ones
# static; comparing the same pixel instead, IoU 0.59 with 31 % static (0.42 and 58 % at 4/255:
# the drift shifts every texture); reprojected at 4/255, IoU 0.44 (bilinear resampling of fine
# textures). It also leaves a margin for the sampling noise of path-traced (real Kubric) frames.
# Only data without motion truth uses it (`truth_motion_mask`).
MOTION_THRESHOLD = 16 / 255
# Surface points per object in the scene-flow truth (`object_points`): plenty for a nearest-point
# test, whatever the resolution and object size.
OBJECT_POINTS = 1024

ViewPairs = tuple[np.ndarray, np.ndarray]  # (context [Vc, 2], target [Vt, 2]) (camera, frame)


def _pairs(where: str, field: str, value) -> np.ndarray:
  """An index entry's list of [camera, frame] pairs.  -> int64 [V, 2]."""
  if not (isinstance(value, list) and value):
    raise EvaluationIndexError(
      f"{where} '{field}': needs a non-empty list of [camera, frame] pairs, got {value!r:.80}"
    )
  for position, pair in enumerate(value):
    if not (
      isinstance(pair, list)
      and len(pair) == 2
      and all(isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in pair)
    ):
      raise EvaluationIndexError(
        f"{where} '{field}' entry {position}: expected [camera, frame], two non-negative "
        f"integers, got {pair!r:.80}"
      )
  return np.asarray(value, np.int64)


def load_kubric_evaluation_index(path: str | os.PathLike) -> dict[str, ViewPairs]:
  """Reads a Kubric evaluation index (see the module docstring); null entries are dropped.

  Returns:
    scene key -> (context [Vc, 2], target [Vt, 2]) (camera, frame) pairs, in file order.

  Raises:
    EvaluationIndexError: not JSON, or any malformed entry (naming file, scene and entry).
  """
  try:
    with open(path) as handle:
      raw = json.load(handle)
  except json.JSONDecodeError as error:
    raise EvaluationIndexError(f"{path}: not JSON ({error})") from error
  if not isinstance(raw, dict):
    raise EvaluationIndexError(
      f"{path}: a Kubric evaluation index maps scene keys to {{'context': [[camera, frame], "
      f"...], 'target': [...]}}, found a {type(raw).__name__}"
    )
  index = {}
  for key, entry in raw.items():
    if entry is None:
      continue
    where = f"{path}: scene '{key}'"
    if not (isinstance(entry, dict) and set(entry) == {"context", "target"}):
      found = sorted(entry) if isinstance(entry, dict) else type(entry).__name__
      raise EvaluationIndexError(
        f"{where}: needs exactly 'context' and 'target' lists of [camera, frame], got {found}"
      )
    index[key] = (
      _pairs(where, "context", entry["context"]),
      _pairs(where, "target", entry["target"]),
    )
  return index


def _view_problems(
  key: str, views: ViewPairs, num_cameras: int, num_frames: int, num_context: int | None = None
) -> list[str]:
  """What is wrong with one scene's views (empty when nothing): a camera or frame outside the
  scene, naming the entry, or a context of another size than `num_context` (None: any)."""
  context, target = views
  problems = []
  if num_context is not None and len(context) != num_context:
    problems.append(f"scene '{key}': {len(context)} context views, the model takes {num_context}")
  for field, pairs in (("context", context), ("target", target)):
    for position, (camera, frame) in enumerate(np.asarray(pairs).tolist()):
      if camera >= num_cameras or frame >= num_frames:
        problems.append(
          f"scene '{key}' {field} entry {position} [camera {camera}, frame {frame}]: the scene "
          f"has cameras 0-{num_cameras - 1} and frames 0-{num_frames - 1}"
        )
  return problems


def validate_kubric_evaluation_index(
  index: Mapping[str, ViewPairs],
  source: KubricSceneSource,
  *,
  num_context: int | None = None,
  where: str = "evaluation index",
) -> EvaluationIndexReport:
  """Checks an index against a source's scenes before any work; reads only the matched scenes'
  metadata.

  Keys as `sampler.validate_evaluation_index` (index keys absent from the data are logged and
  reported; none matching is an error listing both), then every matched entry's views
  (`_view_problems`).

  Returns:
    The report (`report.as_dict()` goes into metrics.json).

  Raises:
    EvaluationIndexError: nothing matches, or any view is outside its scene or a context has
      another size than `num_context` (listing the first 10 problems).
  """
  report = validate_evaluation_index(index, source.keys, where=where)
  position = {key: i for i, key in enumerate(source.keys)}
  problems = []
  for key in report.matched:
    record = source[position[key]]
    problems += _view_problems(
      key, index[key], record["num_cameras"], record["num_frames"], num_context
    )
  if problems:
    raise EvaluationIndexError(
      f"{where}: {len(problems)} problems: {'; '.join(problems[:10])}"
      + (" ..." if len(problems) > 10 else "")
    )
  return report


def default_evaluation_views(
  num_cameras: int,
  num_frames: int,
  num_context: int,
  num_targets: int,
  max_gap: int,
  rng: np.random.Generator,
  context_cameras: int = 0,
) -> ViewPairs:
  """The default protocol's views of one scene (module docstring), drawn from `rng` (the start
  frame and the camera order; give a fixed seed per scene).

  Context v is camera order[v] at the v-th of `num_context` frames evenly spaced over
  `min(max_gap, num_frames - 1)` frames from a random start (cameras repeat when there are fewer
  than inputs; with `context_cameras` K > 0, the first K of the order in turn, as the training
  sampler's option). Targets take the frames strictly inside the span that no input uses, spread
  as the centres of `num_targets` equal bins, and cameras alternately from those no input uses and
  the input cameras.

  Returns:
    (context [Vc, 2], target [Vt, 2]) (camera, frame) pairs.

  Raises:
    NotEnoughFramesError: fewer than 2 inputs, or no frame inside the span is free.
  """
  span = min(max_gap, num_frames - 1)
  if num_context < 2 or span < num_context:
    raise NotEnoughFramesError(
      f"{num_context} inputs over {span + 1} frames (max_gap {max_gap}, {num_frames} frames) "
      f"leave no in-between frame for the targets: need at least 2 inputs and a span of "
      f"{max(num_context, 2)} frames"
    )
  start = int(rng.integers(0, num_frames - span))
  context_frames = start + np.round(np.linspace(0, span, num_context)).astype(np.int64)
  order = rng.permutation(num_cameras)
  used = order[: context_cameras or num_context]
  cameras = np.resize(used, num_context)
  free = np.setdiff1d(np.arange(start + 1, start + span), context_frames)
  target_frames = free[((np.arange(num_targets) + 0.5) * len(free) / num_targets).astype(np.int64)]
  unused, inputs = order[len(used) :], list(dict.fromkeys(cameras.tolist()))
  turns = [c for pair in itertools.zip_longest(unused, inputs) for c in pair if c is not None]
  target_cameras = np.resize(np.asarray(turns, np.int64), num_targets)
  return (
    np.stack([cameras, context_frames], -1).astype(np.int64),
    np.stack([target_cameras, target_frames], -1).astype(np.int64),
  )


def flat_views(record: dict, views: ViewPairs) -> tuple[np.ndarray, np.ndarray]:
  """(camera, frame) pairs -> the flat indices `camera * F + frame` of `KubricSceneSource`'s
  records (what `make_example(views=...)` takes).  -> (context [Vc], target [Vt])."""
  return tuple(pairs[:, 0] * record["num_frames"] + pairs[:, 1] for pairs in views)


def nearest_context_frames(views: ViewPairs) -> np.ndarray:
  """The input frame nearest each target's frame in time (ties: the earlier).  -> [Vt] int."""
  context, target = views
  times = np.unique(context[:, 1])  # sorted: argmin's first minimum is the earlier time
  return times[np.argmin(np.abs(target[:, 1:2] - times[None]), axis=-1)]


def _bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
  """`image [H, W, C]` at pixel coordinates (u, v) (pixel centres at +0.5), clamped to the border.
  -> [..., C] float64."""
  height, width = image.shape[:2]
  x = np.clip(u - 0.5, 0.0, width - 1.0)
  y = np.clip(v - 0.5, 0.0, height - 1.0)
  x0 = np.minimum(np.floor(x).astype(np.int64), max(width - 2, 0))
  y0 = np.minimum(np.floor(y).astype(np.int64), max(height - 2, 0))
  x1, y1 = np.minimum(x0 + 1, width - 1), np.minimum(y0 + 1, height - 1)
  fx, fy = (x - x0)[..., None], (y - y0)[..., None]
  image = np.asarray(image, np.float64)
  top = (1 - fx) * image[y0, x0] + fx * image[y0, x1]
  bottom = (1 - fx) * image[y1, x0] + fx * image[y1, x1]
  return (1 - fy) * top + fy * bottom


def motion_mask(
  target: np.ndarray,
  reference: np.ndarray,
  depth: np.ndarray | None,
  target_c2w: np.ndarray,
  reference_c2w: np.ndarray,
  intrinsics: np.ndarray,
) -> np.ndarray:
  """Pixels of a target view where the scene changed since a reference frame of the same camera.

  Each target pixel's surface point (`depth` along its pixel-centre ray; a pixel that hit nothing,
  depth 0, sees a direction, which only the camera's rotation moves) is projected into the
  reference camera; the pixel is moving when the reference colour there (bilinear) differs from
  its own by more than `MOTION_THRESHOLD` in any channel. A point outside the reference image or
  behind it is not moving (nothing to compare with). Without depth, each pixel is compared with
  the same pixel of the reference (exact for a camera that did not move).

  Args:
    target, reference: uint8 [H, W, 3] frames.
    depth: [H, W] the target's ray distance (Kubric's `depth_*.tiff`), or None.
    target_c2w, reference_c2w: [4, 4] OpenCV camera-to-world, in one world.
    intrinsics: [4] pixels (fx, fy, cx, cy), the camera's at both times.

  Returns:
    bool [H, W].
  """
  height, width = target.shape[:2]
  if depth is None:
    sampled, seen = np.asarray(reference, np.float64), np.ones((height, width), bool)
  else:
    target_c2w = np.asarray(target_c2w, np.float64)
    reference_c2w = np.asarray(reference_c2w, np.float64)
    depth = np.asarray(depth, np.float64)
    centre = target_c2w[:3, 3]
    rays = unproject_ray_depth(np.ones_like(depth), target_c2w, intrinsics) - centre
    hit = (depth > 0)[..., None]
    offset = np.where(hit, centre + depth[..., None] * rays - reference_c2w[:3, 3], rays)
    local = offset @ reference_c2w[:3, :3]  # R^T x: into the reference camera's axes
    fx, fy, cx, cy = np.asarray(intrinsics, np.float64)
    z = local[..., 2]
    safe_z = np.where(z > 0, z, 1.0)
    u, v = fx * local[..., 0] / safe_z + cx, fy * local[..., 1] / safe_z + cy
    seen = (z > 0) & (u >= 0) & (u <= width) & (v >= 0) & (v <= height)
    sampled = _bilinear(reference, u, v)
  change = np.abs(sampled - np.asarray(target, np.float64)).max(axis=-1) / 255.0
  return seen & (change > MOTION_THRESHOLD)


def moved_objects(poses: np.ndarray, reference_poses: np.ndarray) -> np.ndarray:
  """Which objects' poses differ between two times (beyond float noise).

  poses, reference_poses: [K, 4, 4] object-to-world -> bool [K].
  """
  return ~np.isclose(poses, reference_poses, rtol=0.0, atol=1e-6).all(axis=(-2, -1))


def truth_motion_mask(
  segmentation: np.ndarray, reference_segmentation: np.ndarray, moved: np.ndarray
) -> np.ndarray:
  """Pixels of a view where an object that moved since the reference time is, now or then.

  segmentation, reference_segmentation: int [H, W] instance numbers (k + 1 for object k, 0 the
  background) of one camera at the target and the reference time; moved: bool [K]
  (`moved_objects`).  -> bool [H, W].
  """
  moving = np.flatnonzero(moved) + 1
  return np.isin(segmentation, moving) | np.isin(reference_segmentation, moving)


def _object_points(record: dict, frame: int) -> np.ndarray:
  """`OBJECT_POINTS` points on each object's surface at `frame`: every camera's depth points there
  whose segmentation is the object, evenly subsampled (repeated when fewer).  -> float64
  [K, OBJECT_POINTS, 3] in the record's world; NaN for an object no camera sees."""
  num_frames = record["num_frames"]
  points, labels = [], []
  for camera in range(record["num_cameras"]):
    at = camera * num_frames + frame
    depth, segmentation = record["depths"][at], record["segmentations"][at]
    seen = (depth > 0) & (segmentation > 0)
    points.append(unproject_ray_depth(depth, record["c2w"][at], record["intrinsics"][at])[seen])
    labels.append(segmentation[seen])
  points, labels = np.concatenate(points), np.concatenate(labels)
  sampled = np.full((len(record["object_poses"]), OBJECT_POINTS, 3), np.nan)
  for k in range(len(sampled)):
    mine = points[labels == k + 1]
    if len(mine):
      sampled[k] = mine[np.linspace(0, len(mine) - 1, OBJECT_POINTS).round().astype(np.int64)]
  return sampled


def _motion_truth(
  record: dict, views: ViewPairs, image_shape: tuple[int, int], first: int, last: int
) -> dict:
  """The scene-flow truth fields of `evaluation_fields` (see there), between the example's
  `first` and `last` frames."""
  target = views[1]
  num_frames = record["num_frames"]
  poses = record["object_poses"]
  instances = np.arange(1, len(poses) + 1)[:, None, None]
  masks = np.concatenate(
    [record["segmentations"][c * num_frames + f][None] == instances for c, f in target.tolist()]
  )  # [Vt * K, H, W]
  resized = (
    resize_and_center_crop_mask(masks, image_shape) if len(masks) else np.zeros((0, *image_shape))
  )
  return {
    "world_c2w": np.asarray(record["c2w"], np.float64)[np.concatenate(flat_views(record, views))],
    "object_motions": poses[:, last] @ np.linalg.inv(poses[:, first]),
    "object_points": _object_points(record, first),
    "target_object_masks": resized.reshape(len(target), len(poses), *image_shape).astype(bool),
  }


def evaluation_fields(record: dict, views: ViewPairs, image_shape: tuple[int, int]) -> dict:
  """What a Kubric evaluation example carries besides `make_example`'s fields.

  Returns:
    `context_cameras [Vc]`, `target_cameras [Vt]` (int: the same-camera baseline reads them) and
    `target_motion_masks` bool [Vt, H, W]: each target's moving pixels against its camera's frame
    at the nearest input time (`nearest_context_frames`; module docstring), from the truth where
    the record has it (`truth_motion_mask`), else the image rule (`motion_mask`, with the
    target's depth map where its tar has one), at the stored resolution, then resized and cropped
    as the images; all False for a target at an input time.
    The truth needs the record's `object_poses` and the segmentations of the targets and their
    references. With depth maps and segmentations of every camera at the example's first frame
    as well, also the scene-flow truth, in the record's world:
    - `world_c2w [Vc + Vt, 4, 4]`: the views' cameras before the example normalised them (context
      views first), from which `scene_flow.example_similarity` reads that normalisation;
    - `object_motions [K, 4, 4]`: each object's rigid motion from the example's first frame to its
      last (its times 0 and 1): pose(last) pose(first)^-1;
    - `object_points [K, OBJECT_POINTS, 3]`: points on each object at the first frame
      (`_object_points`; NaN for an object no camera sees);
    - `target_object_masks` bool [Vt, K, H, W]: each object's pixels in each target view
      (resized and cropped as the images).

  record: a `KubricSceneSource` record; views: (context [Vc, 2], target [Vt, 2]) pairs.
  """
  context, target = views
  num_frames = record["num_frames"]
  references = nearest_context_frames(views)
  frames = np.concatenate([context[:, 1], target[:, 1]])
  first, last = int(frames.min()), int(frames.max())
  at_first = np.arange(record["num_cameras"]) * num_frames + first

  def present(field: str, items) -> bool:
    return all(record[field].present(i) for i in np.ravel(items).tolist())

  truth = "object_poses" in record and present(
    "segmentations",
    [target[:, 0] * num_frames + target[:, 1], target[:, 0] * num_frames + references],
  )
  flow_truth = truth and present("segmentations", at_first) and present("depths", at_first)
  masks = []
  for (camera, frame), reference in zip(target.tolist(), references.tolist()):
    at, before = camera * num_frames + frame, camera * num_frames + reference
    if truth:
      poses = record["object_poses"]
      mask = truth_motion_mask(
        record["segmentations"][at],
        record["segmentations"][before],
        moved_objects(poses[:, frame], poses[:, reference]),
      )
    else:
      mask = motion_mask(
        record["images"][at],
        record["images"][before],
        record["depths"][at] if record["depths"].present(at) else None,
        record["c2w"][at],
        record["c2w"][before],
        record["intrinsics"][at],
      )
    masks.append(mask)
  return {
    "context_cameras": context[:, 0].copy(),
    "target_cameras": target[:, 0].copy(),
    "target_motion_masks": resize_and_center_crop_mask(np.stack(masks), image_shape),
    **(_motion_truth(record, views, image_shape, first, last) if flow_truth else {}),
  }
