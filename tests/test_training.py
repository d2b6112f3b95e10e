"""experiments.training: how a run ends when the loop cannot go on; gradient accumulation, the
periodic held-out evaluation, the training pictures (TensorBoard) and the weights' moving
average."""

import dataclasses
import json
import math

import numpy as np
import pytest
from tensorboard_events import summaries

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


def _parse(*argv):
  from experiments import cli, re10k

  return cli.parse(["run", "smoke", *argv], re10k.PRESETS, "synthetic-tiny", "prog")[1]


def test_accumulation_and_periodic_evaluation_flags_reach_the_optimiser_and_the_loop(capsys):
  """`--train.grad-accum-steps` (issue 26): the optimiser averages that many micro-batches per
  update, the loop runs that many micro-steps per optimiser step with every period scaled to
  land on one; `--train.eval-every` reaches the loop's evaluation period. Bad values are
  refused as the command line is parsed."""
  from experiments.config import optim_config

  experiment = _parse(
    "--train.grad-accum-steps",
    "2",
    "--train.eval-every",
    "3",
    "--train.checkpoint-every",
    "5",
    "--train.log-image-every",
    "4",
  )
  assert optim_config(experiment).accumulation_steps == 2
  assert optim_config(experiment).total_steps == experiment.train.steps  # optimiser updates
  loop = training._loop_config(experiment)
  assert (loop.total_steps, loop.log_every, loop.eval_every, loop.checkpoint_every) == (
    2 * experiment.train.steps,
    2 * experiment.train.log_every,
    6,
    10,
  )
  assert loop.image_every == 8
  assert training._loop_config(_parse()).eval_every == 0  # off by default
  assert optim_config(_parse()).accumulation_steps == 1
  for argv, said in [
    (("--train.grad-accum-steps", "0"), "grad_accum_steps must be >= 1"),
    (("--train.grad-accum-steps", "3"), "batch_size 2 does not split into grad_accum_steps 3"),
    (("--train.eval-every", "-1"), "eval_every must be >= 0"),
    (("--train.eval-every", "2", "--train.eval-scenes", "0"), "eval_scenes >= 1"),
    (("--train.log-image-every", "-1"), "log_image_every must be >= 0"),
  ]:
    with pytest.raises(SystemExit):
      _parse(*argv)
    assert said in " ".join(capsys.readouterr().err.replace("│", " ").split()), argv


class _Numbered:
  """Batches {"x": [2k, 2k + 1]}, k = 0, 1, ..., with a grain-like state."""

  def __init__(self):
    self.next = 0

  def __next__(self):
    self.next += 1
    return {"x": np.array([2 * self.next - 2, 2 * self.next - 1])}

  def get_state(self):
    return {"next": self.next}

  def set_state(self, state):
    self.next = state["next"]


def test_micro_batches_split_each_batch_and_resume_between_two_of_them():
  micro = training._MicroBatches(_Numbered(), 2)
  assert [int(next(micro)["x"][0]) for _ in range(3)] == [0, 1, 2]
  state = json.loads(json.dumps(micro.get_state()))  # mid-batch, as a checkpoint holds it
  resumed = training._MicroBatches(_Numbered(), 2)
  resumed.set_state(state)
  assert [int(next(resumed)["x"][0]) for _ in range(3)] == [3, 4, 5]
  assert [int(next(micro)["x"][0]) for _ in range(3)] == [3, 4, 5]
  with pytest.raises(
    ValueError, match="batch of 2 examples does not split into grad_accum_steps 3"
  ):
    next(training._MicroBatches(_Numbered(), 3))
  loss_fn, _ = training._accumulated(lambda params, batch, key, step: step, iter(()), 3)
  assert [loss_fn(None, None, None, step) for step in (0, 2, 3, 7)] == [0, 0, 1, 2]


def test_a_run_scores_held_out_scenes_every_eval_every_steps_with_accumulation(tmp_path):
  """The smoke preset for 4 optimiser steps of 2 micro-batches each, scored on one test scene
  every 2 steps: the history (train_history.json) holds "eval/psnr" and "eval/ssim" at steps 2
  and 4, and the training metrics at every step, all counted in optimiser steps."""
  from experiments import re10k, tasks

  smoke = re10k.PRESETS["smoke"]
  experiment = dataclasses.replace(
    smoke,
    output_dir=str(tmp_path / "out"),
    synthetic_dir=str(tmp_path / "data"),
    synthetic=dataclasses.replace(smoke.synthetic, num_train=2, num_test=1, num_ood=0, workers=1),
    train=dataclasses.replace(
      smoke.train,
      steps=4,
      batch_size=8,  # micro-batches of 4, one example per test device
      log_every=1,
      grad_accum_steps=2,
      eval_every=2,
      eval_scenes=1,
      log_image_every=2,
    ),
  )
  tasks.execute("train", experiment)
  history = json.loads((tmp_path / "out" / "train_history.json").read_text())
  evaluated = [entry for entry in history if "eval/psnr" in entry]
  assert [entry["step"] for entry in evaluated] == [2, 4]
  for entry in evaluated:
    assert math.isfinite(entry["eval/psnr"]) and 0 < entry["eval/ssim"] <= 1
  assert [entry["step"] for entry in history if "loss" in entry] == [1, 2, 3, 4]
  # `train.log_image_every`: the first test scene's grid and Gaussian histograms, at the same
  # optimiser steps
  pictures = {
    tag: sorted(steps)
    for tag, steps in summaries(tmp_path / "out" / "tensorboard").items()
    if not tag.startswith(("train/", "eval/")) or tag == "train/images"
  }
  tags = ["train/images", "gaussian/opacity", "gaussian/log_scale", "gaussian/distance"]
  assert pictures == {tag: [2, 4] for tag in tags}


