"""The dynamic evaluation's pictures and scene-flow scores (`KubricTask.extra_visuals`), in
`<output_dir>/dynamic/`: in-between times, the static/dynamic split, the dynamic Gaussians'
trajectories, and their scene flow against the generator's truth (`tokengs_jax.scene_flow`)."""

from __future__ import annotations

import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from experiments import figures
from tokengs_jax import evaluation, export, scene_flow
from tokengs_jax.camera import invert_rigid, project_points
from tokengs_jax.gaussians import Gaussians


def write_pictures(
  out: pathlib.Path, params, config, example, flow_times: int, flow_tracks: int, writer, step
) -> dict:
  """`in_between_times.png` (one target camera at `flow_times` times), `static_dynamic.png`
  (target | full | static only | dynamic only) and `scene_flow.png` (the `flow_tracks` most
  opaque dynamic Gaussians' centres over time, projected into the target camera) of one
  `(key, batch)`; returns the displacement figures for metrics.json."""
  key, batch = example
  height, width = batch["target_images"].shape[-3:-1]
  camera = (batch["target_c2w"][:, :1], batch["target_intrinsics"][:, :1])
  times = np.linspace(0.0, 1.0, flow_times, dtype=np.float32)
  per_time = [_seen_from(params, batch, config, jnp.asarray([t]), camera[0]) for t in times]
  renders = [
    evaluation.render_targets(g, *camera, height=height, width=width).rgb[0, 0] for g in per_time
  ]
  grid = export.image_grid([list(batch["context_images"][0]), renders])
  export.save_png(out / "in_between_times.png", grid)
  if writer is not None:
    writer.add_image("dynamic/in_between_times", grid, step, dataformats="HWC")

  split = config.num_static_gaussians
  at_target = _seen_from(params, batch, config, batch["target_times"][:, 0], camera[0])
  parts = [at_target, *at_target.static_and_dynamic(split)]
  row = [batch["target_images"][0, 0]] + [
    evaluation.render_targets(g, *camera, height=height, width=width).rgb[0, 0] for g in parts
  ]
  export.save_png(out / "static_dynamic.png", export.image_grid([row]))

  dynamic = np.stack([np.asarray(g.means)[0, split:] for g in per_time], axis=1)  # [Nd, T, 3]
  opacity = np.mean([np.asarray(g.opacities)[0, split:] for g in per_time], axis=0)
  chosen = np.argsort(-opacity)[:flow_tracks]
  uv, depth = project_points(
    jnp.asarray(dynamic[chosen].reshape(-1, 3)),
    invert_rigid(jnp.asarray(camera[0][0])),
    jnp.asarray(camera[1][0]),
  )
  tracks = np.where((np.asarray(depth)[0] > 0)[:, None], np.asarray(uv)[0], np.nan)
  tracks = tracks.reshape(len(chosen), len(times), 2)
  figures.trajectory_plot(
    out / "scene_flow.png", tracks, title=f"scene flow, {key}", background=renders[0]
  )
  motion = np.linalg.norm(dynamic[:, -1] - dynamic[:, 0], axis=-1)
  static_motion = np.linalg.norm(
    np.asarray(per_time[-1].means)[0, :split] - np.asarray(per_time[0].means)[0, :split], axis=-1
  )
  return {
    "scene": key,
    "times": times.tolist(),
    "mean_dynamic_displacement_t0_t1": float(motion.mean()),
    # the mean is dominated by a few far, faint Gaussians: also the typical
    # motion, and that of the drawn (most opaque) tracks
    "median_dynamic_displacement_t0_t1": float(np.median(motion)),
    "median_tracked_displacement_t0_t1": float(np.median(motion[chosen])),
    "mean_static_displacement_t0_t1": float(static_motion.mean()),
  }


def _seen_from(params, batch, config, time, c2w) -> Gaussians:
  """Host Gaussians [1] of `batch` at `time` [1], coloured for the camera `c2w` [1, 1, 4, 4]
  where the model's colours depend on the viewer."""
  gaussians = jax.device_get(evaluation.gaussians_for_batch(params, batch, config, time, c2w))
  if len(gaussians.batch_shape) == 2:
    gaussians = jax.tree.map(lambda x: x[:, 0], gaussians)
  return gaussians


def _target_alphas(params, config, scene: dict) -> tuple[np.ndarray, np.ndarray]:
  """Opacity [Vt, H, W] of every target view at its own time: from all Gaussians, and from the
  dynamic ones alone."""
  height, width = scene["target_images"].shape[-3:-1]
  split = config.num_static_gaussians
  alphas = []
  for view in range(scene["target_images"].shape[1]):
    at_view = jax.device_get(
      evaluation.gaussians_for_batch(params, scene, config, scene["target_times"][:, view])
    )
    seen_by = (
      scene["target_c2w"][:, view : view + 1],
      scene["target_intrinsics"][:, view : view + 1],
    )
    alphas.append(
      [
        evaluation.render_targets(g, *seen_by, height=height, width=width).alpha[0, 0, ..., 0]
        for g in (at_view, at_view.static_and_dynamic(split)[1])
      ]
    )
  full, dynamic = np.moveaxis(np.asarray(alphas), 1, 0)
  return full, dynamic


def scene_flow_report(out: pathlib.Path, params, config, examples) -> dict:
  """Scene flow against the generator's truth over every `(key, batch)` that carries it: the
  Gaussians at times 0 and 1 (the truth's first and last frames) and the target views' opacity
  (`tokengs_jax.scene_flow.score_scene`); draws `scene_flow_error.png` and returns the summary.

  A scene whose views share one camera centre (e.g. an index of one static camera) gives no scale
  to carry the truth into the example's frame: it is skipped, with the reason."""
  split = config.num_static_gaussians
  scenes, skipped = [], {}
  for key, scene in examples:
    if "object_motions" not in scene:
      continue
    ends = [
      jax.device_get(evaluation.gaussians_for_batch(params, scene, config, jnp.asarray([t])))
      for t in (0.0, 1.0)
    ]
    try:
      scored = scene_flow.score_scene(
        scene,
        np.asarray(ends[0].means)[0, split:],
        np.asarray(ends[1].means)[0, split:],
        np.asarray(ends[0].opacities)[0, split:],
        *_target_alphas(params, config, scene),
      )
    except scene_flow.SimilarityError as error:
      skipped[key] = str(error)
      continue
    scenes.append({"scene": key, **scored})
  objects = [{"scene": s["scene"], **o} for s in scenes for o in s["objects"]]
  tracked = [o for o in objects if o["moving"] and o["relative_epe"] is not None]
  if scenes:  # data without motion truth has no error to draw
    figures.scatter_plot(
      out / "scene_flow_error.png",
      {
        "moving objects": (
          [o["median_displacement"] for o in tracked],
          [o["median_epe"] for o in tracked],
        )
      },
      title=f"scene flow of the Gaussians on each moving object ({len(tracked)})",
      xlabel="true displacement from time 0 to 1 (median over the object's Gaussians)",
      ylabel="median EPE",
      diagonal="Gaussians that stay put",
    )
  return {
    "scenes": len(scenes),
    **scene_flow.summarise(scenes),
    "skipped": skipped,
    "per_object": objects,
  }
