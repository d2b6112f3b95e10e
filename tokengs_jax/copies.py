"""Copy baselines: target views predicted by copying or averaging the input views (numpy).

The images of `evaluation.baselines()`; each takes a batch of the data contract and returns the
target-view predictions [B, Vt, H, W, 3]. A model that does not beat the best of them has not
learnt to render a new viewpoint (or, for dynamic scenes, a new time).
"""

from __future__ import annotations

import numpy as np


def mean_colour_images(batch: dict) -> np.ndarray:
  """Each target is the mean RGB of the input views.  -> [B, Vt, H, W, 3]."""
  mean = np.asarray(batch["context_images"]).mean(axis=(1, 2, 3))  # [B, 3]
  return np.broadcast_to(mean[:, None, None, None, :], batch["target_images"].shape).copy()


def input_average_images(batch: dict) -> np.ndarray:
  """Each target is the pixel-wise mean of the input views.  -> [B, Vt, H, W, 3]."""
  average = np.asarray(batch["context_images"]).mean(axis=1)  # [B, H, W, 3]
  return np.broadcast_to(average[:, None], batch["target_images"].shape).copy()


def nearest_views(batch: dict) -> np.ndarray:
  """Index of the input view nearest each target.  -> [B, Vt] int.

  By frame index (`context_frames` [B, Vc], `target_frames` [B, Vt]) when the batch has them
  (ties: the earlier input); otherwise by distance between camera centres.
  """
  if "context_frames" in batch and "target_frames" in batch:
    context = np.asarray(batch["context_frames"], np.int64)
    target = np.asarray(batch["target_frames"], np.int64)
    distance = np.abs(target[:, :, None] - context[:, None, :])
  else:
    distance = _centre_distances(batch)
  return np.argmin(distance, axis=-1)


def _centre_distances(batch: dict) -> np.ndarray:
  """Distance from each target's camera centre to each input's.  -> [B, Vt, Vc]."""
  context = np.asarray(batch["context_c2w"])[..., :3, 3]
  target = np.asarray(batch["target_c2w"])[..., :3, 3]
  return np.linalg.norm(target[:, :, None] - context[:, None, :], axis=-1)


# Normalised times closer than this are one instant (equal frame gaps can differ by float32
# rounding after the min-max normalisation).
_SAME_TIME = 1e-6


def _time_distances(batch: dict) -> np.ndarray:
  """|target time - input time| (`target_times` [B, Vt], `context_times` [B, Vc]).
  -> [B, Vt, Vc]."""
  context = np.asarray(batch["context_times"], np.float64)
  target = np.asarray(batch["target_times"], np.float64)
  return np.abs(target[:, :, None] - context[:, None, :])


def nearest_time_views(batch: dict) -> np.ndarray:
  """Index of the input view nearest each target in time (ties: the nearest camera centre, then
  the first input).  -> [B, Vt] int."""
  time = _time_distances(batch)
  tied = time <= time.min(axis=-1, keepdims=True) + _SAME_TIME
  return np.argmin(np.where(tied, _centre_distances(batch), np.inf), axis=-1)


def same_camera_views(batch: dict) -> np.ndarray:
  """Index of the input view from each target's own camera (`context_cameras` [B, Vc],
  `target_cameras` [B, Vt]) nearest it in time (ties: the first such input); where the target's
  camera has no input, the input with the nearest camera centre.  -> [B, Vt] int."""
  cameras = np.asarray(batch["target_cameras"])[:, :, None]
  same = cameras == np.asarray(batch["context_cameras"])[:, None, :]
  by_time = np.argmin(np.where(same, _time_distances(batch), np.inf), axis=-1)
  by_centre = np.argmin(_centre_distances(batch), axis=-1)
  return np.where(same.any(axis=-1), by_time, by_centre)


def _copies(batch: dict, chosen: np.ndarray) -> np.ndarray:
  """Each target is a copy of input view `chosen [B, Vt]`.  -> [B, Vt, H, W, 3]."""
  context = np.asarray(batch["context_images"])
  return context[np.arange(len(chosen))[:, None], chosen]


def nearest_view_images(batch: dict) -> np.ndarray:
  """Each target is a copy of its nearest input view (`nearest_views`).  -> [B, Vt, H, W, 3]."""
  return _copies(batch, nearest_views(batch))


def nearest_time_images(batch: dict) -> np.ndarray:
  """Each target is a copy of the input nearest it in time (`nearest_time_views`).
  -> [B, Vt, H, W, 3]."""
  return _copies(batch, nearest_time_views(batch))


def same_camera_images(batch: dict) -> np.ndarray:
  """Each target is a copy of its own camera's input nearest in time (`same_camera_views`).
  -> [B, Vt, H, W, 3]."""
  return _copies(batch, same_camera_views(batch))
