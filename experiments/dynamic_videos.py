"""The official Kubric videos of a time-conditioned model (the official
`scripts/render_kubric_dyn.py`), written by the Kubric evaluation (`KubricTask.extra_visuals`) in
`<output_dir>/videos/` for the first `eval.media_scenes` scenes of the test split when
`eval.video_frames` > 0 (`videos/<name>.mp4`; with `eval.media_scenes` other than 1, as the
fly-throughs, `videos/<scene>/<name>.mp4`).

As officially, each scene's inputs are chosen for the videos, not taken from the evaluated views:
over the clip's first F = min(`eval.video_frames`, clip length) frames (official `--num_frames`,
24 = the released clip), input v is camera (g + v + 1) mod C at frame round(v (F - 1) / (V - 1)),
g the shown camera (official `--gt_cam_index`, 0); the example (camera frame, pointmap scale,
times min-max normalised over the inputs and the F frames) is built by the data pipeline
(`make_example`). The videos, F frames each at 8 frames per second (official `--fps`):

- `01_gt_input`: camera g's frames 0 .. F - 1 (the data, no model);
- `02_gt_trajectory`: rendered along camera g's poses at frames 0 .. F - 1, each at its frame's time;
- `03_fixed_cam`: from camera g's pose at frame 0, at times 0 .. F - 1;
- `04_fixed_cam_dyn_only` / `05_fixed_cam_static_only`: `03` from the dynamic tokens' Gaussians
  only / the static tokens' only (split at `ModelConfig.num_static_gaussians`; written where the
  model has such tokens, as officially);
- `06_input_cams_hstack` (+ `07_..._dyn`, `08_..._static`): every input camera's pose (at its
  input frame) over the same times, side by side.

Renders use the task's objective (its background) through `evaluation.render_targets`; views
smaller than 256 pixels are upscaled (nearest) to it, as the fly-through. Deviation: the
synthetic rig has 4 cameras, so with 4 inputs camera g is also an input (the last, at frame
F - 1); officially (9 cameras) it is unseen."""

from __future__ import annotations

import pathlib
import time

import jax
import numpy as np

from experiments import figures, results
from tokengs_jax import evaluation, export
from tokengs_jax.data import ExampleConfig, make_example
from tokengs_jax.data.kubric import flat_views
from tokengs_jax.objective import ObjectiveConfig

FPS = 8  # official --fps
CAMERA = 0  # official --gt_cam_index: the camera of 01 / 02 / 03
MIN_SIZE = 256  # nearest upscaling of smaller views, as the fly-through's


def video_views(
  num_cameras: int, num_frames: int, num_context: int, camera: int = CAMERA
) -> tuple[np.ndarray, np.ndarray]:
  """The official video views: (context [V, 2], target [F, 2]) (camera, frame) pairs; input v
  is camera (camera + v + 1) mod C at frame round(v (F - 1) / (V - 1)), the targets `camera` at
  frames 0 .. F - 1."""
  spread = np.round(np.arange(num_context) * (num_frames - 1) / max(num_context - 1, 1))
  context = np.stack(
    [(camera + 1 + np.arange(num_context)) % num_cameras, spread.astype(np.int64)], -1
  )
  target = np.stack([np.full(num_frames, camera), np.arange(num_frames)], -1)
  return context.astype(np.int64), target.astype(np.int64)


def video_example(record: dict, config: ExampleConfig, num_context: int, frames: int) -> dict:
  """The batch of one whose inputs are `video_views`' and whose targets are the shown camera at
  the clip's first `frames` frames (fewer where the clip is shorter)."""
  views = video_views(record["num_cameras"], min(frames, record["num_frames"]), num_context)
  example = make_example(record, config, np.random.default_rng(0), views=flat_views(record, views))
  return {name: value[None] for name, value in example.items()}


def render_path(
  params, config, objective: ObjectiveConfig, batch: dict, c2w, intrinsics, times
) -> dict[str, evaluation.Rendered]:
  """The renders [T] (rgb [T, H, W, 3], alpha, depth) of camera poses c2w [T, 4, 4] with
  intrinsics [T, 4] at times [T] of a `video_example` batch: of every Gaussian ("full") and,
  where the model has such tokens, of the dynamic ("dynamic") and the static ("static") tokens'
  only. One decode at the T times (seen from each pose) and one render per part."""
  gaussians = jax.device_get(
    evaluation.gaussians_for_batch(params, batch, config, times[None], c2w[None])
  )
  parts = {"full": gaussians}
  static, dynamic = gaussians.static_and_dynamic(config.num_static_gaussians)
  if config.num_dynamic_gs_tokens > 0:
    parts["dynamic"] = dynamic
  if config.num_gs_tokens > 0:
    parts["static"] = static
  height, width = batch["target_images"].shape[-3:-1]
  rendered = {
    name: evaluation.render_targets(
      part,
      c2w[None],
      intrinsics[None],
      height=height,
      width=width,
      objective=objective,
      context_images=batch["context_images"],
    )
    for name, part in parts.items()
  }
  return {
    name: evaluation.Rendered(r.rgb[0], r.depth[0], r.alpha[0]) for name, r in rendered.items()
  }


