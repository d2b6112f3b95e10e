"""experiments/tasks.py: `run_eval` on hand-made test sets (the results folder, metrics before
media, exported scenes) and the task's loss settings. Tests of `experiments/` are named
`test_<module>.py`, or `test_experiments_<module>.py` where that name would read as a
`tokengs_jax` module's; the entry points end to end: test_re10k, test_kubric_entry_point,
test_dl3dv."""

import dataclasses
import json
import math
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments import data, re10k, results, tasks
from small_experiments import small_smoke as _small_smoke
from tokengs_jax import evaluation, export, model
from tokengs_jax.gaussians import Gaussians


def _view_batch(seed: int) -> dict:
  """A batch of one: two 16x16 input views and two targets, identity intrinsics-style cameras."""
  rng = np.random.default_rng(seed)
  c2w = np.tile(np.eye(4, dtype=np.float32), (1, 2, 1, 1))
  c2w[0, 1, 0, 3] = 0.1
  intrinsics = np.tile(np.float32([16, 16, 8, 8]), (1, 2, 1))
  return {
    "context_images": rng.uniform(size=(1, 2, 16, 16, 3)).astype(np.float32),
    "target_images": rng.uniform(size=(1, 2, 16, 16, 3)).astype(np.float32),
    "context_c2w": c2w,
    "target_c2w": c2w,
    "context_intrinsics": intrinsics,
    "target_intrinsics": intrinsics,
  }


class _HandMadeTask(tasks.Task):
  """Given test sets scored by one method of given Gaussians: `run_eval` without data or model."""

  def __init__(self, test_sets, gaussians):
    self._test_sets, self._gaussians = test_sets, gaussians

  def test_sets(self, experiment):
    return self._test_sets

  def methods(self, experiment, params, include_untrained):
    return {"splats": evaluation.Method(gaussians=lambda batch: self._gaussians)}


def _gaussians(nan: bool = False, transparent: int = 0):
  """8 Gaussians in front of the cameras, the first `transparent` of opacity 0.001."""
  n = 8
  means = np.random.default_rng(0).uniform(-0.4, 0.4, (1, n, 3)).astype(np.float32)
  means[..., 2] += 2.0
  means[0, 0, 0] = np.nan if nan else means[0, 0, 0]
  opacities = np.full((1, n), 0.8, np.float32)
  opacities[0, :transparent] = 0.001
  return Gaussians(
    means=means,
    opacities=opacities,
    scales=np.full((1, n, 3), 0.15, np.float32),
    quats=np.tile(np.float32([1, 0, 0, 0]), (1, n, 1)),
    colors=np.full((1, n, 3), 0.7, np.float32),
  )


def _hand_made_eval(
  out: pathlib.Path, task: tasks.Task, video_frames: int = 0, **eval_changes
) -> dict:
  smoke = re10k.PRESETS["smoke"]
  experiment = dataclasses.replace(
    smoke,
    output_dir=str(out),
    eval=dataclasses.replace(
      smoke.eval, lpips=False, grid_scenes=2, video_frames=video_frames, **eval_changes
    ),
  )
  return tasks.run_eval(experiment, None, task=task)


def test_eval_names_grids_after_keys_inside_the_output_folder(tmp_path):
  """Scene keys from a data chunk (`/abs/x`, `../../x`) never place a grid outside --output-dir,
  in grids/ or in a further test set's grids/<set>/."""
  out = tmp_path / "out"
  outside = tmp_path / "outside" / "x"  # absolute: where the key alone would have put it
  task = _HandMadeTask(
    {
      "test": [(str(outside), _view_batch(0)), ("../../escaped", _view_batch(1))],
      "ood_kubric": [("../../../escaped_too", _view_batch(2))],
    },
    _gaussians(),
  )
  _hand_made_eval(out, task)
  written = {p.relative_to(tmp_path).parts[0] for p in tmp_path.rglob("*") if p.is_file()}
  assert written == {"out"}
  grids = sorted(p.name for p in (out / "grids").glob("*.png"))
  assert grids == sorted(
    results.safe_file_name(k) + ".png" for k in (str(outside), "../../escaped")
  )
  assert [p.name for p in (out / "grids" / "ood_kubric").glob("*.png")] == [
    results.safe_file_name("../../../escaped_too") + ".png"
  ]


