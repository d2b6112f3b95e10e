"""experiments.tasks and experiments.data through the entry points: evaluation runs and their
results folders, synthetic sets, held-out scenes and batches, the presets' settings, and each entry
point end to end (RE10K, Kubric, DL3DV). Command line: test_cli; results: test_results; figures:
test_figures."""

import dataclasses
import json
import math
import pathlib
import re
import shutil
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments import cli, data, re10k, results, tasks
from tokengs_jax import evaluation, export, model
from tokengs_jax.gaussians import Gaussians

REPO = pathlib.Path(__file__).resolve().parent.parent


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


def test_recorded_settings_of_every_preset_read_back_as_they_were():
  """`config.from_fields` rebuilds an experiment from its metrics.json record (JSON lists back
  to tuples, nested settings, a Kubric experiment's own fields)."""
  from experiments import config, dl3dv, kubric

  for presets in (re10k.PRESETS, dl3dv.PRESETS, kubric.PRESETS):
    for preset in presets.values():
      recorded = json.loads(json.dumps(dataclasses.asdict(preset), default=str))
      assert config.from_fields(type(preset), recorded) == preset
  with pytest.raises(ValueError, match="no fields.*'frames'"):
    config.from_fields(config.Experiment, {"frames": 3})


def test_eval_from_run_takes_the_recorded_settings_and_flags_override_them(tmp_path):
  """`eval --from-run RUN_DIR`: the experiment the run recorded in its metrics.json, scoring its
  trained weights (`params.msgpack`, when it trained; else the weights it evaluated) into
  RUN_DIR/eval/; flags override it. Another command, or a folder without metrics.json, refuses."""
  smoke = re10k.PRESETS["smoke"]
  run = tmp_path / "run"
  recorded = dataclasses.replace(
    smoke,
    output_dir=str(run),
    official_checkpoint="w.safetensors",
    eval=dataclasses.replace(smoke.eval, num_scenes=1, media_scenes=3),
  )
  run.mkdir()
  payload = {"experiment": dataclasses.asdict(recorded)}
  (run / "metrics.json").write_text(json.dumps(payload, default=str))

  def parse(*argv):
    return cli.parse(list(argv), re10k.PRESETS, "synthetic-tiny", "prog")

  assert parse("eval", "--from-run", str(run)) == (
    "eval",
    dataclasses.replace(recorded, output_dir=str(run / "eval")),
  )
  (run / "params.msgpack").write_bytes(b"")
  command, experiment = parse(
    "eval", f"--from-run={run}", "--eval.num-scenes", "4", "--output-dir", str(tmp_path / "x")
  )
  assert experiment == dataclasses.replace(
    recorded,
    checkpoint=str(run / "params.msgpack"),
    official_checkpoint=None,
    output_dir=str(tmp_path / "x"),
    eval=dataclasses.replace(recorded.eval, num_scenes=4),
  )
  with pytest.raises(SystemExit, match="eval --from-run"):
    parse("run", "--from-run", str(run))
  with pytest.raises(SystemExit, match="metrics.json"):
    parse("eval", "--from-run", str(tmp_path))
  from experiments import kubric

  kubric_run = {"experiment": dataclasses.asdict(kubric.PRESETS["synthetic-tiny"])}
  (run / "metrics.json").write_text(json.dumps(kubric_run, default=str))
  with pytest.raises(SystemExit, match="records no Experiment.*another entry point"):
    parse("eval", "--from-run", str(run))


# The `smoke` preset's sizes as flags, to run another preset at its scale.
SMOKE_SCALE = [
  *("--synthetic.num-train 4 --synthetic.num-test 2 --synthetic.frames 10").split(),
  *("--synthetic.num-ood 2 --synthetic.workers 1").split(),
  *("--model.enc-depth 1 --model.dec-depth 1 --model.enc-embed-dim 32").split(),
  *("--model.enc-num-heads 2 --model.num-gs-tokens 4").split(),
  *("--train.steps 3 --train.batch-size 2 --train.min-context-gap 3").split(),
  *("--train.max-context-gap 6 --train.warmup-steps 1 --train.log-every 1").split(),
  *("--eval.num-scenes 2 --eval.num-target-views 2 --eval.context-gap 6").split(),
  *("--eval.tuning-steps 2 --eval.tuning-learning-rate 1e-3 --eval.grid-scenes 1").split(),
  *("--eval.video-frames 4").split(),
]


