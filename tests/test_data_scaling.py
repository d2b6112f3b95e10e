"""benchmarks/data_scaling.py (issue 23): each point trains from scratch, and a folder trained
on another budget is refused rather than tabulated."""

import json
import pathlib
import sys

import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent / "benchmarks"))

import data_scaling  # noqa: E402


def test_a_point_trains_the_shipped_recipe_from_scratch_on_its_scenes(tmp_path):
  """The point's command, parsed as the entry point parses it: the `pretrain` recipe (no
  checkpoint: the default's shipped weights would make every point the same model) on N scenes
  for the asked steps, scored feed-forward."""
  from experiments import cli, re10k

  command = data_scaling.point_command(tmp_path, scenes=48, seed=2, steps=300)
  assert command[1:3] == ["-m", "experiments.re10k"]
  verb, experiment = cli.parse(command[3:], re10k.PRESETS, "synthetic-tiny", "prog")
  assert verb == "run"
  pretrain = re10k.PRESETS["pretrain"]
  assert experiment.checkpoint is None and pretrain.checkpoint is None
  assert experiment.model == pretrain.model
  assert (experiment.synthetic.num_train, experiment.seed) == (48, 2)
  assert experiment.train.steps == 300
  assert experiment.train.learning_rate == pretrain.train.learning_rate
  assert experiment.output_dir == str(tmp_path / "n48_s2")
  assert experiment.synthetic_dir == str(tmp_path / "data_n48_s2")
  assert (experiment.eval.tuning_steps, experiment.eval.pixel_baseline) == (0, False)


def _write_metrics(folder: pathlib.Path, steps: int, scenes: int) -> None:
  folder.mkdir(parents=True)
  metrics = {"train_steps": steps, "experiment": {"synthetic": {"num_train": scenes}}}
  (folder / "metrics.json").write_text(json.dumps(metrics))


def test_only_a_run_of_the_asked_budget_is_a_point(tmp_path):
  _write_metrics(tmp_path / "ok", steps=300, scenes=48)
  assert data_scaling.checked_metrics(tmp_path / "ok", scenes=48, steps=300)["train_steps"] == 300
  _write_metrics(tmp_path / "evaluated_only", steps=0, scenes=48)
  with pytest.raises(SystemExit, match="trained 0 steps on 48 scenes, not 300 on 48"):
    data_scaling.checked_metrics(tmp_path / "evaluated_only", scenes=48, steps=300)
  _write_metrics(tmp_path / "other_scenes", steps=300, scenes=240)
  with pytest.raises(SystemExit, match="on 240 scenes, not 300 on 48"):
    data_scaling.checked_metrics(tmp_path / "other_scenes", scenes=48, steps=300)
