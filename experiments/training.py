"""Training an experiment's model with the library loop, with a progress bar and TensorBoard,
gradient accumulation (`train.grad_accum_steps`) and a periodic held-out score
(`train.eval_every`)."""

from __future__ import annotations

import pathlib
import time
from collections.abc import Callable, Sequence

import jax
import numpy as np

from experiments.config import Experiment, optim_config


class _TrainLogger:
  """The loop's `log_fn`: a tqdm progress bar plus TensorBoard scalars."""

  def __init__(self, total_steps: int, writer, start_step: int = 0, micro_steps: int = 1):
    from tqdm.auto import tqdm

    self.micro_steps = micro_steps  # loop steps per optimiser step: logged in optimiser steps
    self.bar = tqdm(
      total=total_steps,
      initial=start_step,
      desc="train",
      unit="step",
      dynamic_ncols=True,
      mininterval=1.0,
    )
    self.writer = writer

  def __call__(self, step: int, logged: dict) -> None:
    logged = in_optimiser_steps({**logged, "step": step}, self.micro_steps)
    step = logged.pop("step")
    for name, value in logged.items():
      if self.writer is not None:
        self.writer.add_scalar(name if "/" in name else f"train/{name}", value, step)
    if "loss" in logged:
      self.bar.update(step - self.bar.n)
      self.bar.set_postfix(loss=f"{logged['loss']:.4f}", psnr=f"{logged.get('psnr', 0):.2f}")

  def close(self) -> None:
    self.bar.close()


