"""What a scene does not need (issue 27): the Gaussians no target pixel can show, per scene.

    python benchmarks/skips.py                       # 4 RE10K rooms + 4 Kubric scenes, fractions
    python benchmarks/skips.py --scenes 2 --time     # also: evaluation renders with and without
                                                     # the exact compaction

For the shipped default models (`experiments/pretrained/re10k_synthetic/params.msgpack` on the
default's synthetic test rooms, `experiments/pretrained/kubric_synthetic/params.msgpack` on its
synthetic Kubric test scenes, both written to a temporary folder by the generators the defaults
use, with the defaults' evaluation views), it reports per scene:

- `transparent`: the fraction of Gaussians with opacity < 1/255 (gsplat never draws them: every
  alpha = opacity * exp(-power) is below its 1/255 cut);
- `unseen`: the fraction culled in every camera that renders it (behind the near plane, past far,
  degenerate, zero radius or a radius box off the image), read from the renderer's own result
  (`radii` is 0 exactly where the renderer culled a Gaussian), transparent ones included;
- `droppable`: what `splatting.compaction.drawable` (the conservative form of the same rule the
  compaction uses) leaves out, and the bucket the compacted set is padded to (all of a scene's
  sets share one);
- `input_droppable`: the same against the input views, which token tuning renders.

Per-target sets (viewer-dependent colours, a dynamic model's sets at each target time) are each
judged against their own camera, as the evaluation renders them. `--time` times, side by side in
one run, each scene's evaluation render (`evaluation.render_targets`) with and without
`compact=True`, the target set with the most to drop rendered alone, full and compacted, and for
the dynamic (Kubric) model its prediction at the first target's time with and without
`static_scene=True` (the dynamic branch skipped, as for a scene known not to move).
"""

from __future__ import annotations

import argparse
import pathlib
import tempfile
import time

import jax
import numpy as np

from tokengs_jax import evaluation, process, splatting
from tokengs_jax.camera import invert_rigid
from tokengs_jax.objective import render_settings
from tokengs_jax.splatting import compaction


def re10k_scenes(root: str, count: int):
  """(experiment, [(key, batch of one)]): the default's first `count` test rooms and views."""
  from experiments import data, re10k
  from tokengs_jax.data.synthetic import generate_re10k_like

  experiment = re10k.PRESETS["synthetic-tiny"]
  s = experiment.synthetic
  generate_re10k_like(
    root,
    0,
    count,
    *experiment.image_size,
    frames=s.frames,
    seed=experiment.seed,
    config=data._room_family(s),
  )
  held_out = data.HeldOutSet(pathlib.Path(root) / "test", None, count)
  return experiment, data.evaluation_scenes(experiment, held_out=held_out)


def kubric_scenes(root: str, count: int):
  """(experiment, [(key, batch of one)]): the Kubric default's first `count` test scenes."""
  from experiments import kubric
  from experiments.kubric_data import TEST_SUBSET
  from experiments.kubric_task import KubricTask
  from tokengs_jax.data.kubric import KubricSceneSource
  from tokengs_jax.data.synthetic import generate_kubric_like

  experiment = kubric.PRESETS["synthetic-tiny"]
  height, width = experiment.image_size
  generate_kubric_like(
    root,
    count,
    height,
    width,
    frames=experiment.synthetic.frames,
    num_cameras=experiment.num_cameras,
    seed=experiment.seed + 1000,
    subset=TEST_SUBSET,
  )
  source = KubricSceneSource(root, [TEST_SUBSET], num_cameras=experiment.num_cameras)
  views = KubricTask._default_views(experiment, source, count, experiment.seed)
  return experiment, KubricTask._evaluation_scenes(experiment, source, views, experiment.seed)


def _cameras(gaussians, batch):
  """(world_to_camera, intrinsics) as `evaluation.render_targets` renders `gaussians`."""
  world_to_camera = invert_rigid(np.asarray(batch["target_c2w"], np.float32))
  intrinsics = np.asarray(batch["target_intrinsics"], np.float32)
  if len(gaussians.batch_shape) == world_to_camera.ndim - 2:  # one set per target camera
    return world_to_camera[..., None, :, :], intrinsics[..., None, :]
  return world_to_camera, intrinsics


def fractions(gaussians, batch, objective) -> dict:
  """A scene's transparent / unseen / droppable fractions and the compaction's bucket."""
  height, width = batch["target_images"].shape[-3:-1]
  world_to_camera, intrinsics = _cameras(gaussians, batch)
  settings = render_settings(objective, batch["context_images"], world_to_camera)
  out = splatting.render_exact(
    gaussians, world_to_camera, intrinsics, height=height, width=width, **settings
  )
  seen = np.any(np.asarray(out.radii) > 0, axis=(-3, -1))  # [..., N]: drawn by some camera
  settings.pop("background")
  keep = compaction.drawable(
    gaussians, world_to_camera, intrinsics, height=height, width=width, **settings
  )
  keep = np.asarray(keep)
  assert not np.any(seen & ~keep), "the compaction would drop a Gaussian the renderer draws"
  count = int(keep.reshape(-1, keep.shape[-1]).sum(-1).max())
  return {
    "gaussians": keep.shape[-1],
    "transparent": float(np.mean(np.asarray(gaussians.opacities) < 1.0 / 255.0)),
    "unseen": float(np.mean(~seen)),
    "droppable": float(np.mean(~keep)),
    "bucket": compaction.bucket_size(count, keep.shape[-1]),
  }


