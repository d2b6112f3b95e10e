"""The training loop used by experiments: batches -> sharded steps -> logs, checkpoints, evals."""

from __future__ import annotations

import contextlib
import dataclasses
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
    checkpoint_dir: where checkpoints go; an existing checkpoint there is resumed from.
    max_to_keep: checkpoints kept.
    async_checkpoint: background writes.
  """

  total_steps: int
  seed: int = 0
  log_every: int = 10
  checkpoint_every: int = 1000
  eval_every: int = 0
  checkpoint_dir: str | None = None
  max_to_keep: int = 3
  async_checkpoint: bool = True


class NonFiniteError(RuntimeError):
  """A loss or gradient became NaN/inf; raised after the last good checkpoint is on disk."""


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
) -> tuple[TrainState, list[dict]]:
  """Trains `params` on `batches`, resuming from `loop_config.checkpoint_dir` when it holds one.

  Args:
    loss_fn: `(params, batch, key, step) -> (loss, aux)` (e.g. `tokengs_loss_fn(...)`).
    params: initial parameters (host or device pytree, identical on every process); ignored when
      a checkpoint is resumed.
    batches: iterator of this process's batches (dicts of `[B_local, ...]` numpy arrays), all of
      the first batch's shapes (the step is compiled once, ahead of its first run). If it has
      `get_state`/`set_state` (grain), its position is checkpointed and restored (per process).
    optim_config: optimiser and schedule.
    loop_config: loop settings.
    mesh: device mesh; default all devices on "data".
    precision: compute-dtype policy (default `Precision()`: no cast).
    eval_fn: `state -> dict of scalars`, called every `eval_every` steps and logged as "eval/...".
    log_fn: `(step, metrics) -> None`; default prints one line.

  Returns:
    `(final state, history)`; history is the list of logged dicts (each with "step") of the whole
    run: a resumed run starts from the history saved in its checkpoint (entries up to its step).

  Raises:
    NonFiniteError: a loss/gradient went non-finite; no later checkpoint was written.
  """
  mesh = make_mesh() if mesh is None else mesh
  optimizer = make_optimizer(optim_config)
  replicated = NamedSharding(mesh, P())
  init_state = jax.jit(
    lambda p: create_train_state(p, optimizer, loop_config.seed), out_shardings=replicated
  )
  state = init_state(replicate(jax.device_get(params), mesh))

  checkpointer = None
  if loop_config.checkpoint_dir is not None:
    checkpointer = Checkpointer(
      loop_config.checkpoint_dir, loop_config.max_to_keep, loop_config.async_checkpoint
    )
  # Leaving the block waits for a pending save and closes the manager, also on an error.
  with checkpointer or contextlib.nullcontext():
    history = []
    if checkpointer is not None and checkpointer.latest_step() is not None:
      state, host_state = checkpointer.restore(state)
      set_iterator_state(batches, host_state["iterator"])
      history = host_state["history"]
      print(
        f"[train] resuming from step {int(jax.device_get(state.step))} ({checkpointer.directory})",
        flush=True,
      )
    train_step = make_train_step(
      loss_fn, optimizer, mesh, precision=Precision() if precision is None else precision
    )
    # A separate buffer: the state (and its rng) is donated to each step.
    key = jnp.copy(state.rng)

    pending = []
    step = int(jax.device_get(state.step))
    last_saved = checkpointer.latest_step() if checkpointer else None
    tick = time.perf_counter()

    def drain(step_now: int) -> None:
      """Fetches pending metrics, stops on a non-finite one, logs their mean."""
      nonlocal tick
      if not pending:
        return
      fetched = jax.device_get(pending)
      pending.clear()
      first = step_now - len(fetched) + 1
      for offset, metrics in enumerate(fetched):
        if not metrics["finite"]:
          raise NonFiniteError(
            f"non-finite loss or gradient at step {first + offset - 1} (loss "
            f"{float(metrics['loss'])}, grad_norm {float(metrics['grad_norm'])}); the update was "
            f"skipped and training stopped. Last good checkpoint: step {last_saved} in "
            f"{checkpointer.directory if checkpointer else '(checkpointing off)'}."
          )
      logged = {k: float(np.mean([m[k] for m in fetched])) for k in fetched[0] if k != "finite"}
      now = time.perf_counter()
      logged["steps_per_s"] = len(fetched) / (now - tick)
      tick = now
      logged["step"] = step_now
      history.append(logged)
      log_fn(step_now, logged)

    compiled = None
    while step < loop_config.total_steps:
      batch = shard_batch(next(batches), mesh)
      if compiled is None:  # compile first, then meet: the first collective runs in step
        compiled = train_step.lower(state, batch, key).compile()
        barrier("tokengs_train_step_compiled")
      state, metrics = compiled(state, batch, key)
      pending.append(metrics)
      step += 1
      is_last = step == loop_config.total_steps
      save_now = checkpointer is not None and (
        is_last or (loop_config.checkpoint_every and step % loop_config.checkpoint_every == 0)
      )
      if save_now or is_last or step % loop_config.log_every == 0:
        drain(step)
      # Before the save, so the checkpoint's history holds this step's evaluation.
      if eval_fn is not None and loop_config.eval_every and step % loop_config.eval_every == 0:
        evaluated = {f"eval/{k}": float(v) for k, v in jax.device_get(eval_fn(state)).items()}
        history.append({"step": step, **evaluated})
        log_fn(step, evaluated)
      if save_now:
        checkpointer.save(state, {"iterator": iterator_state(batches), "history": history})
        last_saved = step
    return state, history