def _frames(views) -> np.ndarray:
  """uint8 video frames [T, H', W' * V, 3] of V views' frames [T, H, W, 3] side by side, each
  upscaled to `MIN_SIZE`."""
  return np.stack(
    [
      np.concatenate([figures.upscale(export.to_uint8(view[t]), MIN_SIZE) for view in views], 1)
      for t in range(len(views[0]))
    ]
  )


def render_videos(params, config, objective: ObjectiveConfig, batch: dict) -> dict[str, np.ndarray]:
  """The official videos of a `video_example` batch: name (module docstring) -> uint8 frames
  [F, H', W', 3]. Each camera path is one decode at F times and one render per Gaussian part,
  all of one shape (compiled once)."""
  times = np.asarray(batch["target_times"][0], np.float32)
  steps = len(times)
  trajectory = batch["target_c2w"][0], batch["target_intrinsics"][0]
  fixed = np.repeat(trajectory[0][:1], steps, 0), np.repeat(trajectory[1][:1], steps, 0)
  inputs = [
    (np.repeat(c2w[None], steps, 0), np.repeat(k[None], steps, 0))
    for c2w, k in zip(batch["context_c2w"][0], batch["context_intrinsics"][0])
  ]

  def render(path):  # part -> rgb [F, H, W, 3]
    rendered = render_path(params, config, objective, batch, *path, times)
    return {part: r.rgb for part, r in rendered.items()}

  videos = {
    "01_gt_input": _frames([batch["target_images"][0]]),
    "02_gt_trajectory": _frames([render(trajectory)["full"]]),
  }
  at_fixed = render(fixed)
  per_input = [render(path) for path in inputs]
  for part, fixed_name, strip_name in (
    ("full", "03_fixed_cam", "06_input_cams_hstack"),
    ("dynamic", "04_fixed_cam_dyn_only", "07_input_cams_hstack_dyn"),
    ("static", "05_fixed_cam_static_only", "08_input_cams_hstack_static"),
  ):
    if part in at_fixed:
      videos[fixed_name] = _frames([at_fixed[part]])
      videos[strip_name] = _frames([views[part] for views in per_input])
  return dict(sorted(videos.items()))


def write_videos(
  folder, params, config, objective: ObjectiveConfig, batch: dict
) -> list[pathlib.Path]:
  """`render_videos` of a `video_example` batch as `folder/<name>.mp4` (H.264, `FPS`)."""
  videos = render_videos(params, config, objective, batch)
  return [
    export.write_mp4(pathlib.Path(folder) / f"{name}.mp4", list(frames), fps=FPS)
    for name, frames in videos.items()
  ]


def write_scene_videos(
  out,
  params,
  config,
  objective: ObjectiveConfig,
  scenes: list[tuple[str, dict]],
  example_config: ExampleConfig,
  frames: int,
  per_scene: bool = False,
) -> dict:
  """The videos of each (key, scene record) of `scenes` in `out`, or with `per_scene` (as the
  fly-throughs: `eval.media_scenes` other than 1) each in `out/<key>` (a safe file name,
  `results.data_path`). Each scene is a `results.media_step`. Returns metrics.json's `videos`
  facts: the frames asked for, fps, the files written, what failed and the seconds."""
  out, failures, written, start = pathlib.Path(out), [], {}, time.perf_counter()
  for key, record in scenes:
    with results.media_step(f"videos of scene {key!r}", failures):
      folder = results.data_path(out, key, "") if per_scene else out
      batch = video_example(record, example_config, config.num_input_views, frames)
      paths = write_videos(folder, params, config, objective, batch)
      written[key] = [str(path.relative_to(out.parent)) for path in paths]
  seconds = time.perf_counter() - start
  print(f"[videos] {len(written)} scene(s) to {out} in {seconds:.1f} s", flush=True)
  return {
    "video_frames": frames,
    "fps": FPS,
    "scenes": written,
    "failures": failures,
    "seconds": seconds,
  }