def test_entry_point_end_to_end(tmp_path):
  """`python -m experiments.re10k run pretrain` (the command that trained the shipped weights)
  at the smoke preset's scale: generate (the varied family), train TokenGS and the
  pixel-aligned baseline from scratch, evaluate with geometry, write every file; then ship the
  run's weights as the shipped ones were (`experiments.weights ship`), and re-evaluate the run
  from its folder alone (`eval --from-run`) to the same scores."""
  out = tmp_path / "results"
  completed = subprocess.run(
    [
      sys.executable,
      "-m",
      "experiments.re10k",
      "run",
      "pretrain",
      "--output-dir",
      str(out),
      "--synthetic-dir",
      str(tmp_path / "data"),
      *SMOKE_SCALE,
    ],
    cwd=REPO,
    capture_output=True,
    text=True,
    timeout=600,
    check=False,
  )
  assert completed.returncode == 0, completed.stderr[-4000:]
  payload = json.loads((out / "metrics.json").read_text())
  assert set(payload["metrics"]) == {
    "mean_colour",
    "input_average",
    "nearest_view",
    "untrained",
    "trained",
    "trained+token_tuning",
    "pixel_aligned",
  }
  for method in payload["metrics"].values():
    assert len(method["per_scene"]) == 2
    for value in method["mean"].values():
      assert math.isfinite(value)
  assert (out / "pixel_aligned.msgpack").stat().st_size > 0
  for name in ("test", "ood_galleries", "frozen_courtyards"):  # geometry where it renders
    scores = payload if name == "test" else payload["other_test_sets"][name]
    means = {method: v["mean"] for method, v in scores["metrics"].items()}
    assert {"holes", "depth_absrel", "depth_delta1"} <= set(means["pixel_aligned"]) & set(
      means["trained"]
    )
    assert "holes" not in means["nearest_view"]
  for name in (
    "metrics.md",
    "flythrough.mp4",
    "gaussians.ply",
    "params.msgpack",
    "train_history.json",
  ):
    assert (out / name).stat().st_size > 0, name
  assert list((out / "grids").glob("*.png"))
  assert "trained beats nearest_view" in payload["checks"]
  # the other generators' scenes too: the galleries (validation) and the frozen courtyards
  assert payload["test_sets"] == ["test", "ood_galleries", "frozen_courtyards"]
  galleries = payload["other_test_sets"]["ood_galleries"]["metrics"]
  assert set(galleries) == set(payload["metrics"])
  assert all(len(method["per_scene"]) == 2 for method in galleries.values())
  assert list((out / "grids" / "ood_galleries").glob("*.png"))
  assert (
    payload["training_data_rejections"] == "source: nothing rejected\npipeline: nothing rejected"
  )
  assert list((out / "tensorboard").glob("events.out.tfevents.*"))
  ply = export.read_ply(out / "gaussians.ply")
  assert ply["means"].shape == (64, 3) and np.isfinite(ply["means"]).all()

  shipped = subprocess.run(
    [sys.executable, "-m", "experiments.weights", "ship", str(out), str(tmp_path / "shipped")],
    cwd=REPO,
    capture_output=True,
    text=True,
    check=False,
  )
  assert shipped.returncode == 0, shipped.stderr[-4000:]
  provenance = json.loads((tmp_path / "shipped" / "provenance.json").read_text())
  assert set(provenance["files"]) == {"params.msgpack", "pixel_aligned.msgpack"}
  assert provenance["experiment"] == payload["experiment"]
  assert provenance["command"].startswith("python -m experiments.re10k run pretrain")

  # re-evaluated from its folder alone (`eval --from-run`): the same settings, the same scores
  again = subprocess.run(
    [sys.executable, "-m", "experiments.re10k", "eval", "--from-run", str(out)],
    cwd=REPO,
    capture_output=True,
    text=True,
    timeout=600,
    check=False,
  )
  assert again.returncode == 0, again.stderr[-4000:]
  rescored = json.loads((out / "eval" / "metrics.json").read_text())
  assert rescored["experiment"] == {
    **payload["experiment"],
    "output_dir": str(out / "eval"),
    "checkpoint": str(out / "params.msgpack"),
  }
  for name in ("test", "ood_galleries"):
    before, after = (
      record if name == "test" else record["other_test_sets"][name]
      for record in (payload, rescored)
    )
    for method, scores in before["metrics"].items():
      np.testing.assert_allclose(
        [s["psnr"] for s in after["metrics"][method]["per_scene"]],
        [s["psnr"] for s in scores["per_scene"]],
        rtol=1e-4,
        err_msg=f"{name}: {method}",
      )
  assert (out / "eval" / "gaussians.ply").stat().st_size > 0


