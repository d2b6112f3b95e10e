"""orbax checkpoints of the whole `TrainState` plus the data-iterator state; exact resume.

A checkpoint holds two items: "state" (params, optimiser state, step, RNG; array pytree) and
"data" (JSON: the input pipeline's iterator state, e.g. grain's `get_state()`). Saves are
asynchronous: `save` returns once the arrays are copied off the device and the write continues in
the background; `wait()` blocks until it is on disk (call it before exiting).
"""

from __future__ import annotations

import pathlib
from typing import Any

import jax
import orbax.checkpoint as ocp


class Checkpointer:
  """Thin wrapper over `ocp.CheckpointManager` with the two items of a training checkpoint.

  Args:
    directory: where step-numbered checkpoints go (created if missing).
    max_to_keep: checkpoints kept (oldest deleted first); None keeps all.
    async_save: write in a background thread.
  """

  def __init__(self, directory: str | pathlib.Path, max_to_keep: int | None = 3,
               async_save: bool = True):
    self.directory = pathlib.Path(directory).resolve()
    self._manager = ocp.CheckpointManager(
        self.directory, item_names=("state", "data"),
        options=ocp.CheckpointManagerOptions(max_to_keep=max_to_keep,
                                             enable_async_checkpointing=async_save))

  def save(self, state, data_state: Any = None) -> None:
    """Saves `state` under step `int(state.step)` with the JSON-able iterator state."""
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
      `(state, data_state)`.
    """
    self.wait()
    step = self.latest_step() if step is None else step
    if step is None:
      raise FileNotFoundError(f"no checkpoint in {self.directory}")
    abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, like_state)
    restored = self._manager.restore(step, args=ocp.args.Composite(
        state=ocp.args.StandardRestore(abstract), data=ocp.args.JsonRestore()))
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
