"""The training loop used by experiments: batches -> sharded steps -> logs, checkpoints, evals."""

from __future__ import annotations

import contextlib
import dataclasses
import signal
import threading
import time
from collections.abc import Callable, Iterator

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from tokengs_jax.train.checkpoint import Checkpointer, iterator_state, set_iterator_state
from tokengs_jax.train.distributed import barrier, make_mesh, replicate, shard_batch
from tokengs_jax.train.optim import OptimConfig, make_optimizer
from tokengs_jax.train.state import TrainState, create_train_state
from tokengs_jax.train.step import LossFn, Precision, make_train_step


@dataclasses.dataclass(frozen=True)
class LoopConfig:
  """Loop settings.

  Attributes:
    total_steps: `train_step` calls (micro-steps: with accumulation k, updates = total_steps / k).
    seed: base RNG seed (stored in the state, so a resume continues the same stream).
    log_every: host sync + log period; the non-finite check runs at this period and before every
      checkpoint (the step itself already refuses a non-finite update).
    checkpoint_every: save period in steps (0: only at the end); needs `checkpoint_dir`.
    eval_every: eval hook period (0: never).
    image_every: image hook period (0: never).
    checkpoint_dir: where checkpoints go; an existing checkpoint there is resumed from.
    max_to_keep: checkpoints kept.
    async_checkpoint: background writes.
  """

  total_steps: int
  seed: int = 0
  log_every: int = 10
  checkpoint_every: int = 1000
  eval_every: int = 0
  image_every: int = 0
  checkpoint_dir: str | None = None
  max_to_keep: int = 3
  async_checkpoint: bool = True


class NonFiniteError(RuntimeError):
  """A loss or gradient became NaN/inf; raised after the last good checkpoint is on disk."""


class TrainingStopped(Exception):
  """SIGTERM or SIGINT stopped training between two steps; with checkpointing on, that step's
  checkpoint is on disk, so rerunning the same command resumes there.

  Attributes:
    signal: the signal that stopped it.
    step: the last step trained (and saved).
    checkpoint_dir: where it was saved; None when checkpointing is off.
  """

  def __init__(self, signum: int, step: int, checkpoint_dir: str | None):
    self.signal, self.step, self.checkpoint_dir = signal.Signals(signum), step, checkpoint_dir
    where = (
      f"checkpoint step {step} in {checkpoint_dir}"
      if checkpoint_dir
      else "checkpointing is off: a rerun starts over"
    )
    super().__init__(
      f"{self.signal.name}: stopped at step {step}, resume with the same command ({where})"
    )

  @property
  def exit_status(self) -> int:
    """The shell's status of a process the signal killed (128 + signal number), for entry points
    that exit on it: schedulers and `experiments.launch` read it as "stopped by that signal"."""
    return 128 + self.signal


def _print_log(step: int, metrics: dict) -> None:
  print(
    f"[train] step {step} " + " ".join(f"{k} {v:.6g}" for k, v in sorted(metrics.items())),
    flush=True,
  )


