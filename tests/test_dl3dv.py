"""`python -m experiments.dl3dv` on DL3DV scenes as they ship (issue 26): the entry point end to
end (slow), and its flags' data on a folder of scene zips (the reader itself: test_data_dl3dv)."""

import dataclasses
import json
import math
import shutil

import numpy as np
import pytest
from small_experiments import run_entry_point

from experiments import cli, data, tasks


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
  run_entry_point("-c", _LOGGING_TRAINING_READS, log, *argv, "--output-dir", out, *DL3DV_SMOKE)
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