@pytest.mark.slow
def test_kubric_entry_point_end_to_end(tmp_path):
  """`python -m experiments.kubric` on two tiny generated scenes: dynamic pictures and metrics.
  As the default, it starts from static weights (here a tiny static model's, for the shipped
  ones' architecture is too large for the test) and grows the dynamic tokens from them."""
  from experiments import kubric, weights

  out = tmp_path / "results"
  static = kubric.PRESETS["synthetic-tiny"].model.replace(
    enc_depth=1,
    dec_depth=1,
    enc_embed_dim=32,
    enc_num_heads=2,
    num_gs_tokens=4,
    num_dynamic_gs_tokens=0,
    time_embedding=False,
  )
  start = weights.save_params(
    tmp_path / "static.msgpack", model.init_params(jax.random.key(3), static)
  )
  completed = subprocess.run(
    [
      sys.executable,
      "-m",
      "experiments.kubric",
      "--checkpoint",
      str(start),
      "--output-dir",
      str(out),
      "--synthetic-dir",
      str(tmp_path / "data"),
      "--synthetic.num-train",
      "2",
      "--synthetic.num-test",
      "1",
      "--synthetic.frames",
      "6",
      "--synthetic.workers",
      "1",
      "--num-cameras",
      "2",
      "--max-gap",
      "4",
      "--train.steps",
      "2",
      "--train.batch-size",
      "2",
      "--train.log-every",
      "1",
      "--eval.num-scenes",
      "1",
      "--eval.video-frames",
      "2",
      "--eval.tuning-steps",
      "2",
      "--flow-times",
      "3",
      "--model.dec-patch-size",
      "4",
      "--model.num-dynamic-gs-tokens",
      "2",
      "--model.enc-depth",
      "1",
      "--model.dec-depth",
      "1",
      "--model.enc-embed-dim",
      "32",
      "--model.enc-num-heads",
      "2",
      "--model.num-gs-tokens",
      "4",
    ],
    cwd=REPO,
    capture_output=True,
    text=True,
    timeout=600,
    check=False,
  )
  assert completed.returncode == 0, completed.stderr[-4000:]
  assert "gs_tokens_dynamic: from static gs_tokens" in completed.stdout
  payload = json.loads((out / "metrics.json").read_text())
  assert set(payload["metrics"]) == {
    "mean_colour",
    "input_average",
    "nearest_view",
    "same_camera",
    "nearest_time",
    "untrained",
    "static_only",  # the preset's static-only model of the same budget
    "trained",
    "trained+token_tuning",
  }
  assert (out / "static_only.msgpack").stat().st_size > 0
  for method in ("same_camera", "static_only", "trained", "trained+token_tuning"):
    assert math.isfinite(payload["metrics"][method]["mean"]["psnr"])
    assert math.isfinite(payload["metrics"][method]["mean"]["psnr_moving"])
  assert "trained beats same_camera" in payload["checks"]
  assert payload["test_sets"] == ["test", "ood_kubric"]  # the frozen held-out dynamic family
  history = json.loads((out / "train_history.json").read_text())
  # the auxiliary weight held all run (`pretrain`'s dyn_aux_hold_fraction 1.0), on the moving pixels
  assert [h["dyn_aux_weight"] for h in history] == pytest.approx([0.3, 0.3])
  assert all(math.isfinite(h["motion"]) for h in history)
  for name in ("mean_dynamic", "median_dynamic", "median_tracked", "mean_static"):
    assert math.isfinite(payload["dynamic"][f"{name}_displacement_t0_t1"]), name
  for name in ("in_between_times.png", "static_dynamic.png", "scene_flow.png"):
    assert (out / "dynamic" / name).stat().st_size > 0, name
  # the generator's truth reaches the scene-flow scores (tokengs_jax.scene_flow)
  assert payload["scene_flow"]["scenes"] == 1 and payload["scene_flow"]["per_object"]
  assert (out / "dynamic" / "scene_flow_error.png").stat().st_size > 0


def test_kubric_loss_is_the_official_release_scaled_to_the_run():
  from experiments import kubric
  from experiments.kubric_task import KubricTask

  paper = kubric.PRESETS["paper"]
  config = KubricTask().loss_config(paper)
  assert (config.rgb_loss, config.lambda_rgb, config.lambda_ssim, config.lambda_vis) == (
    "l1",
    0.8,
    0.2,
    1.0,
  )
  # official release: 0.3 held for 5k steps, decayed to 0 over 10k (of 50k finetuning steps)
  assert (
    config.lambda_dyn_aux,
    config.dyn_aux_hold_steps,
    config.dyn_aux_decay_steps,
    config.dyn_aux_min,
  ) == (0.3, 5_000, 10_000, 0.0)
  assert (config.lambda_motion, config.dyn_aux_on_motion) == (0.0, False)
  tiny = kubric.PRESETS["pretrain"]  # what trained the default's shipped weights
  config = KubricTask().loss_config(tiny)
  # the default's deviations: moving pixels x5, the auxiliary term on them, held all run
  assert (config.lambda_motion, config.dyn_aux_on_motion) == (4.0, True)
  assert config.dyn_aux_hold_steps == tiny.train.steps
  assert config.dyn_aux_decay_steps == round(0.2 * tiny.train.steps)
  # token tuning's input views moved nowhere: the official auxiliary term
  assert not KubricTask().tuning_loss_config(tiny).dyn_aux_on_motion
  assert KubricTask().objective(tiny).decode_times == "first"
  mse = dataclasses.replace(tiny, train=dataclasses.replace(tiny.train, rgb_loss="l2"))
  assert KubricTask().loss_config(mse).rgb_loss == "l2"


