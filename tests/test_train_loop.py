"""The training loop (`train.loop`): exact resume from a checkpoint (past a damaged one; with the
parameters' moving average), the training log kept across resumes, loud stop on non-finite
values, a clean stop on SIGTERM/SIGINT; end to end, the TokenGS objective with the real model and
renderer, static (tiny preset; slow: renderer compiles) and dynamic (the loop on generated
Kubric-like scenes)."""

import dataclasses
import logging
import signal

import jax
import numpy as np
import pytest
from checkpoints import truncate_json
from scenes import DYNAMIC_CONFIG, DYNAMIC_SIZE, dynamic_params, synthetic_batch
from toy_training import toy_batch, toy_loss, toy_params

from tokengs_jax import losses
from tokengs_jax.objective import ObjectiveConfig, tokengs_loss_fn
from tokengs_jax.train import (
  Checkpointer,
  LoopConfig,
  NonFiniteError,
  OptimConfig,
  create_train_state,
  make_mesh,
  make_optimizer,
  train,
)
from tokengs_jax.train.loop import TrainingStopped

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


def test_a_resumed_run_keeps_its_parameter_average_exactly(tmp_path):
  """`OptimConfig.ema_decay`: the average is in the checkpoint, so a run stopped and resumed ends
  with the same average as one that was not (and it is not the params)."""
  optim = dataclasses.replace(OPTIM, ema_decay=0.9)
  full, _ = train(
    toy_loss, toy_params(), ToyBatches(), optim, LoopConfig(total_steps=8), log_fn=quiet
  )
  directory = str(tmp_path / "run")
  for total in (4, 8):
    resumed, _ = train(
      toy_loss,
      toy_params(),
      ToyBatches(),
      optim,
      LoopConfig(total_steps=total, checkpoint_dir=directory),
      log_fn=quiet,
    )
  assert int(resumed.step) == 8
  jax.tree.map(
    np.testing.assert_array_equal,
    jax.device_get(full.ema_params),
    jax.device_get(resumed.ema_params),
  )
  assert not np.array_equal(full.ema_params["gs_tokens"], full.params["gs_tokens"])


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


class GuardSignal(Exception):
  """Raised by the handler a test sets before `train`: the signal reached it, not the loop's."""


@pytest.fixture
def guarded(request):
  """Sets a raising handler for SIGTERM and SIGINT (so a signal the loop does not catch fails the
  test instead of ending pytest) and puts the previous ones back afterwards."""

  def guard(signum, frame):
    raise GuardSignal(signal.Signals(signum).name)

  previous = {signum: signal.signal(signum, guard) for signum in (signal.SIGTERM, signal.SIGINT)}
  yield guard
  for signum, handler in previous.items():
    signal.signal(signum, handler)


def signal_at(step_to_signal, *signums):
  """A `log_fn` that sends itself `signums` once `step_to_signal` is logged."""

  def log_fn(step, metrics):
    del metrics
    if step == step_to_signal:
      for signum in signums:
        signal.raise_signal(signum)

  return log_fn


def test_sigterm_finishes_the_step_saves_it_and_stops_then_the_rerun_resumes_exactly(
  tmp_path, capsys, guarded
):
  """SIGTERM while step 3 runs (checkpoints every 1000 steps): training stops after step 3 with
  step 3 saved, says how to resume, hands SIGTERM back; the rerun ends as an uninterrupted run."""
  config = LoopConfig(total_steps=8, log_every=1, checkpoint_every=1000)
  full, _ = train(toy_loss, toy_params(), ToyBatches(), OPTIM, config, log_fn=quiet)

  directory = tmp_path / "run"
  config = dataclasses.replace(config, checkpoint_dir=str(directory))
  with pytest.raises(TrainingStopped) as stopped:
    train(toy_loss, toy_params(), ToyBatches(), OPTIM, config, log_fn=signal_at(3, signal.SIGTERM))
  assert (stopped.value.signal, stopped.value.step, stopped.value.exit_status) == (
    signal.SIGTERM,
    3,
    143,
  )
  assert (
    "[train] SIGTERM: stopped at step 3, resume with the same command" in capsys.readouterr().out
  )
  assert signal.getsignal(signal.SIGTERM) is guarded and signal.getsignal(signal.SIGINT) is guarded
  assert Checkpointer(str(directory)).all_steps() == [3]

  resumed_batches = ToyBatches()
  resumed, history = train(toy_loss, toy_params(), resumed_batches, OPTIM, config, log_fn=quiet)
  assert resumed_batches.position == 8 and [entry["step"] for entry in history] == list(range(1, 9))
  jax.tree.map(np.testing.assert_array_equal, jax.device_get(full), jax.device_get(resumed))


def test_a_second_signal_reaches_the_previous_handler_at_once(tmp_path, guarded):
  with pytest.raises(GuardSignal, match="SIGINT"):
    train(
      toy_loss,
      toy_params(),
      ToyBatches(),
      OPTIM,
      LoopConfig(total_steps=8, log_every=1, checkpoint_dir=str(tmp_path / "run")),
      log_fn=signal_at(2, signal.SIGINT, signal.SIGINT),
    )
  assert signal.getsignal(signal.SIGINT) is guarded


def test_a_signal_during_the_last_step_is_delivered_after_the_final_save(tmp_path, guarded):
  directory = str(tmp_path / "run")
  with pytest.raises(GuardSignal, match="SIGTERM"):
    train(
      toy_loss,
      toy_params(),
      ToyBatches(),
      OPTIM,
      LoopConfig(total_steps=4, log_every=1, checkpoint_every=1000, checkpoint_dir=directory),
      log_fn=signal_at(4, signal.SIGTERM),
    )
  assert Checkpointer(directory).all_steps() == [4]