def train(
  loss_fn: LossFn,
  params,
  batches: Iterator[dict],
  optim_config: OptimConfig,
  loop_config: LoopConfig,
  *,
  mesh: Mesh | None = None,
  precision: Precision | None = None,
  eval_fn: Callable[[TrainState], dict] | None = None,
  log_fn: Callable[[int, dict], None] = _print_log,
  image_fn: Callable[[int, TrainState], None] | None = None,
) -> tuple[TrainState, list[dict]]:
  """Trains `params` on `batches`, resuming from `loop_config.checkpoint_dir` when it holds one.

  Args:
    loss_fn: `(params, batch, key, step) -> (loss, aux)` (e.g. `objective.tokengs_loss_fn(...)`).
    params: initial parameters (host or device pytree, identical on every process); ignored when
      a checkpoint is resumed.
    batches: iterator of this process's batches (dicts of `[B_local, ...]` numpy arrays), all of
      the first batch's shapes (the step is compiled once, ahead of its first run). If it has
      `get_state`/`set_state` (grain), its position is checkpointed and restored (per process).
    optim_config: optimiser and schedule (with `ema_decay` > 0 the state keeps `ema_params`).
    loop_config: loop settings.
    mesh: device mesh; default all devices on "data".
    precision: compute-dtype policy (default `Precision()`: no cast).
    eval_fn: `state -> dict of scalars`, called every `eval_every` steps and logged as "eval/...".
    log_fn: `(step, metrics) -> None`; default prints one line.
    image_fn: `(step, state) -> None`, called every `image_every` steps between two steps, outside
      the compiled one (e.g. renders of the current parameters); must not keep the `state`.

  Returns:
    `(final state, history)`; history is the list of logged dicts (each with "step") of the whole
    run: a resumed run starts from the history saved in its checkpoint (entries up to its step).

  Raises:
    NonFiniteError: a loss/gradient went non-finite; no later checkpoint was written.
    TrainingStopped: SIGTERM or SIGINT arrived (handled while this runs, see `_StopRequest`): the
      step in flight finished and, with checkpointing on, was saved.
  """
  mesh = make_mesh() if mesh is None else mesh
  optimizer = make_optimizer(optim_config)
  state = _initial_state(params, optimizer, mesh, loop_config.seed, optim_config.ema_decay)

  checkpointer = _checkpointer(loop_config)
  # Leaving the blocks waits for a pending save and closes the manager, also on an error, and then
  # gives SIGTERM/SIGINT back to their previous handlers.
  with _StopRequest(mesh) as stop_request, checkpointer or contextlib.nullcontext():
    state, history = _resume(checkpointer, state, batches)
    train_step = make_train_step(
      loss_fn, optimizer, mesh, precision=precision or Precision(), ema_decay=optim_config.ema_decay
    )
    # A separate buffer: the state (and its rng) is donated to each step.
    key = jnp.copy(state.rng)
    step = int(jax.device_get(state.step))
    log = _MetricsLog(history, log_fn, checkpointer)
    compiled = None
    while step < loop_config.total_steps:
      batch = shard_batch(next(batches), mesh)
      if compiled is None:  # compile first, then meet: the first collective runs in step
        compiled = train_step.lower(state, batch, key).compile()
        barrier("tokengs_train_step_compiled")
      # Every input is on its devices already (shard_batch, the state, the key): an implicit host
      # transfer here would be a silent per-step copy, so it is an error (as big_vision's loop).
      with jax.transfer_guard("disallow"):
        state, metrics = compiled(state, batch, key)
      log.pending.append(metrics)
      step += 1
      is_last = step == loop_config.total_steps
      save_now = checkpointer is not None and (
        is_last or _every(loop_config.checkpoint_every, step)
      )
      if save_now or is_last or step % loop_config.log_every == 0:
        log.drain(step)
      _periodic_hooks(loop_config, step, state, log, eval_fn, image_fn)
      if save_now:
        _save(checkpointer, state, batches, log, step)
      if not is_last and (signum := stop_request.agreed()):
        _stop(signum, step, state, batches, log, checkpointer)
    return state, history


def _periodic_hooks(loop_config: LoopConfig, step: int, state, log, eval_fn, image_fn) -> None:
  """The eval and image hooks due at `step`, run before its save (so the checkpoint's history
  holds this step's evaluation)."""
  if eval_fn is not None and _every(loop_config.eval_every, step):
    log.evaluation(step, eval_fn(state))
  if image_fn is not None and _every(loop_config.image_every, step):
    image_fn(step, state)


def _initial_state(params, optimizer, mesh: Mesh, seed: int, ema_decay: float) -> TrainState:
  """A fresh, replicated `TrainState` of `params` (with their moving average when
  `ema_decay` > 0), built on the devices."""
  init_state = jax.jit(
    lambda p: create_train_state(p, optimizer, seed, ema_decay),
    out_shardings=NamedSharding(mesh, P()),
  )
  return init_state(replicate(jax.device_get(params), mesh))


def _save(checkpointer: Checkpointer, state: TrainState, batches, log: _MetricsLog, step: int):
  """Saves `state` with the iterator's position and the log so far as step `step`."""
  checkpointer.save(state, {"iterator": iterator_state(batches), "history": log.history})
  log.last_saved = step


def _stop(signum: int, step: int, state: TrainState, batches, log, checkpointer) -> None:
  """Logs and saves step `step` (unless saved already), says so, raises `TrainingStopped`."""
  log.drain(step)
  if checkpointer is not None:
    if log.last_saved != step:
      _save(checkpointer, state, batches, log, step)
    checkpointer.wait()
  stopped = TrainingStopped(signum, step, str(checkpointer.directory) if checkpointer else None)
  print(f"[train] {stopped}", flush=True)
  raise stopped


