"""experiments/: command-line parsing, baselines, results writing, plots, and the entry point end to end."""

import dataclasses
import json
import math
import pathlib
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from experiments import common, plot, re10k
from tokengs_jax import export

REPO = pathlib.Path(__file__).resolve().parent.parent


def test_parse_defaults_to_run_with_default_preset():
  command, experiment = common.parse([], re10k.PRESETS, "synthetic-tiny", "prog")
  assert command == "run"
  assert experiment == re10k.PRESETS["synthetic-tiny"]


def test_parse_command_preset_and_overrides():
  command, experiment = common.parse(
      ["eval", "--preset", "paper", "--data-dir", "/x", "--train.steps", "7",
       "--official-checkpoint", "w.safetensors", "--model-overrides", "enc_depth=1"],
      re10k.PRESETS, "synthetic-tiny", "prog")
  assert command == "eval"
  assert experiment.data_dir == "/x" and experiment.train.steps == 7
  assert experiment.official_checkpoint == "w.safetensors"
  assert experiment.model == "re10k"  # from the preset, not the default
  assert common.model_config(experiment).enc_depth == 1


def test_parse_rejects_unknown_preset():
  with pytest.raises(SystemExit):
    common.parse(["--preset=nope"], re10k.PRESETS, "synthetic-tiny", "prog")


def test_mean_colour_baseline_is_the_context_mean():
  rng = np.random.default_rng(0)
  batch = {"context_images": rng.uniform(size=(1, 2, 4, 5, 3)),
           "target_images": np.zeros((1, 3, 4, 5, 3))}
  images = common.mean_colour_images(batch)
  assert images.shape == (1, 3, 4, 5, 3)
  np.testing.assert_allclose(images[0, 2, 1, 1], batch["context_images"][0].mean(axis=(0, 1, 2)))


def test_write_metrics_means_over_scenes_and_markdown(tmp_path):
  result = common.MethodResult("trained", per_scene=[
      {"key": "a", "psnr": 10.0, "ssim": 0.5}, {"key": "b", "psnr": 20.0, "ssim": 0.7}])
  base = common.MethodResult("mean_colour", per_scene=[
      {"key": "a", "psnr": 8.0, "ssim": 0.1}, {"key": "b", "psnr": 9.0, "ssim": 0.2}])
  results = {"mean_colour": base, "trained": result}
  info = {"title": "t", "checks": common.score_checks({k: r.summary() for k, r in results.items()})}
  payload = common.write_metrics(tmp_path, results, info)
  assert payload["metrics"]["trained"]["mean"]["psnr"] == pytest.approx(15.0)
  assert json.loads((tmp_path / "metrics.json").read_text())["metrics"]["mean_colour"]["mean"][
      "ssim"] == pytest.approx(0.15)
  text = (tmp_path / "metrics.md").read_text()
  assert "| trained | 15.0000 | 0.6000 |" in text
  assert "trained beats mean_colour: True (PSNR margin +6.500 dB)" in text


def test_line_plot_draws_every_series(tmp_path):
  path = plot.line_plot(tmp_path / "p.png", {"a": ([1, 2, 4], [1.0, 2.0, 1.5]),
                                             "b": ([1, 2, 4], [0.5, float("nan"), 3.0])},
                        title="t", xlabel="x", ylabel="y", log_x=True, dashed=("b",))
  image = np.asarray(Image.open(path))
  for color in plot.PALETTE[:2]:
    assert np.any(np.all(image == np.array(color, np.uint8), axis=-1)), color


def test_trajectory_plot_on_background(tmp_path):
  tracks = np.stack([np.linspace([2, 2], [20, 10], 5), np.linspace([30, 5], [5, 30], 5)])
  path = plot.trajectory_plot(tmp_path / "t.png", tracks, title="flow",
                              background=np.zeros((32, 32, 3)), size=64)
  assert Image.open(path).size == (64, 64)


def test_entry_point_end_to_end(tmp_path):
  """`python -m experiments.re10k --preset smoke`: generate, train, evaluate, write every file."""
  out = tmp_path / "results"
  completed = subprocess.run(
      [sys.executable, "-m", "experiments.re10k", "--preset", "smoke", "--output-dir", str(out),
       "--synthetic-dir", str(tmp_path / "data")],
      cwd=REPO, capture_output=True, text=True, timeout=600, check=False)
  assert completed.returncode == 0, completed.stderr[-4000:]
  payload = json.loads((out / "metrics.json").read_text())
  assert set(payload["metrics"]) == {"mean_colour", "untrained", "trained", "trained+token_tuning"}
  for method in payload["metrics"].values():
    assert len(method["per_scene"]) == 2
    for value in method["mean"].values():
      assert math.isfinite(value)
  for name in ("metrics.md", "flythrough.mp4", "gaussians.ply", "params.msgpack",
               "train_history.json"):
    assert (out / name).stat().st_size > 0, name
  assert list((out / "grids").glob("*.png"))
  assert list((out / "tensorboard").glob("events.out.tfevents.*"))
  ply = export.read_ply(out / "gaussians.ply")
  assert ply["means"].shape == (64, 3) and np.isfinite(ply["means"]).all()


