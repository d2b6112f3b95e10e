"""`python -m experiments.re10k` end to end (the entry point's run, its weights shipped, the run
re-evaluated from its folder)."""

import json
import math

import numpy as np
from small_experiments import run_entry_point

from tokengs_jax import export


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
  """`python -m experiments.re10k run pretrain` then `run finetune` (the two commands that
  trained the shipped weights) at the smoke preset's scale: generate (the varied family), train
  TokenGS and the pixel-aligned baseline from scratch, evaluate with geometry, write every file;
  train both on from there with the finetune recipe; then ship those weights as the shipped ones
  were (`experiments.weights ship`), and re-evaluate the run from its folder alone
  (`eval --from-run`) to the same scores."""
  out = tmp_path / "results"
  run_entry_point(
    "-m",
    "experiments.re10k",
    "run",
    "pretrain",
    "--output-dir",
    out,
    "--synthetic-dir",
    tmp_path / "data",
    *SMOKE_SCALE,
  )
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

  # the second stage, from both of the first's models; its tuning and video are the first's
  # code at other settings, so left out (each would compile afresh here and in `eval --from-run`)
  pretrained, out = out, tmp_path / "finetuned"
  finetune = run_entry_point(
    *("-m", "experiments.re10k", "run", "finetune", "--checkpoint", pretrained / "params.msgpack"),
    *("--output-dir", out, "--synthetic-dir", tmp_path / "data", *SMOKE_SCALE),
    *("--eval.tuning-steps 0 --eval.video-frames 0").split(),
  )
  assert f"[pixel_aligned] starting from {pretrained / 'pixel_aligned.msgpack'}" in finetune.stdout
  payload = json.loads((out / "metrics.json").read_text())
  train, config = payload["experiment"]["train"], payload["experiment"]["model"]
  assert train["use_input_supervision"] and train["eps2d"] == 0.1 and train["steps"] == 3
  assert config["viewer_colour_sharpness"] == 1000.0
  assert "pixel_aligned" in payload["metrics"]

  run_entry_point("-m", "experiments.weights", "ship", out, tmp_path / "shipped")
  provenance = json.loads((tmp_path / "shipped" / "provenance.json").read_text())
  assert set(provenance["files"]) == {"params.msgpack", "pixel_aligned.msgpack"}
  assert provenance["experiment"] == payload["experiment"]
  assert provenance["command"].startswith("python -m experiments.re10k run finetune")

  # re-evaluated from its folder alone (`eval --from-run`): the same settings, the same scores
  run_entry_point("-m", "experiments.re10k", "eval", "--from-run", out)
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