def in_optimiser_steps(entry: dict, micro_steps: int) -> dict:
  """A loop log entry (its "step", "steps_per_s" in loop steps) in optimiser steps, each
  `micro_steps` loop steps (`train.grad_accum_steps`)."""
  entry = {**entry, "step": entry["step"] // micro_steps}
  if "steps_per_s" in entry:
    entry["steps_per_s"] /= micro_steps
  return entry


class _MicroBatches:
  """Each batch of `batches` as `count` equal micro-batches along the batch axis, in turn.

  Its state (what the loop checkpoints) is the wrapped iterator's before the batch being split
  plus the micro-batches of it already given, so a run stopped between two micro-batches resumes
  at the next one.
  """

  def __init__(self, batches, count: int):
    self.batches, self.count = batches, count
    self.pieces, self.given, self.before = [], 0, self._inner_state()

  def _inner_state(self):
    return self.batches.get_state() if hasattr(self.batches, "get_state") else None

  def __iter__(self):
    return self

  def __next__(self) -> dict:
    if self.given == len(self.pieces):
      self.before = self._inner_state()
      batch = {name: np.asarray(value) for name, value in next(self.batches).items()}
      size = len(next(iter(batch.values())))
      if size % self.count:
        raise ValueError(
          f"this process's batch of {size} examples does not split into grad_accum_steps "
          f"{self.count} equal micro-batches"
        )
      parts = {name: np.split(value, self.count) for name, value in batch.items()}
      self.pieces = [{name: part[i] for name, part in parts.items()} for i in range(self.count)]
      self.given = 0
    self.given += 1
    return self.pieces[self.given - 1]

  def get_state(self):
    if self.given == len(self.pieces):  # between two batches
      return {"batches": self._inner_state(), "given": 0}
    return {"batches": self.before, "given": self.given}

  def set_state(self, state) -> None:
    if state["batches"] is not None:
      self.batches.set_state(state["batches"])
    self.pieces, self.given = [], 0
    for _ in range(state["given"]):  # the micro-batches already trained on
      next(self)


def held_out_metrics(
  experiment: Experiment, scenes: Callable[[], Sequence], method: Callable
) -> Callable[[dict], dict] | None:
  """The periodic score of `train.eval_every` (None when 0): `params -> {"psnr", "ssim", ...}`,
  the means over the first `train.eval_scenes` of `scenes()` (the test split's (key, batch)
  pairs) of `method(params)` (an `evaluation.Method`), scored as the final evaluation scores
  (`evaluation.evaluate`) without LPIPS."""
  from tokengs_jax import evaluation

  if experiment.train.eval_every <= 0:
    return None
  chosen = list(scenes())[: experiment.train.eval_scenes]
  scorer = evaluation.Scorer(lpips=False)

  def metrics(params) -> dict:
    scored = evaluation.evaluate(chosen, {"model": method(params)}, scorer)
    return scored.scores["model"].summary()

  return metrics


def training_pictures(
  experiment: Experiment, scenes: Callable[[], Sequence], method: Callable, writer
) -> Callable[[int, dict], None] | None:
  """The TensorBoard pictures of `train.log_image_every` (None when 0 or without a writer, as on
  the processes that write no results): `(step, params) -> None` renders `method(params)` (an
  `evaluation.Method`) on the first of `scenes()` (read at the first call) through the
  evaluation's own path (`evaluation.evaluate`, no LPIPS) and writes its grid and its Gaussians'
  histograms (`results.write_training_pictures`). A picture that fails is reported in one line
  and ends the pictures, never the training."""
  from experiments import results
  from tokengs_jax import evaluation

  if experiment.train.log_image_every <= 0 or writer is None:
    return None
  chosen, failures = [], []

  def write(step: int, params) -> None:
    if failures:
      return
    with results.media_step(f"training pictures at step {step}", failures):
      if not chosen:
        chosen.extend(list(scenes())[:1])
      drawn = evaluation.evaluate(
        chosen, {"prediction": method(params)}, evaluation.Scorer(lpips=False), keep=1
      )
      results.write_training_pictures(writer, drawn.kept[0], "prediction", step)

  return write


def _loop_config(experiment: Experiment):
  """The library loop's settings: its steps are micro-steps (`grad_accum_steps` per optimiser
  step), so every period is scaled to fall on an optimiser step."""
  from tokengs_jax.train import LoopConfig

  t, micro = experiment.train, experiment.train.grad_accum_steps
  return LoopConfig(
    total_steps=t.steps * micro,
    seed=experiment.seed,
    log_every=t.log_every * micro,
    checkpoint_every=t.checkpoint_every * micro,
    eval_every=t.eval_every * micro,
    image_every=t.log_image_every * micro,
    checkpoint_dir=str((pathlib.Path(experiment.output_dir) / "checkpoints").resolve()),
    async_checkpoint=False,
  )


def _accumulated(loss_fn, batches, micro: int):
  """(loss_fn, batches) for `micro` micro-steps per optimiser step: the loss sees the optimiser
  step (its step-scheduled terms keep their schedule), the batches come in micro-batches."""
  if micro == 1:
    return loss_fn, batches

  def micro_loss_fn(params, batch, key, step):
    return loss_fn(params, batch, key, step // micro)

  return micro_loss_fn, _MicroBatches(batches, micro)


def train_model(
  experiment: Experiment, params, loss_fn, batches, writer=None, evaluate=None, pictures=None
) -> tuple[dict, list[dict], float]:
  """Trains with the library loop (sharded over every device); returns (params, history, seconds).
  With `train.steps == 0` the starting weights come back unchanged (`run` then evaluates them).
  SIGTERM/SIGINT: the loop saves the step it finished and says so; the process then exits with
  128 + the signal's number (`SystemExit`), and the same command resumes. A checkpoint that
  cannot be written (disk full, permission denied) ends the run with its one-line reason, status 1.
  The history's and TensorBoard's steps are optimiser steps (`train.grad_accum_steps` loop steps
  each). With `train.ema_decay` > 0 the returned params (and those `evaluate` and `pictures` see)
  are the moving average of the weights (`tokengs_jax.train.trained_params`), and the run says so.

  loss_fn: `(params, batch, key, step) -> (loss, aux)`.
  batches: iterator of this process's batches.
  evaluate: `params -> dict of scalars` (`held_out_metrics`), run every `train.eval_every`
    steps and logged as "eval/<name>"; None: no periodic evaluation.
  pictures: `(step, params) -> None` (`training_pictures`), run every `train.log_image_every`
    steps; None: none.
  """
  from tokengs_jax.train import CheckpointWriteError, TrainingStopped, train, trained_params

  if experiment.train.steps == 0:
    print("[train] 0 steps: the starting weights are the trained ones", flush=True)
    return jax.device_get(params), [], 0.0

  micro = experiment.train.grad_accum_steps
  loss_fn, batches = _accumulated(loss_fn, batches, micro)
  # The weights handed on (evaluated, pictured, returned): the moving average when one is kept.
  eval_fn = None if evaluate is None else lambda s: evaluate(jax.device_get(trained_params(s)))

  def image_fn(step, state):  # the loop's steps are micro-steps
    pictures(step // micro, jax.device_get(trained_params(state)))

  if experiment.train.ema_decay > 0:
    print(
      f"[train] EMA of weights, decay {experiment.train.ema_decay:g}: the saved params.msgpack, "
      "the evaluation, eval_every and the training pictures use the averaged weights; the last "
      "step's raw weights stay in the final checkpoint (checkpoints/, state.params)",
      flush=True,
    )

  logger = _TrainLogger(experiment.train.steps, writer, micro_steps=micro)
  start = time.perf_counter()
  try:
    state, history = train(
      loss_fn,
      params,
      batches,
      optim_config(experiment),
      _loop_config(experiment),
      eval_fn=eval_fn,
      log_fn=logger,
      image_fn=None if pictures is None else image_fn,
    )
  except TrainingStopped as stopped:  # the loop has said where and how to resume
    raise SystemExit(stopped.exit_status) from None
  except CheckpointWriteError as refused:  # its message names the step, the path and the remedy
    print(f"[train] {refused}", flush=True)
    raise SystemExit(1) from None
  finally:
    logger.close()
  seconds = time.perf_counter() - start
  history = [in_optimiser_steps(entry, micro) for entry in history]
  return jax.device_get(trained_params(state)), history, seconds
