"""orbax checkpoints of the whole `TrainState` plus the data-iterator state; exact resume.

A checkpoint holds two items: "state" (params, optimiser state, step, RNG; array pytree) and
"data": the input pipeline's iterator state (e.g. grain's `get_state()`) of *every process*, one
JSON file per process, `data/process_{i}-of-{n}.json` (the layout of grain's own orbax handler).
In a multi-host run each process reads its own shard of the data, so its iterator position is its
own; every process writes its file into the shared step directory and restores from it, so a
resume on the same number of processes is exact. Restoring on another process count is refused
(the shards would differ). Saves are asynchronous: `save` returns once the arrays are copied off
the device and the write continues in the background; `wait()` blocks until it is on disk (call
it before exiting).
"""

from __future__ import annotations

import pathlib
from typing import Any

import jax
import orbax.checkpoint as ocp


def data_state_file(process_index: int, process_count: int) -> str:
  """Name of one process's iterator-state file inside a checkpoint's "data" item."""
  return f"process_{process_index}-of-{process_count}.json"


def data_state_handler(process_index: int, process_count: int) -> ocp.JsonCheckpointHandler:
  """orbax handler of the "data" item as seen by one process: its own JSON file, written by it.

  `primary_host=None` makes every process write (orbax's default writes JSON from process 0 only,
  which would keep one process's position for all).
  """
  return ocp.JsonCheckpointHandler(
      filename=data_state_file(process_index, process_count),
      multiprocessing_options=ocp.options.MultiprocessingOptions(primary_host=None))


class Checkpointer:
  """Thin wrapper over `ocp.CheckpointManager` with the two items of a training checkpoint.

  Args:
    directory: where step-numbered checkpoints go (created if missing).
    max_to_keep: checkpoints kept (oldest deleted first); None keeps all.
    async_save: write in a background thread.
    process_index, process_count: whose iterator state this process saves and restores; default
      `jax.process_index()` / `jax.process_count()` (other values only simulate hosts in tests).
  """

  def __init__(self, directory: str | pathlib.Path, max_to_keep: int | None = 3,
               async_save: bool = True, process_index: int | None = None,
               process_count: int | None = None):
    self.directory = pathlib.Path(directory).resolve()
    self.process_index = jax.process_index() if process_index is None else process_index
    self.process_count = jax.process_count() if process_count is None else process_count
    data_handler = data_state_handler(self.process_index, self.process_count)
    registry = ocp.handlers.DefaultCheckpointHandlerRegistry()
    for args in (ocp.args.JsonSave, ocp.args.JsonRestore):
      registry.add("data", args, data_handler)
    state_handler = ocp.StandardCheckpointHandler()
    for args in (ocp.args.StandardSave, ocp.args.StandardRestore):
      registry.add("state", args, state_handler)
    self._manager = ocp.CheckpointManager(
        self.directory, handler_registry=registry,
        options=ocp.CheckpointManagerOptions(max_to_keep=max_to_keep,
                                             enable_async_checkpointing=async_save))

  def save(self, state, data_state: Any = None) -> None:
    """Saves `state` under step `int(state.step)` with this process's JSON-able iterator state.

    Every process must call it (orbax coordinates the step directory across processes).
    """
    step = int(jax.device_get(state.step))
    self._manager.save(step, args=ocp.args.Composite(
        state=ocp.args.StandardSave(state),
        data=ocp.args.JsonSave({"iterator": data_state})), force=True)

  def latest_step(self) -> int | None:
    return self._manager.latest_step()

  def all_steps(self) -> list[int]:
    return list(self._manager.all_steps())

  def restore(self, like_state, step: int | None = None):
    """Restores (state, data_state) at `step` (default: latest).

    Args:
      like_state: a state (or tree of `jax.ShapeDtypeStruct` with shardings) whose structure,
        dtypes and shardings the restored arrays take.
      step: which checkpoint.

    Returns:
      `(state, data_state)`: the data state is this process's.

    Raises:
      FileNotFoundError: no checkpoint, or none holding this process's iterator state (written
        by a different number of processes).
    """
    self.wait()
    step = self.latest_step() if step is None else step
    if step is None:
      raise FileNotFoundError(f"no checkpoint in {self.directory}")
    abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, like_state)
    try:
      restored = self._manager.restore(step, args=ocp.args.Composite(
          state=ocp.args.StandardRestore(abstract), data=ocp.args.JsonRestore()))
    except FileNotFoundError as error:
      data_dir = self.directory / str(step) / "data"
      written = sorted(p.name for p in data_dir.glob("process_*.json"))
      raise FileNotFoundError(
          f"checkpoint step {step} in {self.directory} has no iterator state for process "
          f"{self.process_index} of {self.process_count} "
          f"(expected data/{data_state_file(self.process_index, self.process_count)}; found "
          f"{written or 'none'}): resume with the process count it was written with") from error
    return restored["state"], restored["data"]["iterator"]

  def wait(self) -> None:
    """Blocks until every pending asynchronous save is on disk."""
    self._manager.wait_until_finished()

  def close(self) -> None:
    self._manager.close()


def iterator_state(iterator) -> Any:
  """JSON-able state of a data iterator (grain returns a dict or JSON bytes), or None."""
  if not hasattr(iterator, "get_state"):
    return None
  state = iterator.get_state()
  return {"utf8": state.decode()} if isinstance(state, bytes) else state


def set_iterator_state(iterator, state: Any) -> None:
  """Inverse of `iterator_state`."""
  if state is None:
    return
  iterator.set_state(state["utf8"].encode() if isinstance(state, dict) and set(state) == {"utf8"}
                     else state)