def _refusal(capsys, parse, *argv) -> str:
  """What the command line says, on one line, as it refuses `argv` (tyro's boxed message)."""
  with pytest.raises(SystemExit):
    parse(*argv)
  return " ".join(re.sub("[\u2500-\u257f]", " ", capsys.readouterr().err).split())


def test_kubric_presets_keep_their_loss_and_honour_the_common_train_flags(capsys):
  """The loss terms moved to `train` (issue 26): each preset's loss is the one it had (by hand:
  the official release's L1 x 0.8 + SSIM x 0.2 + visibility x 1 and the auxiliary term), the
  common `--train.*` loss flags now change Kubric's loss, and a record of a run from before the
  move reads back to the loss it trained with."""
  from experiments import config, kubric
  from experiments.kubric_task import KubricExperiment, KubricTask
  from tokengs_jax.losses import LossConfig

  release = dict(rgb_loss="l1", lambda_rgb=0.8, lambda_ssim=0.2, lambda_vis=1.0)
  pretrain = dict(release, lambda_dyn_aux=0.3, lambda_motion=4.0, dyn_aux_on_motion=True)
  expected = {
    "pretrain": LossConfig(**pretrain, dyn_aux_hold_steps=1200, dyn_aux_decay_steps=240),
    # 0 steps: nothing to hold, the decay's one-step floor
    "synthetic-tiny": LossConfig(**pretrain, dyn_aux_hold_steps=0, dyn_aux_decay_steps=1),
    "paper": LossConfig(
      **release, lambda_dyn_aux=0.3, dyn_aux_hold_steps=5_000, dyn_aux_decay_steps=10_000
    ),
  }
  for name, loss in expected.items():
    assert KubricTask().loss_config(kubric.PRESETS[name]) == loss, name
  assert KubricTask().loss_config(KubricExperiment()).lambda_rgb == 0.8  # the release's default

  def parse(*argv):
    return cli.parse(list(argv), kubric.PRESETS, "synthetic-tiny", "prog")[1]

  flags = ("--train.lambda-ssim", "0.5", "--train.rgb-loss", "l2", "--train.lambda-opacity", "0.1")
  loss = KubricTask().loss_config(parse("run", "paper", *flags))
  assert loss == dataclasses.replace(
    expected["paper"], lambda_ssim=0.5, rgb_loss="l2", lambda_opacity=0.1
  )
  tuned = parse("--train.use-input-supervision")
  assert KubricTask().objective(tuned).use_input_supervision
  assert "Unrecognized" in _refusal(capsys, parse, "--rgb-loss", "l2")  # the duplicate flag
  said = _refusal(capsys, parse, "--train.lambda-depth", "0.1")
  assert "lambda_depth must be 0 on Kubric" in said
  assert "dyn_aux_on_motion needs lambda_motion" in _refusal(capsys, parse, "--lambda-motion", "0")

  old = json.loads(json.dumps(dataclasses.asdict(kubric.PRESETS["pretrain"]), default=str))
  old["rgb_loss"] = "l2"  # recorded top-level, and train's unused photometric weights
  old["train"].update(rgb_loss="l2", lambda_rgb=1.0, lambda_ssim=0.2, lambda_opacity=0.3)
  read = config.from_fields(KubricExperiment, old)
  assert KubricTask().loss_config(read) == dataclasses.replace(expected["pretrain"], rgb_loss="l2")


def test_evaluation_scenes_read_a_list_format_index(tmp_path):
  """A Long-LRM list index (official DL3DV eval form): its context list, every frame a target."""
  smoke = re10k.PRESETS["smoke"]
  experiment = dataclasses.replace(
    smoke,
    synthetic_dir=str(tmp_path / "data"),
    synthetic=dataclasses.replace(smoke.synthetic, num_train=1, num_test=1, workers=1),
  )
  data.ensure_synthetic(experiment)
  key = data.evaluation_scenes(experiment)[0][0]
  index = tmp_path / "index.json"
  index.write_text(json.dumps([{"scene_name": key, "fold_8_kmeans_2_input": [1, 7]}]))
  ((got_key, batch),) = data.evaluation_scenes(
    dataclasses.replace(experiment, eval_index=str(index))
  )
  assert got_key == key
  frames = smoke.synthetic.frames
  assert batch["context_images"].shape[1] == 2 and batch["target_images"].shape[1] == frames
  for view, frame in enumerate([1, 7]):  # the listed inputs are frames 1 and 7 of the targets
    np.testing.assert_array_equal(
      batch["context_images"][0, view], batch["target_images"][0, frame]
    )
  # the batch names its frames (the nearest-view baseline reads them)
  np.testing.assert_array_equal(batch["context_frames"], [[1, 7]])
  np.testing.assert_array_equal(batch["target_frames"], [np.arange(frames)])
  with pytest.raises(ValueError, match="fold_8_kmeans_3_input"):
    data.evaluation_scenes(dataclasses.replace(experiment, eval_index=str(index)).with_views(3))