@pytest.mark.slow
def test_kubric_entry_point_end_to_end(tmp_path):
  """`python -m experiments.kubric` on two tiny generated scenes: dynamic pictures and metrics."""
  out = tmp_path / "results"
  completed = subprocess.run(
      [sys.executable, "-m", "experiments.kubric", "--output-dir", str(out),
       "--synthetic-dir", str(tmp_path / "data"), "--synthetic.num-train", "2",
       "--synthetic.num-test", "1", "--synthetic.frames", "6", "--synthetic.workers", "1",
       "--num-cameras", "2", "--max-gap", "4", "--train.steps", "2", "--train.batch-size", "2",
       "--train.log-every", "1", "--eval.num-scenes", "1", "--eval.video-frames", "2",
       "--eval.tuning-steps", "2",
       "--flow-times", "3", "--model-overrides", "dec_patch_size=4", "num_dynamic_gs_tokens=2",
       "time_embedding=True", "enc_depth=1", "dec_depth=1", "enc_embed_dim=32", "enc_num_heads=2",
       "num_gs_tokens=4"],
      cwd=REPO, capture_output=True, text=True, timeout=600, check=False)
  assert completed.returncode == 0, completed.stderr[-4000:]
  payload = json.loads((out / "metrics.json").read_text())
  assert set(payload["metrics"]) == {"mean_colour", "untrained", "trained", "trained+token_tuning"}
  for method in ("trained", "trained+token_tuning"):
    assert math.isfinite(payload["metrics"][method]["mean"]["psnr"])
  history = json.loads((out / "train_history.json").read_text())
  # the official auxiliary weight, scaled to 2 steps: held at step 0, decayed to 0 at step 1
  assert [h["dyn_aux_weight"] for h in history] == pytest.approx([0.3, 0.0])
  for name in ("mean_dynamic", "median_dynamic", "median_tracked", "mean_static"):
    assert math.isfinite(payload["dynamic"][f"{name}_displacement_t0_t1"]), name
  for name in ("in_between_times.png", "static_dynamic.png", "scene_flow.png"):
    assert (out / "dynamic" / name).stat().st_size > 0, name


def test_kubric_loss_is_the_official_release_scaled_to_the_run():
  from experiments import kubric

  paper = kubric.PRESETS["paper"]
  config = kubric.KubricTask().loss_config(paper)
  assert (config.rgb_loss, config.lambda_rgb, config.lambda_ssim, config.lambda_vis) == (
      "l1", 0.8, 0.2, 1.0)
  # official release: 0.3 held for 5k steps, decayed to 0 over 10k (of 50k finetuning steps)
  assert (config.lambda_dyn_aux, config.dyn_aux_hold_steps, config.dyn_aux_decay_steps,
          config.dyn_aux_min) == (0.3, 5_000, 10_000, 0.0)
  tiny = kubric.PRESETS["synthetic-tiny"]
  config = kubric.KubricTask().loss_config(tiny)
  assert config.dyn_aux_hold_steps == round(0.1 * tiny.train.steps)
  assert config.dyn_aux_decay_steps == round(0.2 * tiny.train.steps)
  assert kubric.KubricTask().objective(tiny).decode_times == "first"
  mse = dataclasses.replace(tiny, rgb_loss="l2")
  assert kubric.KubricTask().loss_config(mse).rgb_loss == "l2"


def test_tick_labels_keep_significant_zeros():
  ticks = np.array([0.0, 10.0, 25.0, 50.0])
  assert [plot._label(v, ticks) for v in ticks] == ["0", "10", "25", "50"]
  assert plot._label(19.0, np.array([18.5, 19.0, 19.5])) == "19"


def test_evaluation_examples_read_a_list_format_index(tmp_path):
  """A Long-LRM list index (official DL3DV eval form): its context list, every frame a target."""
  smoke = re10k.PRESETS["smoke"]
  experiment = dataclasses.replace(
      smoke, synthetic_dir=str(tmp_path / "data"),
      synthetic=dataclasses.replace(smoke.synthetic, num_train=1, num_test=1, workers=1))
  common.ensure_synthetic(experiment)
  key = common.evaluation_examples(experiment)[0][0]
  index = tmp_path / "index.json"
  index.write_text(json.dumps([{"scene_name": key, "fold_8_kmeans_2_input": [1, 7]}]))
  (got_key, batch), = common.evaluation_examples(
      dataclasses.replace(experiment, eval_index=str(index)))
  assert got_key == key
  frames = smoke.synthetic.frames
  assert batch["context_images"].shape[1] == 2 and batch["target_images"].shape[1] == frames
  for view, frame in enumerate([1, 7]):  # the listed inputs are frames 1 and 7 of the targets
    np.testing.assert_array_equal(batch["context_images"][0, view], batch["target_images"][0, frame])
  with pytest.raises(ValueError, match="fold_8_kmeans_3_input"):
    common.evaluation_examples(dataclasses.replace(experiment, eval_index=str(index),
                                                   num_context_views=3))


def test_merge_history_keeps_the_log_of_a_resumed_run():
  earlier = [{"step": 5, "loss": 1.0}, {"step": 10, "loss": 0.9}, {"step": 15, "loss": 0.8}]
  assert common.merge_history(earlier, []) == earlier  # re-evaluation only: log kept
  resumed = [{"step": 15, "loss": 0.7}, {"step": 20, "loss": 0.6}]
  assert [e["loss"] for e in common.merge_history(earlier, resumed)] == [1.0, 0.9, 0.7, 0.6]
  fresh = [{"step": 5, "loss": 2.0}]
  assert common.merge_history(earlier, fresh) == fresh