def test_a_host_array_reaching_the_compiled_step_is_an_error_not_a_silent_copy(monkeypatch):
  from tokengs_jax.train import loop

  monkeypatch.setattr(loop, "shard_batch", lambda batch, mesh: batch)  # numpy arrays, not placed
  with pytest.raises(Exception, match="[Dd]isallowed host-to-device transfer"):
    train(toy_loss, toy_params(), ToyBatches(), OPTIM, LoopConfig(total_steps=2), log_fn=quiet)


def test_the_image_hook_runs_every_image_every_steps_with_that_steps_params():
  """`image_fn` sees the step count and the parameters that step produced (fetched between two
  steps, outside the compiled one); a period of 0, or no hook, calls nothing."""
  seen = []

  def hook(step, state):
    seen.append((step, int(jax.device_get(state.step)), jax.device_get(state.params)))

  config = LoopConfig(total_steps=6, image_every=2)
  train(toy_loss, toy_params(), ToyBatches(), OPTIM, config, log_fn=quiet, image_fn=hook)
  assert [(step, state_step) for step, state_step, _ in seen] == [(2, 2), (4, 4), (6, 6)]
  again, _ = train(
    toy_loss, toy_params(), ToyBatches(), OPTIM, LoopConfig(total_steps=4), log_fn=quiet
  )  # the same first four steps without a hook
  kernels = [np.asarray(jax.device_get(p)["dense1"]["kernel"]) for p in (seen[0][2], seen[1][2])]
  np.testing.assert_array_equal(kernels[1], jax.device_get(again.params)["dense1"]["kernel"])
  assert not np.array_equal(kernels[0], kernels[1])
  train(
    toy_loss,
    toy_params(),
    ToyBatches(),
    OPTIM,
    LoopConfig(total_steps=3),
    log_fn=quiet,
    image_fn=lambda step, state: seen.append(step),
  )
  assert len(seen) == 3  # image_every 0: never called


# ---- end to end: the TokenGS objective with the real model and renderer --------------------------


@pytest.mark.slow
def test_tiny_training_loss_falls(tiny):
  config, params = tiny
  batch = synthetic_batch()

  def batches():
    while True:
      yield batch

  history = []
  # two scenes on a 2-device data mesh: the real model and renderer under sharding
  train(
    tokengs_loss_fn(config),
    params,
    batches(),
    OptimConfig(learning_rate=1e-2, schedule="warmup_cosine", total_steps=30, warmup_steps=3),
    LoopConfig(total_steps=30, log_every=5),
    mesh=make_mesh(devices=jax.devices()[:2]),
    log_fn=lambda step, m: history.append(m),
  )
  print("loss every 5 steps:", [round(m["loss"], 4) for m in history])
  assert history[-1]["loss"] < 0.8 * history[0]["loss"]


@pytest.fixture(scope="module")
def kubric_batches(tmp_path_factory):
  """One batch of two examples from two generated Kubric-like scenes through the data pipeline."""
  from tokengs_jax.data import kubric
  from tokengs_jax.data.pipeline import DATASET_PRESETS, InputPipeline
  from tokengs_jax.data.synthetic import generate

  root = tmp_path_factory.mktemp("kubric")
  generate.generate_kubric_like(
    root,
    2,
    DYNAMIC_SIZE,
    DYNAMIC_SIZE,
    frames=6,
    num_cameras=3,
    seed=1,
    config=generate.KubricLikeConfig(supersample=1),
  )
  example_config = dataclasses.replace(
    DATASET_PRESETS["kubric"], image_shape=(DYNAMIC_SIZE, DYNAMIC_SIZE), random_flip=False
  )
  pipeline = InputPipeline(
    kubric.KubricSceneSource(root, num_cameras=3),
    example_config,
    batch_size=2,
    seed=0,
    shuffle=False,
    num_epochs=None,
    shard_index=0,
    shard_count=1,
    select_views=kubric.kubric_view_selector(num_context=2, num_targets=2, min_gap=2, max_gap=5),
  )
  return next(iter(pipeline))


def test_dynamic_training_on_generated_kubric_scenes(kubric_batches):
  batch = kubric_batches
  assert batch["context_times"].shape == batch["target_times"].shape == (2, 2)
  loss_config = losses.LossConfig(
    rgb_loss="l1", lambda_rgb=0.8, lambda_dyn_aux=0.3, dyn_aux_hold_steps=2, dyn_aux_decay_steps=4
  )

  def batches():
    while True:
      yield batch

  history = []
  steps = 30
  # the train step adds "step" to each batch; the auxiliary weight reads it
  train(
    tokengs_loss_fn(DYNAMIC_CONFIG, loss_config, objective=ObjectiveConfig(view_chunk_size=1)),
    dynamic_params(),
    batches(),
    OptimConfig(learning_rate=1e-2, schedule="constant", total_steps=steps),
    LoopConfig(total_steps=steps, log_every=1),
    mesh=make_mesh(devices=jax.devices()[:1]),
    log_fn=lambda step, metrics: history.append(metrics),
  )
  print("rgb per step:", [round(m["rgb"], 4) for m in history])
  assert all(np.isfinite(m["loss"]) and np.isfinite(m["dyn_aux"]) for m in history)
  np.testing.assert_allclose(
    [m["dyn_aux_weight"] for m in history],
    [float(losses.dynamic_aux_weight(s, loss_config)) for s in range(steps)],
    rtol=1e-6,
  )
  # measured: 0.209 -> 0.182 in 30 steps (noisy at first: few, small Gaussians at init)
  assert np.mean([m["rgb"] for m in history[-5:]]) < 0.95 * np.mean([m["rgb"] for m in history[:5]])