def test_a_synthetic_set_written_with_other_settings_is_not_reused(tmp_path):
  smoke = re10k.PRESETS["smoke"]
  experiment = dataclasses.replace(
    smoke,
    synthetic_dir=str(tmp_path / "data"),
    synthetic=dataclasses.replace(smoke.synthetic, num_train=1, num_test=1, workers=1),
  )
  root = data.ensure_synthetic(experiment)
  assert data.ensure_synthetic(experiment) == root  # same settings: reused
  other_walk = dataclasses.replace(
    experiment.synthetic, walk=dataclasses.replace(experiment.synthetic.walk, pitch=(0.0, 0.0))
  )
  for changed in (
    dataclasses.replace(experiment, synthetic=other_walk),
    dataclasses.replace(experiment, seed=1),
  ):
    with pytest.raises(ValueError, match="other settings.*another --synthetic-dir"):
      data.ensure_synthetic(changed)
  (root / "generator.json").unlink()  # a set from before the settings were recorded
  with pytest.raises(ValueError, match="not recorded"):
    data.ensure_synthetic(experiment)


def test_an_index_matching_no_scene_fails_before_any_work_and_lists_unknown_keys(tmp_path):
  smoke = re10k.PRESETS["smoke"]
  experiment = dataclasses.replace(
    smoke,
    synthetic_dir=str(tmp_path / "data"),
    synthetic=dataclasses.replace(smoke.synthetic, num_train=1, num_test=1, workers=1),
  )
  data.ensure_synthetic(experiment)
  key = data.evaluation_scenes(experiment)[0][0]
  index = tmp_path / "index.json"
  index.write_text(json.dumps({"nope": {"context": [0, 4], "target": [2]}}))
  with pytest.raises(ValueError, match=f"none of its 1 scenes is in the data.*'nope'.*'{key}'"):
    data.check_evaluation_data(dataclasses.replace(experiment, eval_index=str(index)))
  index.write_text(
    json.dumps(
      {"nope": {"context": [0, 4], "target": [2]}, key: {"context": [0, 4], "target": [2]}}
    )
  )
  partial = dataclasses.replace(experiment, eval_index=str(index))
  assert data.check_evaluation_data(partial) == {
    "requested": 2,
    "evaluated": 1,
    "missing": ["nope"],
  }
  assert [k for k, _ in data.evaluation_scenes(partial)] == [key]
  index.write_text(json.dumps({key: {"context": [0, 4], "target": [99]}}))
  with pytest.raises(ValueError, match="frame 99"):
    data.check_evaluation_data(dataclasses.replace(experiment, eval_index=str(index)))


def test_novel_targets_are_inside_the_span_and_never_inputs():
  np.testing.assert_array_equal(data.novel_targets(np.array([0, 12]), 3), [1, 6, 11])
  targets = data.novel_targets(np.array([0, 5, 11, 16]), 4)
  assert not set(targets.tolist()) & {0, 5, 11, 16} and targets.min() > 0 and targets.max() < 16
  with pytest.raises(ValueError, match="widen"):
    data.novel_targets(np.array([0, 2]), 2)


def test_default_evaluation_scores_no_input_view_as_a_target(tmp_path):
  """Without an index, every evaluated target is a frame that is not an input."""
  smoke = re10k.PRESETS["smoke"]
  experiment = dataclasses.replace(
    smoke,
    synthetic_dir=str(tmp_path / "data"),
    synthetic=dataclasses.replace(smoke.synthetic, num_train=1, num_test=2, workers=1),
  )
  data.ensure_synthetic(experiment)
  for _, batch in data.evaluation_scenes(experiment):
    context, target = batch["context_frames"][0], batch["target_frames"][0]
    assert len(target) == smoke.eval.num_target_views
    assert not set(target.tolist()) & set(context.tolist())
    assert context.min() < target.min() and target.max() < context.max()


def test_generated_sets_are_published_whole_and_the_first_copy_kept(tmp_path):
  """Processes racing to write the same synthetic set never leave a partial or mixed one."""
  root = tmp_path / "set"

  def writer(content):
    def write(staging):
      (staging / "test").mkdir(parents=True)
      (staging / "test" / "index.json").write_text(content)

    return write

  data._publish(root, ("test",), writer("first"))
  data._publish(root, ("test",), writer("second"))
  assert (root / "test" / "index.json").read_text() == "first"
  assert sorted(p.name for p in tmp_path.iterdir()) == ["set"]  # no staging folder left