def test_training_pictures_are_off_at_0_or_without_a_writer_and_a_failure_ends_only_them(
  tmp_path, capsys
):
  """`train.log_image_every` 0 (or a process that writes no results: no writer) draws nothing
  and the loop gets no image period; a picture that fails says so once and stops the pictures,
  never the training."""
  off = dataclasses.replace(_experiment(tmp_path), train=TrainSettings(log_image_every=0))
  assert training._loop_config(off).image_every == 0
  assert training.training_pictures(off, list, None, object()) is None
  assert training.training_pictures(_experiment(tmp_path), list, None, None) is None
  asked = []

  def missing():
    asked.append(1)
    raise FileNotFoundError("no test split in /data")

  pictures = training.training_pictures(_experiment(tmp_path), missing, None, object())
  pictures(100, {})
  pictures(200, {})
  said = capsys.readouterr().out
  assert said.count("not written") == 1 and len(asked) == 1
  assert "training pictures at step 100: FileNotFoundError: no test split in /data" in said


def test_a_dynamic_models_training_pictures_show_it_at_the_targets_times(tmp_path):
  """A time-conditioned model is drawn as evaluation draws it (each target at its own time);
  its histograms are of the Gaussians at the first target's time."""
  from scenes import DYNAMIC_CONFIG, dynamic_batch, dynamic_params
  from tensorboardX import SummaryWriter

  from tokengs_jax import evaluation

  params = dynamic_params()
  batch = dynamic_batch([[0.0, 1.0]], [[0.2, 0.9]])
  writer = SummaryWriter(str(tmp_path))
  pictures = training.training_pictures(
    _experiment(tmp_path),
    lambda: [("scene", batch)],
    lambda trained: evaluation.feed_forward(trained, DYNAMIC_CONFIG),
    writer,
  )
  pictures(7, params)
  writer.close()
  read = summaries(tmp_path)
  assert read["train/images"].keys() == {7}
  at_times = evaluation.gaussians_for_batch(params, batch, DYNAMIC_CONFIG)  # [1, 2]
  distances = [np.linalg.norm(np.asarray(at_times.means[0, t]), axis=-1) for t in (0, 1)]
  assert not np.allclose(distances[0], distances[1])  # the dynamic Gaussians moved
  assert read["gaussian/distance"][7].histo.sum == pytest.approx(distances[0].sum(), rel=1e-5)


def test_the_ema_flag_reaches_the_optimiser_and_the_run_hands_on_the_averaged_weights(
  tmp_path, monkeypatch, capsys
):
  """`--train.ema-decay D` (issue 26): off by default, refused outside [0, 1) at parse time; when
  on, `train_model` returns (to be saved as params.msgpack and evaluated) the average, and says
  so."""
  from experiments.config import optim_config
  from tokengs_jax.train import TrainState

  assert optim_config(_parse()).ema_decay == 0.0
  assert optim_config(_parse("--train.ema-decay", "0.999")).ema_decay == 0.999
  for bad in ("-0.5", "1", "1.5", "nan"):
    with pytest.raises(SystemExit):
      _parse("--train.ema-decay", bad)
    assert "ema_decay must be in [0, 1)" in " ".join(
      capsys.readouterr().err.replace("│", " ").split()
    ), bad

  state = TrainState(
    params={"w": np.zeros(2)}, opt_state=(), step=np.int32(3), rng=np.zeros(2, np.uint32)
  )
  monkeypatch.setattr(
    tokengs_jax.train,
    "train",
    lambda *args, **kwargs: (state.replace(ema_params={"w": np.ones(2)}), []),
  )
  experiment = _experiment(tmp_path)
  averaged = dataclasses.replace(
    experiment, train=dataclasses.replace(experiment.train, ema_decay=0.9)
  )
  params, _, _ = training.train_model(averaged, {}, None, iter(()))
  np.testing.assert_array_equal(params["w"], np.ones(2))
  assert "[train] EMA of weights, decay 0.9: the saved params.msgpack" in capsys.readouterr().out
  monkeypatch.setattr(tokengs_jax.train, "train", lambda *args, **kwargs: (state, []))
  params, _, _ = training.train_model(experiment, {}, None, iter(()))
  np.testing.assert_array_equal(params["w"], np.zeros(2))
  assert "EMA" not in capsys.readouterr().out