def test_eval_writes_metrics_before_media_and_survives_a_failing_export(
  tmp_path, monkeypatch, capsys
):
  """A NaN Gaussian in the first scene: write_ply refuses it, and that costs the PLY only: the
  scores are in metrics.json (written before any picture), the grids and the fly-through are
  written, and the reason is printed in one line and kept in metrics.json."""
  out = tmp_path / "out"
  before_grids, plain = [], results.write_grids

  def write_grids(*args, **kwargs):
    before_grids.append((out / "metrics.json").exists())
    return plain(*args, **kwargs)

  monkeypatch.setattr(results, "write_grids", write_grids)
  task = _HandMadeTask({"test": [("s", _view_batch(0))]}, _gaussians(nan=True))
  payload = _hand_made_eval(out, task, video_frames=2)
  assert before_grids == [True]
  written = json.loads((out / "metrics.json").read_text())
  assert math.isfinite(written["metrics"]["splats"]["mean"]["psnr"])
  assert written == json.loads(json.dumps(payload, default=str))
  [reason] = written["media_failures"]
  assert reason.startswith("gaussians.ply: ValueError: refusing to write non-finite Gaussians")
  assert f"[results] not written: {reason}\n" in capsys.readouterr().out
  assert not (out / "gaussians.ply").exists()
  assert (out / "grids" / "s.png").exists() and (out / "flythrough.mp4").stat().st_size > 0


def test_eval_exports_scenes_under_their_names_without_transparent_gaussians(tmp_path):
  """`eval.media_scenes` N > 1 exports the PLY and fly-through of the first N scenes (0: of
  every kept one), each under its key as a safe file name in gaussians/ and flythrough/; the
  default, 1, the first scene's as gaussians.ply / flythrough.mp4. The PLYs leave out the
  Gaussians below `eval.ply_min_opacity` (default the official 0.005; 0 keeps all); the grids
  stay those of the first `eval.grid_scenes`."""
  keys = ["a", "../b", "c"]
  task = _HandMadeTask(
    {"test": [(key, _view_batch(i)) for i, key in enumerate(keys)]}, _gaussians(transparent=2)
  )
  safe = [results.safe_file_name(key) for key in keys]

  def names(folder, suffix):
    return sorted(p.name for p in folder.glob(f"*{suffix}"))

  first = tmp_path / "first"
  _hand_made_eval(first, task, video_frames=2)
  assert len(export.read_ply(first / "gaussians.ply")["means"]) == 6
  assert (first / "flythrough.mp4").stat().st_size > 0
  assert not (first / "gaussians").exists() and not (first / "flythrough").exists()
  two = tmp_path / "two"
  _hand_made_eval(two, task, video_frames=2, media_scenes=2, ply_min_opacity=0.0)
  assert names(two / "gaussians", ".ply") == sorted(name + ".ply" for name in safe[:2])
  assert names(two / "flythrough", ".mp4") == sorted(name + ".mp4" for name in safe[:2])
  assert not (two / "gaussians.ply").exists() and not (two / "flythrough.mp4").exists()
  assert [len(export.read_ply(p)["means"]) for p in (two / "gaussians").glob("*")] == [8, 8]
  every = tmp_path / "every"
  _hand_made_eval(every, task, media_scenes=0)
  assert names(every / "gaussians", ".ply") == sorted(name + ".ply" for name in safe)
  assert names(every / "grids", ".png") == sorted(name + ".png" for name in safe[:2])
  assert not (every / "flythrough").exists()  # no video frames


@pytest.mark.slow  # compiles the VGG network's gradient
def test_lpips_term_reaches_both_trained_models_and_token_tuning(tmp_path):
  smoke = re10k.PRESETS["smoke"]
  experiment = _small_smoke(tmp_path, {"pixel_baseline": True}, lambda_lpips=0.5)
  task = tasks.Task()
  assert task.loss_config(experiment).lambda_lpips == 0.5
  assert task.tuning_loss_config(experiment).lambda_lpips == 0.5  # as official test-time training
  assert task.lpips_params(dataclasses.replace(experiment, train=smoke.train)) is None
  batch = next(iter(data.training_batches(experiment)))
  key, step = jax.random.key(0), jnp.asarray(0)
  params = model.init_params(key, experiment.model)
  loss, terms = task.loss_fn(experiment, experiment.model)(params, batch, key, step)
  assert float(terms["lpips"]) > 0
  plain = dataclasses.replace(experiment, train=smoke.train)
  plain_loss, plain_terms = task.loss_fn(plain, experiment.model)(params, batch, key, step)
  assert "lpips" not in plain_terms
  np.testing.assert_allclose(loss, plain_loss + 0.5 * terms["lpips"], rtol=1e-5)
  (pixel,) = task.trained_baselines(experiment)
  _, pixel_terms = pixel.loss_fn(pixel.init_params(key), batch, key, step)
  assert float(pixel_terms["lpips"]) > 0