def _tiny_kubric(tmp_path, **changes):
  """The Kubric default on one training and one test scene of 2 cameras x 4 frames at 16x16 (no
  held-out family) under `tmp_path / "data"`, with these settings changed."""
  from experiments import kubric
  from experiments.config import SyntheticSettings

  tiny = kubric.PRESETS["synthetic-tiny"]
  return dataclasses.replace(
    tiny,
    synthetic_dir=str(tmp_path / "data"),
    output_dir=str(tmp_path / "out"),
    model=tiny.model.replace(image_size=(16, 16)),
    num_cameras=2,
    synthetic=SyntheticSettings(num_train=1, num_test=1, frames=4, num_ood=0, workers=1),
    **changes,
  )


@pytest.mark.parametrize("entry_point", ["re10k", "kubric"])
def test_a_batch_that_does_not_split_evenly_across_processes_is_rejected(
  tmp_path, monkeypatch, entry_point
):
  """Both entry points split the global batch with one check, before any data is written."""
  from experiments.kubric_task import KubricTask

  monkeypatch.setattr(jax, "process_count", lambda: 3)
  if entry_point == "kubric":
    task, experiment = KubricTask(), _tiny_kubric(tmp_path)
  else:
    task, experiment = tasks.Task(), _small_smoke(tmp_path)
  experiment = dataclasses.replace(
    experiment, train=dataclasses.replace(experiment.train, batch_size=4)
  )
  with pytest.raises(ValueError, match="batch_size 4 is not divisible by 3 processes"):
    task.training_batches(experiment)
  assert not (tmp_path / "data").exists()
  assert data.local_batch_size(6) == 2


def test_kubric_synthetic_subsets_are_published_whole_stamped_and_rewritten_when_changed(
  tmp_path, monkeypatch
):
  """Each subset goes through `data.ensure_generated_set`: reused under the same settings,
  written anew under others, never left half-written, and refused when it records none."""
  from experiments import kubric_task

  task, experiment = kubric_task.KubricTask(), _tiny_kubric(tmp_path)
  root = task.root(experiment)
  assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]  # no staging folder left
  assert sorted(p.name for p in root.iterdir()) == ["test", "v0"]
  stamp = json.loads((root / "v0" / "generator.json").read_text())
  assert stamp["generator"] == "generate_kubric_like" and stamp["seed"] == experiment.seed
  for subset in ("v0", "test"):
    (root / subset / "kept").touch()
  task.root(experiment)  # the same settings: both subsets reused
  assert (root / "v0" / "kept").exists() and (root / "test" / "kept").exists()

  reseeded = dataclasses.replace(experiment, seed=experiment.seed + 1)
  task.root(reseeded)  # another seed: both subsets written anew, nothing left aside
  assert not (root / "v0" / "kept").exists() and not (root / "test" / "kept").exists()
  assert json.loads((root / "v0" / "generator.json").read_text())["seed"] == reseeded.seed
  assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]
  assert sorted(p.name for p in root.iterdir()) == ["test", "v0"]
  more = dataclasses.replace(
    reseeded, synthetic=dataclasses.replace(reseeded.synthetic, num_train=2)
  )
  assert len(task.sources(more)[0]) == 2

  def interrupted(staging, subset, **arguments):
    (staging / subset / "scene_000000").mkdir(parents=True)
    raise RuntimeError("interrupted")

  shutil.rmtree(root / "v0")  # missing: the next call writes it
  monkeypatch.setattr(kubric_task, "generate_kubric_like", interrupted)
  with pytest.raises(RuntimeError, match="interrupted"):
    task.root(more)
  assert not (root / "v0").exists()  # the half-written subset was never published
  monkeypatch.undo()
  assert len(task.sources(more)[0]) == 2
  assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]

  (root / "v0" / "generator.json").unlink()  # a subset from before the settings were recorded
  with pytest.raises(ValueError, match="not recorded.*another --synthetic-dir"):
    task.root(more)
  assert (root / "v0" / "scene_000000").exists()  # refused, not deleted


def _small_smoke(tmp_path, eval_changes=None, **train_changes):
  """The smoke preset on 2 training scenes and 1 test scene under `tmp_path`, with these
  training (and evaluation) settings changed."""
  smoke = re10k.PRESETS["smoke"]
  return dataclasses.replace(
    smoke,
    synthetic_dir=str(tmp_path / "data"),
    synthetic=dataclasses.replace(smoke.synthetic, num_train=2, num_test=1, workers=1),
    train=dataclasses.replace(smoke.train, **train_changes),
    eval=dataclasses.replace(smoke.eval, **(eval_changes or {})),
  )


