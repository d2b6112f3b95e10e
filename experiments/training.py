"""Training an experiment's model with the library loop, with a progress bar and TensorBoard."""

from __future__ import annotations

import pathlib
import time

import jax

from experiments.config import Experiment, optim_config


class _TrainLogger:
  """The loop's `log_fn`: a tqdm progress bar plus TensorBoard scalars."""

  def __init__(self, total_steps: int, writer, start_step: int = 0):
    from tqdm.auto import tqdm

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
    for name, value in logged.items():
      if name != "step" and self.writer is not None:
        self.writer.add_scalar(name if "/" in name else f"train/{name}", value, step)
    if "loss" in logged:
      self.bar.update(step - self.bar.n)
      self.bar.set_postfix(loss=f"{logged['loss']:.4f}", psnr=f"{logged.get('psnr', 0):.2f}")

  def close(self) -> None:
    self.bar.close()


def train_model(
  experiment: Experiment, params, loss_fn, batches, writer=None
) -> tuple[dict, list[dict], float]:
  """Trains with the library loop (sharded over every device); returns (params, history, seconds).
  With `train.steps == 0` the starting weights come back unchanged (`run` then evaluates them).
  SIGTERM/SIGINT: the loop saves the step it finished and says so; the process then exits with
  128 + the signal's number (`SystemExit`), and the same command resumes. A checkpoint that
  cannot be written (disk full, permission denied) ends the run with its one-line reason, status 1.

  loss_fn: `(params, batch, key, step) -> (loss, aux)`.
  batches: iterator of this process's batches.
  """
  from tokengs_jax.train import CheckpointWriteError, LoopConfig, TrainingStopped, train

  if experiment.train.steps == 0:
    print("[train] 0 steps: the starting weights are the trained ones", flush=True)
    return jax.device_get(params), [], 0.0

  out = pathlib.Path(experiment.output_dir)
  loop = LoopConfig(
    total_steps=experiment.train.steps,
    seed=experiment.seed,
    log_every=experiment.train.log_every,
    checkpoint_every=experiment.train.checkpoint_every,
    checkpoint_dir=str((out / "checkpoints").resolve()),
    async_checkpoint=False,
  )
  logger = _TrainLogger(experiment.train.steps, writer)
  start = time.perf_counter()
  try:
    state, history = train(loss_fn, params, batches, optim_config(experiment), loop, log_fn=logger)
  except TrainingStopped as stopped:  # the loop has said where and how to resume
    raise SystemExit(stopped.exit_status) from None
  except CheckpointWriteError as refused:  # its message names the step, the path and the remedy
    print(f"[train] {refused}", flush=True)
    raise SystemExit(1) from None
  finally:
    logger.close()
  seconds = time.perf_counter() - start
  return jax.device_get(state.params), history, seconds
