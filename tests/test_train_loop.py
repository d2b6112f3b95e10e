"""The training loop: exact resume from a checkpoint (past a damaged one), the training log kept
across resumes, loud stop on non-finite values."""

import dataclasses
import logging

import jax
import numpy as np
import pytest
from test_checkpoint import truncate_json
from test_train import toy_batch, toy_loss, toy_params

from tokengs_jax.train import (
  Checkpointer,
  LoopConfig,
  NonFiniteError,
  OptimConfig,
  create_train_state,
  make_optimizer,
  train,
)

OPTIM = OptimConfig(
  learning_rate=1e-2, schedule="one_cycle", total_steps=6, warmup_steps=2, accumulation_steps=2
)


class ToyBatches:
  """A resumable batch iterator with grain's `get_state`/`set_state` protocol."""

  def __init__(self, poison_at=None):
    self.position, self.poison_at = 0, poison_at

  def __next__(self):
    batch = toy_batch(self.position)
    if self.position == self.poison_at:
      batch["x"][0, 0] = np.nan
    self.position += 1
    return batch

  def get_state(self):
    return {"position": self.position}

  def set_state(self, state):
    self.position = state["position"]


def quiet(step, metrics):
  del step, metrics


def test_resume_is_exact(tmp_path):
  config = LoopConfig(total_steps=12, log_every=4, checkpoint_every=6)
  full, _ = train(toy_loss, toy_params(), ToyBatches(), OPTIM, config, log_fn=quiet)

  directory = str(tmp_path / "run")
  # "killed" after 6 steps: a separate run whose state is then discarded
  train(
    toy_loss,
    toy_params(),
    ToyBatches(),
    OPTIM,
    LoopConfig(total_steps=6, log_every=4, checkpoint_dir=directory),
    log_fn=quiet,
  )
  resumed_batches = ToyBatches()
  # fresh params with another seed prove the checkpoint, not the argument, is used
  resumed, _ = train(
    toy_loss,
    toy_params(seed=5),
    resumed_batches,
    OPTIM,
    LoopConfig(total_steps=12, log_every=4, checkpoint_every=6, checkpoint_dir=directory),
    log_fn=quiet,
  )
  assert resumed_batches.position == 12
  assert int(resumed.step) == 12
  jax.tree.map(
    np.testing.assert_array_equal, jax.device_get(full.params), jax.device_get(resumed.params)
  )
  jax.tree.map(
    np.testing.assert_array_equal, jax.device_get(full.opt_state), jax.device_get(resumed.opt_state)
  )


def test_non_finite_stops_and_keeps_last_good_checkpoint(tmp_path):
  directory = str(tmp_path / "run")
  with pytest.raises(NonFiniteError, match=r"step 5 .*Last good checkpoint: step 4"):
    train(
      toy_loss,
      toy_params(),
      ToyBatches(poison_at=5),
      OPTIM,
      LoopConfig(total_steps=12, log_every=100, checkpoint_every=2, checkpoint_dir=directory),
      log_fn=quiet,
    )
  checkpointer = Checkpointer(directory)
  assert checkpointer.all_steps()[-1] == 4
  state, data_state = checkpointer.restore(
    create_train_state(toy_params(), make_optimizer(OPTIM), seed=0)
  )
  assert data_state["iterator"] == {"position": 4}
  assert [entry["step"] for entry in data_state["history"]] == [2, 4]
  assert all(np.all(np.isfinite(leaf)) for leaf in jax.tree.leaves(jax.device_get(state.params)))


def test_resume_past_a_damaged_checkpoint_is_exact_and_keeps_the_log(tmp_path, capsys, caplog):
  """Killed after step 6 with step 6's checkpoint damaged (its JSON truncated): the rerun says it skipped
  step 6, resumes from step 3, ends bit-equal to an uninterrupted run, and its history holds the
  steps logged before the checkpoint."""
  config = LoopConfig(total_steps=9, log_every=3, checkpoint_every=3)
  full, full_history = train(toy_loss, toy_params(), ToyBatches(), OPTIM, config, log_fn=quiet)

  directory = tmp_path / "run"
  train(
    toy_loss,
    toy_params(),
    ToyBatches(),
    OPTIM,
    dataclasses.replace(config, total_steps=6, checkpoint_dir=str(directory)),
    log_fn=quiet,
  )
  truncate_json(directory / "6")
  capsys.readouterr()
  resumed_batches = ToyBatches()
  with caplog.at_level(logging.WARNING, logger="tokengs_jax.train.checkpoint"):
    resumed, history = train(
      toy_loss,
      toy_params(seed=5),
      resumed_batches,
      OPTIM,
      dataclasses.replace(config, checkpoint_dir=str(directory)),
      log_fn=quiet,
    )
  assert "[train] resuming from step 3" in capsys.readouterr().out
  assert any(
    "checkpoint step 6" in r.getMessage() and "unusable, skipped" in r.getMessage()
    for r in caplog.records
  )
  assert resumed_batches.position == 9 and int(resumed.step) == 9
  jax.tree.map(np.testing.assert_array_equal, jax.device_get(full), jax.device_get(resumed))
  assert [entry["step"] for entry in history] == [3, 6, 9]
  assert [entry["loss"] for entry in history] == [entry["loss"] for entry in full_history]