def input_droppable(gaussians, batch, objective) -> float:
  """The fraction no input view can draw: what token tuning, which renders the input views from
  every set, could leave out (`drawable` against every context camera)."""
  height, width = batch["context_images"].shape[-3:-1]
  world_to_camera = invert_rigid(np.asarray(batch["context_c2w"], np.float32))
  intrinsics = np.asarray(batch["context_intrinsics"], np.float32)
  if len(gaussians.batch_shape) == 2:  # every set against every input view
    world_to_camera, intrinsics = world_to_camera[:, None], intrinsics[:, None]
  keep = compaction.drawable(gaussians, world_to_camera, intrinsics, height=height, width=width,
    near=objective.near, far=objective.far)  # fmt: skip
  return float(np.mean(~np.asarray(keep)))


def _seconds(run, repeats: int) -> float:
  """Min wall time of `repeats` calls of `run` (after one warm-up call: compilation)."""
  jax.block_until_ready(run())
  times = []
  for _ in range(repeats):
    start = time.perf_counter()
    jax.block_until_ready(run())
    times.append(time.perf_counter() - start)
  return min(times)


def timings(gaussians, batch, objective, repeats: int) -> dict:
  """Seconds of the scene's evaluation render (`evaluation.render_targets`) without / with
  `compact=True`, and of the one target set with the most to drop rendered alone, full /
  compacted (what compaction buys where it applies; all sets share one bucket in the first)."""
  height, width = batch["target_images"].shape[-3:-1]
  row = {}
  for compact in (False, True):
    render = lambda compact=compact: (
      evaluation.render_targets(
        gaussians,
        batch["target_c2w"],
        batch["target_intrinsics"],
        height=height,
        width=width,
        objective=objective,
        context_images=batch["context_images"],
        compact=compact,
      ).rgb
    )
    row["render_s_compact" if compact else "render_s"] = _seconds(render, repeats)
  world_to_camera, intrinsics = _cameras(gaussians, batch)
  if len(gaussians.batch_shape) == 2:  # one set per target: the set with the most to drop
    settings = render_settings(objective, batch["context_images"], world_to_camera)
    keep = np.asarray(compaction.drawable(gaussians, world_to_camera, intrinsics,
      height=height, width=width, near=settings["near"], far=settings["far"]))  # fmt: skip
    v = int(np.argmin(keep[0].sum(-1)))
    one = jax.tree.map(lambda x: x[:, v], gaussians)
    cameras = (world_to_camera[:, v], intrinsics[:, v])
    small = compaction.compact_for_cameras(one, *cameras, height=height, width=width,
      near=settings["near"], far=settings["far"])  # fmt: skip
    if np.ndim(settings["background"]) > 1:  # [B, 1, 1, 3] behind the sets -> [B, 1, 3]
      settings["background"] = settings["background"][:, 0]
    for name, g in (("set_render_s", one), ("set_render_s_compact", small)):
      run = lambda g=g: splatting.render_exact(g, *cameras, height=height, width=width,
        **settings).rgb  # fmt: skip
      row[name] = _seconds(run, repeats)
  return row


def static_scene_timings(params, batch, config, repeats: int) -> dict:
  """Seconds of a dynamic model's prediction (`model.reconstruct` at the first target's time,
  coloured for its camera) in full and with the dynamic branch skipped (`static_scene=True`)."""
  from tokengs_jax import model

  arguments = (params, batch["context_images"], batch["context_c2w"], batch["context_intrinsics"])
  keywords = dict(
    times=batch["context_times"],
    target_times=batch["target_times"][:, 0],
    viewer_c2w=batch["target_c2w"][:, :1] if config.viewer_dependent else None,
  )
  row = {}
  for static_scene in (False, True):
    predict = jax.jit(
      lambda *a, static_scene=static_scene: (
        model.reconstruct(*a, config=config, static_scene=static_scene, **keywords).means
      )
    )
    name = "predict_s_static_scene" if static_scene else "predict_s"
    row[name] = _seconds(lambda predict=predict: predict(*arguments), repeats)
  return row


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--scenes", type=int, default=4, help="scenes per model")
  parser.add_argument("--time", action="store_true", help="also time the renders")
  parser.add_argument("--repeats", type=int, default=3)
  args = parser.parse_args()
  process.setup()
  from experiments import kubric_task, tasks, weights

  models = (
    ("re10k", re10k_scenes, tasks.Task()),
    ("kubric", kubric_scenes, kubric_task.KubricTask()),
  )
  for name, scenes_of, task in models:
    with tempfile.TemporaryDirectory() as root:
      experiment, scenes = scenes_of(root, args.scenes)
      params = weights.load_params(experiment.checkpoint)
      objective = task.objective(experiment)
      for key, batch in scenes:
        gaussians = evaluation.gaussians_for_batch(params, batch, experiment.model)
        row = {"model": name, "scene": key, **fractions(gaussians, batch, objective)}
        row["input_droppable"] = input_droppable(gaussians, batch, objective)
        if args.time:
          row.update(timings(gaussians, batch, objective, args.repeats))
          if experiment.model.num_dynamic_gs_tokens:
            row.update(static_scene_timings(params, batch, experiment.model, args.repeats))
        print(
          " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items())
        )


if __name__ == "__main__":
  main()