class _StopRequest:
  """SIGTERM and SIGINT while `train` runs: stop between two steps instead of at once.

  The handler only notes the signal (Python runs it between bytecodes, so a compiled step in
  flight finishes first); the loop then saves and raises `TrainingStopped`. A second signal acts
  at once, as the handler it replaced would (SIGTERM's default: exit; SIGINT's:
  KeyboardInterrupt). A signal noted during the last step is delivered to that previous handler
  once the final checkpoint is on disk. Handlers can only be set from the main thread: elsewhere
  signals keep theirs.

  In a multi-process job every process must stop at the same step (a process that stopped alone
  would leave the others waiting in the next step's collectives), wherever the signal arrived:
  each step ends with a small all-process max of the noted signals, read one step later so the
  host never waits for the step it just dispatched. A job stops one step after the signal.
  """

  SIGNALS = (signal.SIGTERM, signal.SIGINT)

  def __init__(self, mesh: Mesh):
    self.received = 0  # the noted signal's number; 0: none
    self.previous = {}
    self.in_flight = None  # multi-process: the last all-process max, not fetched yet
    if jax.process_count() > 1:
      flags = NamedSharding(mesh, P(tuple(mesh.axis_names)))
      local_devices = len(mesh.local_devices)
      largest = jax.jit(jnp.max, out_shardings=NamedSharding(mesh, P()))
      self.max_over_processes = lambda signum: largest(
        jax.make_array_from_process_local_data(
          flags, np.full(local_devices, signum, np.int32), (mesh.size,)
        )
      )

  def __enter__(self) -> _StopRequest:
    if threading.current_thread() is threading.main_thread():
      for signum in self.SIGNALS:
        previous = signal.signal(signum, self._note)
        # None: a handler not set from Python, which cannot be set back; the default instead.
        self.previous[signum] = signal.SIG_DFL if previous is None else previous
    return self

  def __exit__(self, exc_type, *exc_info) -> None:
    for signum, previous in self.previous.items():
      signal.signal(signum, previous)
    if self.received and exc_type is None:
      signal.raise_signal(self.received)

  def _note(self, signum: int, frame) -> None:
    del frame
    if self.received:
      signal.signal(signum, self.previous[signum])
      signal.raise_signal(signum)
      return
    self.received = signum

  def agreed(self) -> int:
    """The signal to stop on now, the same on every process (0: go on)."""
    if jax.process_count() == 1:
      return self.received
    seen, self.in_flight = self.in_flight, self.max_over_processes(self.received)
    return 0 if seen is None else int(seen)


def _checkpointer(loop_config: LoopConfig) -> Checkpointer | None:
  """The run's checkpoint manager; None when checkpointing is off (no `checkpoint_dir`)."""
  if loop_config.checkpoint_dir is None:
    return None
  return Checkpointer(
    loop_config.checkpoint_dir, loop_config.max_to_keep, loop_config.async_checkpoint
  )


def _every(period: int, step: int) -> bool:
  """Whether a periodic action (period 0: never) falls on `step`."""
  return bool(period) and step % period == 0


def _resume(
  checkpointer: Checkpointer | None, state: TrainState, batches
) -> tuple[TrainState, list[dict]]:
  """`(state, history)` of the latest checkpoint (also restoring the iterator's position), or
  `(state, [])` unchanged when there is none."""
  if checkpointer is None or checkpointer.latest_step() is None:
    return state, []
  state, host_state = checkpointer.restore(state)
  set_iterator_state(batches, host_state["iterator"])
  print(
    f"[train] resuming from step {int(jax.device_get(state.step))} ({checkpointer.directory})",
    flush=True,
  )
  return state, host_state["history"]


class _MetricsLog:
  """The steps' metrics on their way to the log: kept on device until a `drain` fetches them.

  Attributes:
    pending: per-step metric dicts of [] device arrays, not fetched yet.
    history: the logged dicts (each with "step"), appended to in place.
    last_saved: step of the last checkpoint written (named when training stops on a NaN).
  """

  def __init__(self, history: list[dict], log_fn, checkpointer: Checkpointer | None):
    self.pending = []
    self.history = history
    self.log_fn = log_fn
    self.checkpointer = checkpointer
    self.last_saved = checkpointer.latest_step() if checkpointer else None
    self.tick = time.perf_counter()

  def drain(self, step_now: int) -> None:
    """Fetches pending metrics, stops on a non-finite one, logs their mean."""
    if not self.pending:
      return
    fetched = jax.device_get(self.pending)
    self.pending.clear()
    first = step_now - len(fetched) + 1
    for offset, metrics in enumerate(fetched):
      if not metrics["finite"]:
        raise NonFiniteError(
          f"non-finite loss or gradient at step {first + offset - 1} (loss "
          f"{float(metrics['loss'])}, grad_norm {float(metrics['grad_norm'])}); the update was "
          f"skipped and training stopped. Last good checkpoint: step {self.last_saved} in "
          f"{self.checkpointer.directory if self.checkpointer else '(checkpointing off)'}."
        )
    logged = {k: float(np.mean([m[k] for m in fetched])) for k in fetched[0] if k != "finite"}
    now = time.perf_counter()
    logged["steps_per_s"] = len(fetched) / (now - self.tick)
    self.tick = now
    logged["step"] = step_now
    self.history.append(logged)
    self.log_fn(step_now, logged)

  def evaluation(self, step: int, results: dict) -> None:
    """Logs `eval_fn`'s dict of scalars as "eval/..." entries."""
    evaluated = {f"eval/{k}": float(v) for k, v in jax.device_get(results).items()}
    self.history.append({"step": step, **evaluated})
    self.log_fn(step, evaluated)