def test_training_batches_carry_true_depths_for_the_depth_loss(tmp_path):
  smoke = re10k.PRESETS["smoke"]
  experiment = _small_smoke(tmp_path, lambda_depth=0.1)
  batch = next(iter(data.training_batches(experiment)))
  depths = batch["target_depths"]
  assert depths.shape == batch["target_images"].shape[:-1]
  # Scaled as the cameras (translation scale 0.25): closed rooms of a few metres.
  assert (depths > 0).all() and 0.05 < float(depths.mean()) < 2.0
  assert tasks.Task().loss_config(experiment).lambda_depth == 0.1
  plain = dataclasses.replace(experiment, train=smoke.train)
  assert "target_depths" not in next(iter(data.training_batches(plain)))


def test_lpips_term_reaches_both_trained_models_but_not_token_tuning(tmp_path):
  smoke = re10k.PRESETS["smoke"]
  experiment = _small_smoke(tmp_path, {"pixel_baseline": True}, lambda_lpips=0.5)
  task = tasks.Task()
  assert task.loss_config(experiment).lambda_lpips == 0.5
  assert task.tuning_loss_config(experiment).lambda_lpips == 0.0
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


# ----- DL3DV scenes as they ship, through `python -m experiments.dl3dv` (issue 26) ---------------

# Held out by the index (DepthSplat form: key -> context / target frames); the others train.
DL3DV_HELD_OUT = {
  "c0ffee": {"context": [0, 10], "target": [3, 7]},
  "d00d1e": {"context": [1, 11], "target": [5]},
}
DL3DV_TRAINING = ["aaaa01", "bbbb02"]
# `synthetic-2view` at the smoke scale, on DL3DV's sampler and translation scale
DL3DV_SMOKE = [
  *("--dataset dl3dv --model.enc-depth 1 --model.dec-depth 1 --model.enc-embed-dim 32").split(),
  *("--model.enc-num-heads 2 --model.num-gs-tokens 4 --train.steps 2 --train.batch-size 2").split(),
  *("--train.warmup-steps 1 --train.log-every 1 --train.num-workers 0 --eval.no-lpips").split(),
  *("--eval.tuning-steps 0 --eval.video-frames 0 --eval.grid-scenes 1").split(),
]
# Runs the entry point with every scene read by the training source logged ("train <key>").
_LOGGING_TRAINING_READS = """
import runpy, sys
from tokengs_jax.data import dl3dv
log, read, make = sys.argv.pop(1), dl3dv.DL3DVSceneSource._read_scene, dl3dv.dl3dv_training_source
def logged(self, path):
  with open(log, "a") as f:
    f.write(f"{getattr(self, 'role', 'other')} {path.stem}\\n")
  return read(self, path)
def training_source(*args, **kwargs):
  source = make(*args, **kwargs)
  source.role = "train"
  return source
dl3dv.DL3DVSceneSource._read_scene, dl3dv.dl3dv_training_source = logged, training_source
sys.argv[0] = "experiments/dl3dv.py"
runpy.run_module("experiments.dl3dv", run_name="__main__", alter_sys=True)
"""


@pytest.fixture(scope="module")
def dl3dv_zips(tmp_path_factory):
  """(folder of 4 DL3DV scene zips rendered by the ray tracer, its evaluation index JSON)."""
  from scenes import write_dl3dv_scenes

  root = tmp_path_factory.mktemp("dl3dv_zips")
  write_dl3dv_scenes(root / "scenes", DL3DV_TRAINING + list(DL3DV_HELD_OUT))
  index = root / "index.json"
  index.write_text(json.dumps({**DL3DV_HELD_OUT, "absent": None}))
  return root / "scenes", index


@pytest.mark.slow
def test_dl3dv_entry_point_trains_and_evaluates_on_scene_zips(tmp_path, dl3dv_zips):
  """`python -m experiments.dl3dv run --data-dir ZIPS --eval-index J` (about 110 s here; the
  same plumbing without training: `test_dl3dv_zips_reach_training_and_evaluation_from_the_cli`):
  the index's scenes scored at its views, and never read by the training."""
  folder, index = dl3dv_zips
  out, log = tmp_path / "run", tmp_path / "reads.txt"
  argv = ["run", "synthetic-2view", "--data-dir", str(folder), "--eval-index", str(index)]
  completed = subprocess.run(
    [sys.executable, "-c", _LOGGING_TRAINING_READS, str(log), *argv, "--output-dir", str(out)]
    + DL3DV_SMOKE,
    cwd=REPO,
    capture_output=True,
    text=True,
    timeout=600,
    check=False,
  )
  assert completed.returncode == 0, completed.stderr[-4000:]
  payload = json.loads((out / "metrics.json").read_text())
  for method in ("trained", "untrained", "nearest_view"):
    scenes = payload["metrics"][method]["per_scene"]
    assert [s["key"] for s in scenes] == list(DL3DV_HELD_OUT)
    assert all(math.isfinite(s["psnr"]) for s in scenes)
  assert payload["evaluation_index"] == {"requested": 2, "evaluated": 2, "missing": []}
  assert payload["experiment"]["dataset"] == "dl3dv"
  reads = [line.split() for line in log.read_text().splitlines()]
  trained_on = {key for role, key in reads if role == "train"}
  assert trained_on and trained_on <= set(DL3DV_TRAINING)
  assert (out / "params.msgpack").stat().st_size > 0


