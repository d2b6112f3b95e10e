"""What the pipeline draws from a Kubric scene record: the official views and translation scale.

`sample_dynamic_indices` is the official `_get_indices_dynamic`; `kubric_view_selector` wraps it
as a pipeline `select_views` over `KubricSceneSource`'s flattened records; `pointmap_scale` is the
official "pointmap" scene scale from the context views' depth maps.
"""

from __future__ import annotations

import numpy as np

from tokengs_jax.data.kubric.camera_tar import check_finite_depth
from tokengs_jax.data.sampler import NotEnoughFramesError


def sample_dynamic_indices(
  rng: np.random.Generator,
  num_frames: int,
  num_cameras: int,
  num_context: int,
  min_gap: int = 3,
  max_gap: int = 23,
  interp_target: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
  """Official `_get_indices_dynamic`, with the same draws from `rng` in the same order.

  Returns:
    frames [num_context + 1] (increasing context frames spanning the gap, then the target frame,
    anywhere in the span when `interp_target`, else one of the context frames) and
    cameras [num_context] (distinct cameras; repeated in a shuffled cycle when there are fewer).
  """
  if num_frames < num_context:
    raise NotEnoughFramesError(f"{num_frames} frames are fewer than {num_context} context views")
  gap = int(rng.integers(min_gap, max_gap + 1))
  gap = max(min(num_frames - 1, gap), num_context - 1)
  start = int(rng.integers(0, num_frames - gap))
  between = np.sort(rng.permutation(np.arange(start + 1, start + gap))[: num_context - 2])
  frames = np.array([start, *between, start + gap])
  target = rng.permutation(np.arange(start, start + gap + 1))[:1]
  if not interp_target:
    target = rng.permutation(frames)[:1]
  frames = np.concatenate([frames, target])
  if num_context > num_cameras:
    views = rng.permutation(np.arange(num_context) % num_cameras)
  else:
    views = rng.permutation(np.arange(num_cameras))[:num_context]
  return frames, views


def check_pointmap_trim(lo: float, hi: float) -> None:
  """ValueError unless 0 <= lo < hi <= 1 (the `pointmap_scale` trim's quantiles; the official
  provider silently falls back to no trim)."""
  if not 0.0 <= lo < hi <= 1.0:
    raise ValueError(
      f"pointmap_trim_lo / pointmap_trim_hi must satisfy 0 <= lo < hi <= 1 (quantiles of the "
      f"depth points' distances), got {lo} / {hi}"
    )


def pointmap_scale(
  depths: np.ndarray,
  c2w: np.ndarray,
  intrinsics: np.ndarray,
  trim: tuple[float, float] = (0.0, 1.0),
) -> float:
  """Mean distance from the origin of the points the depth maps see (official "pointmap").

  Unprojects every pixel with depth > 1e-8 exactly as the official `_compute_pointmap_scale`:
  point = depth x ((u - cx) / fx, (v - cy) / fy, 1) at integer pixel coordinates (no +0.5), i.e.
  it treats the stored value as planar z. Kubric's files hold the distance along the ray, so
  off-axis points land sqrt(1 + x^2 + y^2) too far (up to ~19 % at the corners of the 35 mm /
  32 mm lens); this is kept so the scale is the official one. `unproject_ray_depth` gives the
  true points. Optionally keeps only distances between the `trim` quantiles (official
  `pointmap_trim_lo` / `pointmap_trim_hi`, `np.quantile`'s linear rule as `torch.quantile`'s);
  returns the mean (1.0 when no pixel has depth).

  depths: [V, H, W] as stored (Kubric: ray distance), c2w: [V, 4, 4] (already normalised),
  intrinsics: [V, 4] pixels (of the stored resolution).

  Raises `KubricError` for a NaN or inf depth value (`check_finite_depth`: the official scale
  would be NaN, or 1.0 for NaN-only maps), ValueError for a trim outside 0 <= lo < hi <= 1.
  """
  check_pointmap_trim(*trim)
  check_finite_depth(depths, "the context views' depth maps")
  distances = []
  for depth, pose, (fx, fy, cx, cy) in zip(depths, np.asarray(c2w, np.float64), intrinsics):
    rows, cols = np.nonzero(depth > 1e-8)
    z = depth[rows, cols].astype(np.float64)
    points = np.stack([(cols - cx) / fx * z, (rows - cy) / fy * z, z], -1)
    distances.append(np.linalg.norm(points @ pose[:3, :3].T + pose[:3, 3], axis=-1))
  distances = np.concatenate(distances) if distances else np.zeros(0)
  if distances.size == 0:
    return 1.0
  lo, hi = trim
  if (lo > 0.0 or hi < 1.0) and distances.size > 1:
    kept = distances[
      (distances >= np.quantile(distances, lo)) & (distances <= np.quantile(distances, hi))
    ]
    distances = kept if kept.size else distances
  return float(max(distances.mean(), 1e-6))


def kubric_view_selector(
  num_context: int,
  num_targets: int,
  min_gap: int = 3,
  max_gap: int = 23,
  interp_target: bool = True,
  context_cameras: int = 0,
):
  """A pipeline `select_views(record, rng, step)` doing the official dynamic sampling on the
  flattened records of `KubricSceneSource`: context v = (camera v, frame v), target v =
  (camera v, target frame), returned as flat indices camera * F + frame.

  `context_cameras` K > 0 (not official) takes the inputs from K of the drawn cameras in turn
  (a, b, a, b, ... over the increasing input frames), so each of them is seen at several times
  and the scene's motion shows as a difference between two images of one camera; 0 keeps the
  official draw (distinct cameras while there are enough)."""
  if not 0 < num_targets <= num_context:
    raise ValueError(f"need 0 < targets ({num_targets}) <= context views ({num_context})")
  if context_cameras < 0:
    raise ValueError(f"context_cameras must be >= 0, got {context_cameras}")

  def select(record: dict, rng: np.random.Generator, step: int) -> tuple[np.ndarray, np.ndarray]:
    del step  # the official dynamic sampler has no warm-up
    num_frames = record["num_frames"]
    frames, cameras = sample_dynamic_indices(
      rng, num_frames, record["num_cameras"], num_context, min_gap, max_gap, interp_target
    )
    if context_cameras:
      cameras = np.resize(cameras[:context_cameras], num_context)
    context = cameras * num_frames + frames[:num_context]
    target = cameras[:num_targets] * num_frames + frames[-1]
    return context, target

  return select
