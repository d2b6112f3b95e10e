"""The target views' per-pixel truth beyond their images, for `pipeline.make_example`.

`target_objects [Vt, H, W]` (where the record's `segmentations` show an object),
`target_masks [Vt, H, W]` (the foreground masks: the record's `alphas`, Kubric's PNG alpha) and
`target_flows [Vt, H, W, 3]` (the scene flow each pixel sees, from Kubric's depth maps,
segmentations and per-frame object poses), each resized, cropped and mirrored as `make_example`
did the target images. A record without the field (or without it for a chosen frame) raises
`MissingTargetField`, which the pipeline reports as a bad example.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from tokengs_jax.data.kubric.camera_tar import check_finite_depth, unproject_ray_depth
from tokengs_jax.data.transforms import (
  resize_and_center_crop,
  resize_and_center_crop_mask,
  resize_and_center_crop_values,
)


class MissingTargetField(ValueError):
  """The record lacks a per-pixel field an example was asked to carry."""


def target_fields(record: dict, target: Sequence[int], config, flipped: bool) -> dict:
  """The fields `config` (a `pipeline.ExampleConfig`) asks for, of the record's target frames
  `target` [Vt], as float32 [Vt, H, W] at `config.image_shape`, mirrored left-right when the
  images were (`flipped`): "target_objects" (1 on object pixels) with `config.target_objects`,
  "target_masks" (alpha / 255, 1: foreground) with `config.target_masks`."""
  image_shape, fields = config.image_shape, {}
  if config.target_objects:
    segmentations = _read(record, "segmentations", target, "target_objects")
    fields["target_objects"] = resize_and_center_crop_mask(segmentations > 0, image_shape)
  if config.target_masks:
    alphas = _read(record, "alphas", target, "target_masks")
    # the images' own resize (official: the masks go through the images' transform), on the
    # alpha repeated into the three channels that transform takes
    rgb = np.repeat(alphas.astype(np.uint8)[..., None], 3, axis=-1)
    resized, _ = resize_and_center_crop(rgb, np.zeros((len(target), 4), np.float32), image_shape)
    fields["target_masks"] = resized[..., 0] / 255.0
  return {
    name: np.ascontiguousarray(value[:, :, ::-1] if flipped else value).astype(np.float32)
    for name, value in fields.items()
  }


def _read(record: dict, field: str, target: Sequence[int], purpose: str) -> np.ndarray:
  """The record's `field` at the frames `target`, stacked; `MissingTargetField` naming `purpose`
  if the record (or one of those frames: a lazy sequence's `.present(i)`) has none."""
  if field not in record:
    raise MissingTargetField(f"{purpose} needs the record's '{field}'")
  frames = record[field]
  missing = [int(i) for i in target if hasattr(frames, "present") and not frames.present(int(i))]
  if missing:
    raise MissingTargetField(f"{purpose} needs {field}, none for frames {missing}")
  return np.stack([np.asarray(frames[int(i)]) for i in target])


def target_flows(
  record: dict,
  target: Sequence[int],
  example_c2w: np.ndarray,
  scale: float,
  span: float,
  config,
  flipped: bool,
) -> np.ndarray:
  """The velocity of the surface point each target pixel sees, in the example's frame and per
  unit of its normalised time (`transforms.normalize_times` of the example's frames).

  A pixel on object k (segmentation k + 1) at frame f sees the point X its depth map places in
  the world; the point moves with the object's rigid motion, and its velocity is the central
  difference (M_k(f+1) - M_k(f-1)) M_k(f)^-1 X / 2 frames (one-sided at the clip's ends). The
  background and pixels that saw nothing do not move (0). A velocity turns into the example's
  frame as its cameras did: through the target camera's frame (mirrored with the images when
  `flipped`), times the example's translation `scale`, times its span of frames (normalised time
  runs 0 to 1 over it).

  Args:
    record: a Kubric scene record with "depths", "segmentations", "object_poses" [K, F, 4, 4],
      "times" (frame indices), "c2w" and "intrinsics".
    target: [Vt] the record's frame indices of the target views.
    example_c2w: [Vt, 4, 4] the same views' cameras in the example (normalised, scaled, flipped).
    scale: the example's translation scale.
    span: frames between the example's first and last view (its normalised time's unit).
    config: the `pipeline.ExampleConfig` (its `image_shape`).
    flipped: whether the example mirrored its images.

  Returns:
    float32 [Vt, H, W, 3] at `config.image_shape`.

  Raises:
    MissingTargetField: the record lacks a field (or a target frame's map).
    KubricError: a target frame's depth map holds NaN or inf.
  """
  if "object_poses" not in record:
    raise MissingTargetField("target_flows needs the record's 'object_poses'")
  depths = _read(record, "depths", target, "target_flows").astype(np.float64)
  # a damaged map would give its object pixels NaN velocities, and the step a NaN loss
  check_finite_depth(depths, f"target_flows: the depth maps of frames {[int(i) for i in target]}")
  segmentations = _read(record, "segmentations", target, "target_flows")
  poses = np.asarray(record["object_poses"], np.float64)  # [K, F, 4, 4]
  times = np.asarray(record["times"])
  flows = []
  for view, index in enumerate(target):
    world_c2w = np.asarray(record["c2w"][index], np.float64)
    points = unproject_ray_depth(depths[view], world_c2w, record["intrinsics"][index])
    velocity = _object_velocities(points, segmentations[view], poses, int(times[index]))
    camera = velocity @ world_c2w[:3, :3]  # world -> camera frame (row vectors)
    if flipped:
      camera[..., 0] *= -1.0
    flows.append(camera)
  flows = np.stack(flows)
  channels = [resize_and_center_crop_values(flows[..., c], config.image_shape) for c in range(3)]
  flows = np.stack(channels, -1)
  if flipped:
    flows = flows[:, :, ::-1]
  example = flows @ np.transpose(np.asarray(example_c2w, np.float64)[:, None, :3, :3], (0, 1, 3, 2))
  return np.ascontiguousarray(example * scale * span, np.float32)


def _object_velocities(points, segmentation, poses, frame: int) -> np.ndarray:
  """[H, W, 3] world velocity per frame of the points [H, W, 3] on the objects `segmentation`
  [H, W] numbers (k + 1), under the objects' poses [K, F, 4, 4] at `frame`; 0 elsewhere."""
  num_frames = poses.shape[1]
  before, after = max(frame - 1, 0), min(frame + 1, num_frames - 1)
  velocity = np.zeros_like(points)
  if after == before:
    return velocity
  for k in range(poses.shape[0]):
    on = segmentation == k + 1
    if not on.any():
      continue
    motion = (poses[k, after] - poses[k, before]) @ np.linalg.inv(poses[k, frame])
    velocity[on] = (points[on] @ motion[:3, :3].T + motion[:3, 3]) / (after - before)
  return velocity
