"""experiments.training: how a run ends when the loop cannot go on."""

import dataclasses

import pytest

import tokengs_jax.train
from experiments import training
from experiments.config import Experiment, TrainSettings
from tokengs_jax.train import CheckpointWriteError, TrainingStopped


def _experiment(tmp_path):
  return Experiment(output_dir=str(tmp_path), train=dataclasses.replace(TrainSettings(), steps=3))


def _loop_raising(error):
  def loop(*args, **kwargs):
    raise error

  return loop


def test_a_checkpoint_that_cannot_be_written_ends_the_run_with_its_one_line(
  tmp_path, monkeypatch, capsys
):
  refused = CheckpointWriteError(
    f"no space left on device writing checkpoint step 2 to {tmp_path}: free space there"
  )
  monkeypatch.setattr(tokengs_jax.train, "train", _loop_raising(refused))
  with pytest.raises(SystemExit) as ended:
    training.train_model(_experiment(tmp_path), {}, None, iter(()))
  assert ended.value.code == 1
  assert f"[train] no space left on device writing checkpoint step 2 to {tmp_path}" in (
    capsys.readouterr().out
  )


def test_a_stopped_run_exits_with_the_signals_shell_status(tmp_path, monkeypatch):
  monkeypatch.setattr(tokengs_jax.train, "train", _loop_raising(TrainingStopped(15, 7, "ckpt")))
  with pytest.raises(SystemExit) as ended:
    training.train_model(_experiment(tmp_path), {}, None, iter(()))
  assert ended.value.code == 143
