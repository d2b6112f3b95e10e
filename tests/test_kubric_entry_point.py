"""`python -m experiments.kubric` end to end (slow). Named `test_kubric_entry_point` as
test_kubric is the Kubric reader's (`tokengs_jax.data.kubric`)."""

import json
import math

import jax
import pytest
from small_experiments import run_entry_point

from tokengs_jax import model


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
  completed = run_entry_point(
    "-m",
    "experiments.kubric",
    "--checkpoint",
    start,
    "--output-dir",
    out,
    "--synthetic-dir",
    tmp_path / "data",
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
  )
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