def _dl3dv_experiment(*argv):
  from experiments import dl3dv

  return cli.parse(list(argv) + DL3DV_SMOKE, dl3dv.PRESETS, "synthetic-4view", "dl3dv")


def test_dl3dv_zips_reach_training_and_evaluation_from_the_cli(tmp_path, dl3dv_zips):
  """The entry point's flags on a folder of scene zips: training reads every scene but the
  index's, evaluation the index's at its views; the format is read from the folder."""
  folder, index = dl3dv_zips
  command, experiment = _dl3dv_experiment(
    "eval", "synthetic-2view", "--data-dir", str(folder), "--eval-index", str(index)
  )
  assert command == "eval" and data.data_format(experiment) == "zips"
  pipeline = data.training_batches(experiment)
  assert pipeline.source.keys == DL3DV_TRAINING
  batch = next(iter(pipeline))
  assert batch["context_images"].shape == (2, 2, 32, 32, 3)
  assert tasks.Task().check_evaluation(experiment) == {
    "requested": 2,
    "evaluated": 2,
    "missing": [],
  }
  scenes = data.evaluation_scenes(experiment)
  assert [key for key, _ in scenes] == list(DL3DV_HELD_OUT)
  for (_, batch), entry in zip(scenes, DL3DV_HELD_OUT.values()):
    np.testing.assert_array_equal(batch["context_frames"][0], entry["context"])
    np.testing.assert_array_equal(batch["target_frames"][0], entry["target"])
  # without an index one folder has no held-out scenes: refused before any work
  _, unindexed = _dl3dv_experiment("eval", "synthetic-2view", "--data-dir", str(folder))
  with pytest.raises(ValueError, match="name the held-out ones.*--eval-index"):
    data.check_evaluation_data(unindexed)
  assert data.training_batches(unindexed).source.keys == sorted(
    DL3DV_TRAINING + list(DL3DV_HELD_OUT)
  )  # `train` alone: nothing is held out


def test_dl3dv_zips_split_into_train_and_test_hold_out_every_test_scene(tmp_path, dl3dv_zips):
  """`D/train` and `D/test` (e.g. links to DL3DV-ALL and the benchmark): a training scene also
  in test/ is never trained on; without an index every test/ scene is scored."""
  folder, _ = dl3dv_zips
  root = tmp_path / "split"
  (root / "train" / "1K").mkdir(parents=True)
  (root / "test").mkdir()
  for key in DL3DV_TRAINING + ["c0ffee"]:  # DL3DV-ALL holds the benchmark's scenes too
    shutil.copy(folder / f"{key}.zip", root / "train" / "1K")
  shutil.copy(folder / "c0ffee.zip", root / "test")
  _, experiment = _dl3dv_experiment(
    "run", "synthetic-2view", "--data-dir", str(root), "--eval.num-target-views", "2"
  )
  assert data.training_batches(experiment).source.keys == DL3DV_TRAINING
  assert data.check_evaluation_data(experiment) is None
  ((key, batch),) = data.evaluation_scenes(experiment)
  assert key == "c0ffee" and batch["target_images"].shape[1] == 2


def test_a_data_dir_of_neither_format_or_dl3dv_zips_under_re10k_settings_is_refused(
  tmp_path, dl3dv_zips
):
  folder, index = dl3dv_zips
  (tmp_path / "empty" / "train").mkdir(parents=True)
  (tmp_path / "empty" / "train" / "notes.txt").write_text("nothing to read")
  for root, message in (
    (tmp_path / "empty", "empty: holds neither pixelSplat chunks.*nor DL3DV scenes"),
    (tmp_path / "nowhere", "--data-dir .*nowhere: no such folder"),
  ):
    _, experiment = _dl3dv_experiment("run", "synthetic-2view", "--data-dir", str(root))
    with pytest.raises(ValueError, match=message):
      tasks.Task().prepare(experiment)
  re10k_settings = dataclasses.replace(
    _dl3dv_experiment("run", "--data-dir", str(folder))[1], dataset="re10k"
  )
  with pytest.raises(ValueError, match="holds DL3DV scenes: pass --dataset dl3dv"):
    tasks.Task().prepare(re10k_settings)
  _, depth = _dl3dv_experiment(
    "train", "--data-dir", str(folder), "--eval-index", str(index), "--train.lambda-depth", "0.1"
  )
  with pytest.raises(ValueError, match="lambda_depth > 0 needs true depths"):
    data.training_batches(depth)
