"""Scene flow of dynamic Gaussians, measured against a generator's true object motion (issue 24).

A time-conditioned model decodes the same Gaussians at any time, so a dynamic Gaussian's
displacement between two times is its predicted scene flow. The truth (Kubric's per-frame object
poses and segmentations; `tokengs_jax.data.kubric.evaluation_fields`) is each object's rigid
motion between those times, points on its surface at the first one and its pixels in the target
views, all in the data's world. They are carried into the example's (model) frame by the
similarity the example applied to its cameras (`example_similarity`), then, per object:

- **flow** (`object_flow`): the Gaussians at the first time that sit on the object
  (`assign_to_objects`: the nearest object's surface point within `relative_distance` of its
  radius) should move with it: a Gaussian at x has the true displacement d = M x - x (M the
  object's motion). Relative end-point error = median |d_pred - d| / median |d| over those
  Gaussians: 0 for perfect tracks, exactly 1 for Gaussians that stay put, above 1 when worse
  than staying put.
- **static/dynamic split** (`dynamic_coverage`): the share of the object's pixels in the target
  views where the dynamic Gaussians alone render at least half the full render's opacity; the
  same share of the background's pixels, and the share of the dynamic Gaussians that sit on an
  object at all, say how clean the split is.

`score_scene` composes them for one evaluation batch, `summarise` over many scenes. Everything is
numpy on host arrays.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class SimilarityError(ValueError):
  """An example's cameras do not determine the similarity from the data's world to its frame."""


def example_similarity(
  world_c2w: np.ndarray, model_c2w: np.ndarray, *, tolerance: float = 1e-4
) -> np.ndarray:
  """The similarity x -> s R x + t from the data's world to an example's frame, read off the
  example's cameras.

  The example pipeline (`tokengs_jax.data.make_example`: `mean_cam` / `first_cam`
  normalisation, then one translation scale) moves all of an example's cameras by one such map:
  every camera turns by R (R_model = R R_world) and its centre maps as a point. Reading the map
  off the cameras, rather than redoing the normalisation, carries the truth exactly as the
  cameras went, whatever the example's configuration.

  Args:
    world_c2w: [V, 4, 4] the views' cameras as the data stores them (OpenCV c2w).
    model_c2w: [V, 4, 4] the same views' cameras in the example.
    tolerance: largest disagreement allowed between the map and any camera: rotation entries,
      and centres relative to their spread in the example.

  Returns:
    [4, 4] float64, upper-left block s R.

  Raises:
    SimilarityError: the camera centres coincide (no scale to read), or no one proper similarity
      maps every camera (e.g. a mirrored example).
  """
  world, model = np.asarray(world_c2w, np.float64), np.asarray(model_c2w, np.float64)
  # the rotation nearest the views' R_model R_world^T (all equal for a similarity)
  u, _, vt = np.linalg.svd(np.einsum("vij,vkj->ik", model[:, :3, :3], world[:, :3, :3]))
  rotation = u @ vt
  world_offsets = world[:, :3, 3] - world[:, :3, 3].mean(0)
  model_offsets = model[:, :3, 3] - model[:, :3, 3].mean(0)
  spread = float(np.sum(world_offsets**2))
  if spread < 1e-18:
    raise SimilarityError("the views' camera centres coincide: no scale to read off them")
  scale = float(np.sum(model_offsets * (world_offsets @ rotation.T))) / spread
  similarity = np.eye(4)
  similarity[:3, :3] = scale * rotation
  similarity[:3, 3] = model[:, :3, 3].mean(0) - scale * rotation @ world[:, :3, 3].mean(0)
  turned = np.abs(rotation @ world[:, :3, :3] - model[:, :3, :3]).max()
  moved = np.abs(transform_points(similarity, world[:, :3, 3]) - model[:, :3, 3]).max()
  model_spread = max(float(np.sqrt(np.mean(np.sum(model_offsets**2, -1)))), 1e-12)
  proper = np.linalg.det(rotation) > 0 and scale > 0
  if not proper or turned > tolerance or moved > tolerance * model_spread:
    raise SimilarityError(
      f"the example's cameras are not the data's under one similarity (rotation off by "
      f"{turned:.2g}, centres by {moved / model_spread:.2g} of their spread)"
    )
  return similarity


def transform_points(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
  """points [..., 3] through a 4x4 affine transform [4, 4] -> [..., 3] float64."""
  transform = np.asarray(transform, np.float64)
  return np.asarray(points, np.float64) @ transform[:3, :3].T + transform[:3, 3]


def motions_in_frame(similarity: np.ndarray, motions: np.ndarray) -> np.ndarray:
  """Rigid motions of the data's world as the same motions of the example's frame: S M S^-1.

  similarity: [4, 4] (`example_similarity`); motions: [K, 4, 4] -> [K, 4, 4] float64 (rigid).
  """
  similarity = np.asarray(similarity, np.float64)
  return similarity @ np.asarray(motions, np.float64) @ np.linalg.inv(similarity)


def assign_to_objects(
  points: np.ndarray, object_points: np.ndarray, *, relative_distance: float = 0.5
) -> np.ndarray:
  """The object each point sits on: the object with the nearest surface point, when that point
  is within `relative_distance` x the object's radius (the median distance of its surface points
  from their mean).

  Args:
    points: [N, 3] (e.g. Gaussian centres).
    object_points: [K, P, 3] points on each object's surface; NaN rows are ignored (an object
      with no finite point takes nothing).
    relative_distance: how far off an object's surface a point may sit, in object radii.

  Returns:
    [N] int64: the object's index, -1 for a point on none.
  """
  points = np.asarray(points, np.float64)
  object_points = np.asarray(object_points, np.float64)
  nearest = np.full((len(points), len(object_points)), np.inf)  # [N, K]
  reach = np.zeros(len(object_points))
  for k, surface in enumerate(object_points):
    surface = surface[np.isfinite(surface).all(-1)]
    if not len(surface):
      continue
    reach[k] = relative_distance * np.median(np.linalg.norm(surface - surface.mean(0), axis=-1))
    for start in range(0, len(points), 1024):  # bounded memory: [1024, P] distances at a time
      chunk = points[start : start + 1024]
      distances = np.linalg.norm(chunk[:, None] - surface[None], axis=-1)
      nearest[start : start + 1024, k] = distances.min(-1)
  if not nearest.size:
    return np.full(len(points), -1, np.int64)
  closest = np.argmin(nearest, axis=-1)
  on_it = nearest[np.arange(len(points)), closest] <= reach[closest]
  return np.where(on_it, closest, -1).astype(np.int64)


class ObjectFlow(NamedTuple):
  """Per-object flow scores, each [K] (NaN where an object has no Gaussian).

  gaussians: how many Gaussians sit on the object (int).
  median_epe: median end-point error |d_pred - d| of its Gaussians.
  median_displacement: median true displacement |d| of its Gaussians.
  median_predicted: median predicted displacement |d_pred|.
  relative_epe: median_epe / median_displacement (NaN also where the object did not move).
  """

  gaussians: np.ndarray
  median_epe: np.ndarray
  median_displacement: np.ndarray
  median_predicted: np.ndarray
  relative_epe: np.ndarray


def object_flow(
  start: np.ndarray,
  end: np.ndarray,
  motions: np.ndarray,
  assignment: np.ndarray,
  *,
  min_displacement: float = 1e-6,
) -> ObjectFlow:
  """End-point errors of Gaussians' displacements against their objects' rigid motions.

  Args:
    start, end: [N, 3] the Gaussians' centres at the two times (the same Gaussian in each row).
    motions: [K, 4, 4] each object's rigid motion between the two times, in the Gaussians'
      frame (`motions_in_frame`): a point x on object k goes to motions[k] x.
    assignment: [N] the object each Gaussian sits on at the first time, -1 for none
      (`assign_to_objects`).
    min_displacement: an object whose median true displacement is at most this did not move:
      its relative error is NaN (0 / 0).

  Returns:
    `ObjectFlow`.
  """
  start, end = np.asarray(start, np.float64), np.asarray(end, np.float64)
  motions = np.asarray(motions, np.float64)
  scores = np.full((4, len(motions)), np.nan)
  counts = np.zeros(len(motions), np.int64)
  for k, motion in enumerate(motions):
    mine = assignment == k
    counts[k] = mine.sum()
    if not counts[k]:
      continue
    truth = transform_points(motion, start[mine]) - start[mine]
    predicted = end[mine] - start[mine]
    scores[:3, k] = [
      np.median(np.linalg.norm(predicted - truth, axis=-1)),
      np.median(np.linalg.norm(truth, axis=-1)),
      np.median(np.linalg.norm(predicted, axis=-1)),
    ]
    if scores[1, k] > min_displacement:
      scores[3, k] = scores[0, k] / scores[1, k]
  return ObjectFlow(counts, *scores)


def dynamic_coverage(
  full_alpha: np.ndarray, dynamic_alpha: np.ndarray, object_masks: np.ndarray, *, ratio: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
  """How many of each object's pixels the dynamic Gaussians cover: where the render of the
  dynamic Gaussians alone reaches `ratio` of the full render's opacity (and that is not 0).

  Args:
    full_alpha, dynamic_alpha: [V, H, W] opacity of the full render and of the dynamic
      Gaussians alone, of the same views.
    object_masks: bool [V, K, H, W] each object's pixels in each view.

  Returns:
    (covered [K], pixels [K]) int64 pixel counts over the views; the share is covered / pixels.
  """
  full_alpha, dynamic_alpha = np.asarray(full_alpha), np.asarray(dynamic_alpha)
  covered = (dynamic_alpha >= ratio * full_alpha) & (full_alpha > 0)  # [V, H, W]
  masks = np.asarray(object_masks, bool)
  return (
    (masks & covered[:, None]).sum(axis=(0, 2, 3)).astype(np.int64),
    masks.sum(axis=(0, 2, 3)).astype(np.int64),
  )


def score_scene(
  batch: dict,
  start: np.ndarray,
  end: np.ndarray,
  opacities: np.ndarray,
  full_alpha: np.ndarray,
  dynamic_alpha: np.ndarray,
  *,
  min_opacity: float = 0.1,
  relative_distance: float = 0.5,
) -> dict:
  """Scene-flow and coverage scores of one Kubric evaluation batch.

  Args:
    batch: a batch of one with the scene-flow truth of `data.kubric.evaluation_fields`
      (`world_c2w`, `object_motions`, `object_points`, `target_object_masks`) besides
      `context_c2w` / `target_c2w`.
    start, end: [N, 3] the dynamic Gaussians' centres at the example's times 0 and 1 (the
      truth's first and last frames).
    opacities: [N] their opacities at time 0; those below `min_opacity` hardly draw anything and
      are not scored.
    full_alpha, dynamic_alpha: [Vt, H, W] the target views' opacity rendered from all Gaussians
      and from the dynamic ones alone, each at its target's time.
    relative_distance: `assign_to_objects`'s reach.

  Raises:
    SimilarityError: from `example_similarity`.

  Returns:
    `objects`: one dict per object k: `object` (k; segmentation number k + 1), `moving` (its pose
    changed between the two times), the `ObjectFlow` fields, `pixels` (in the target views) and
    `dynamic_coverage` (covered / pixels; None without pixels), NaN scores as None;
    `background`: the background's (no object's) `pixels` and how many the dynamic Gaussians
    `covered`; `dynamic_gaussians`: how many are scored, `on_objects`: how many sit on one.
  """
  model_c2w = np.concatenate([batch["context_c2w"][0], batch["target_c2w"][0]])
  similarity = example_similarity(batch["world_c2w"][0], model_c2w)
  motions = motions_in_frame(similarity, batch["object_motions"][0])
  surfaces = transform_points(similarity, batch["object_points"][0])
  opaque = np.asarray(opacities) >= min_opacity
  start, end = np.asarray(start)[opaque], np.asarray(end)[opaque]
  assignment = assign_to_objects(start, surfaces, relative_distance=relative_distance)
  flow = object_flow(start, end, motions, assignment)
  masks = batch["target_object_masks"][0]  # [Vt, K, H, W]
  background = ~masks.any(axis=1, keepdims=True)
  covered, pixels = dynamic_coverage(
    full_alpha, dynamic_alpha, np.concatenate([masks, background], axis=1)
  )
  # moved: its world motion is not the identity, to the tolerance of the data's `moved_objects`
  identity = np.isclose(batch["object_motions"][0], np.eye(4), rtol=0.0, atol=1e-6)
  moving = ~identity.all(axis=(-2, -1))
  objects = [
    {
      "object": k,
      "moving": bool(moving[k]),
      **{field: _number(values[k]) for field, values in flow._asdict().items()},
      "pixels": int(pixels[k]),
      "dynamic_coverage": _number(covered[k] / pixels[k]) if pixels[k] else None,
    }
    for k in range(len(motions))
  ]
  return {
    "objects": objects,
    "background": {"pixels": int(pixels[-1]), "covered": int(covered[-1])},
    "dynamic_gaussians": len(start),
    "on_objects": int((assignment >= 0).sum()),
  }


def summarise(scenes: list[dict]) -> dict:
  """Medians over the objects of several scenes (`score_scene`'s results), and pooled shares.

  Returns:
    `objects`, `moving_objects` and `moving_objects_with_gaussians` (counts);
    `median_relative_epe` over the moving objects with Gaussians on them;
    `median_dynamic_coverage` over the moving objects seen in the target views, and
    `median_dynamic_coverage_static` over the static ones; `dynamic_coverage_background`, the
    share of all background pixels the dynamic Gaussians cover (a clean split: 1, 0 and 0);
    `dynamic_gaussians_on_objects`, the share of the scored dynamic Gaussians that sit on an
    object. None where there is nothing to take a median or share of.
  """
  objects = [o for scene in scenes for o in scene["objects"]]
  moving = [o for o in objects if o["moving"]]
  errors = [o["relative_epe"] for o in moving if o["relative_epe"] is not None]

  def coverage(group: list[dict]) -> float | None:
    shares = [o["dynamic_coverage"] for o in group if o["dynamic_coverage"] is not None]
    return float(np.median(shares)) if shares else None

  def share(part: int, whole: int) -> float | None:
    return part / whole if whole else None

  return {
    "objects": len(objects),
    "moving_objects": len(moving),
    "moving_objects_with_gaussians": len(errors),
    "median_relative_epe": float(np.median(errors)) if errors else None,
    "median_dynamic_coverage": coverage(moving),
    "median_dynamic_coverage_static": coverage([o for o in objects if not o["moving"]]),
    "dynamic_coverage_background": share(
      sum(s["background"]["covered"] for s in scenes),
      sum(s["background"]["pixels"] for s in scenes),
    ),
    "dynamic_gaussians_on_objects": share(
      sum(s["on_objects"] for s in scenes), sum(s["dynamic_gaussians"] for s in scenes)
    ),
  }


def _number(value) -> float | int | None:
  """A JSON-ready score: NaN as None."""
  value = value.item() if isinstance(value, np.generic) else value
  return None if isinstance(value, float) and not np.isfinite(value) else value
