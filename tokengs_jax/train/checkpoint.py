"""orbax checkpoints of the whole `TrainState` plus per-process host state; verified restore.

A checkpoint (one step directory, written atomically by orbax: a temporary directory renamed
once every process has written its part) holds three items:
- "state": params, optimiser state, step, RNG and, when the run keeps one, the parameters'
  moving average (array pytree, `StandardCheckpointHandler`); a `TrainState` restores whether or
  not the checkpoint holds an average: one the run does not keep is dropped, one the checkpoint
  lacks starts from the restored params (both logged);
- "data": one JSON file per process, `data/process_{i}-of-{n}.json` (the layout of grain's own
  orbax handler), with that process's host-side state (the loop stores its input iterator
  position and the training log). In a multi-host run each process reads its own shard of the
  data, so its iterator position is its own; a resume on the same number of processes is exact,
  another process count is refused (the shards would differ);
- "checksums": one JSON file per process, `checksums/process_{i}-of-{n}.json`: the crc32 of
  every array shard the process held at save time, and of its "data" JSON (under `HOST_STATE`:
  a changed digit in the iterator position or the log is damage too).

Restore walks back from the newest step to the newest one that restores *and* whose arrays match
their checksums (a bit flip inside a compressed chunk can decode to wrong numbers without any
read error); each skipped step is logged with the reason and renamed `<step>.unusable` so later
saves of that step number and `max_to_keep` only see good checkpoints. All processes agree on
the step they resume from. Saves are asynchronous: `save` returns once the arrays are copied off
the device; `wait()` blocks until the write is on disk (call it before exiting).

What orbax would follow out of the directory or block on (a step that is a symbolic link, a FIFO
in a step) is set aside when the checkpointer opens the directory, and a full or unwritable disk
is one `CheckpointWriteError` line naming the step and the directory (`checkpoint_files`).
"""

from __future__ import annotations

import contextlib
import json
import logging
import pathlib
import re
import shutil
import zlib
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
from jax.experimental import multihost_utils

from tokengs_jax.train.checkpoint_files import (
  STEP_NAME,
  foreign_step_reason,
  missing_space,
  set_aside,
  step_bytes,
  write_error,
)
from tokengs_jax.train.state import TrainState

log = logging.getLogger(__name__)


class UnusableCheckpointError(RuntimeError):
  """The checkpoint directory holds steps but none restores and verifies."""


class ChecksumError(ValueError):
  """Restored arrays differ from the checksums written when they were saved."""


def data_state_file(process_index: int, process_count: int) -> str:
  """Name of one process's JSON file inside a checkpoint's "data" item."""
  return f"process_{process_index}-of-{process_count}.json"


def data_state_handler(process_index: int, process_count: int) -> ocp.JsonCheckpointHandler:
  """orbax handler of a per-process JSON item ("data", "checksums") as seen by one process: its
  own file, written by it.

  `primary_host=None` makes every process write (orbax's default writes JSON from process 0 only,
  which would keep one process's position for all).
  """
  return ocp.JsonCheckpointHandler(
    filename=data_state_file(process_index, process_count),
    multiprocessing_options=ocp.options.MultiprocessingOptions(primary_host=None),
  )


def _index_key(index: tuple, shape: tuple) -> str:
  """'0:4,0:16' for a shard's index (tuple of slices) into an array of `shape`."""
  return ",".join(
    f"{s.start or 0}:{dim if s.stop is None else s.stop}"
    for s, dim in zip(index, shape, strict=True)
  )


def array_checksums(tree) -> dict[str, dict[str, int]]:
  """crc32 of the bytes of every array shard this process holds.

  Returns:
    {leaf path (`jax.tree_util.keystr`): {shard index ('0:4,0:16'): crc32}}; a replicated array
    has one entry (the whole array), a sharded one an entry per distinct local shard.
  """
  sums = {}
  for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
    if isinstance(leaf, jax.Array):
      pieces = [(_index_key(s.index, leaf.shape), s.data) for s in leaf.addressable_shards]
    else:
      leaf = np.asarray(leaf)
      pieces = [(_index_key((slice(None),) * leaf.ndim, leaf.shape), leaf)]
    shards = {}
    for key, data in pieces:
      if key not in shards:
        shards[key] = zlib.crc32(np.ascontiguousarray(jax.device_get(data)).view(np.uint8))
    sums[jax.tree_util.keystr(path)] = shards
  return sums


HOST_STATE = "host_state"  # the checksum manifest's entry of the "data" item


def host_state_checksum(host) -> dict[str, int]:
  """The crc32 of a JSON-able host state in canonical form (sorted keys, no spaces), as saved
  and as parsed back alike."""
  text = json.dumps(host, sort_keys=True, separators=(",", ":"))
  return {"json": zlib.crc32(text.encode())}


def verify_checksums(tree, expected: dict[str, dict[str, int]]) -> int:
  """Checks `tree`'s local shards against `array_checksums` taken at save time.

  Returns:
    how many shards were verified (shards saved under another layout are not comparable).

  Raises:
    ChecksumError: naming the arrays whose bytes differ (or that the manifest lacks).
  """
  verified, bad = 0, []
  for name, shards in array_checksums(tree).items():
    if name not in expected:
      bad.append(f"{name} (not in the checksum manifest)")
      continue
    for key, crc in shards.items():
      if key in expected[name]:
        verified += 1
        if expected[name][key] != crc:
          bad.append(f"{name}[{key}]")
  if bad:
    raise ChecksumError(
      f"checksum mismatch in {len(bad)} array(s): {', '.join(bad[:5])}"
      + (" ..." if len(bad) > 5 else "")
    )
  return verified


def _all_agree(ok: bool) -> bool:
  """True iff `ok` on every process (a collective: every process must call it)."""
  if jax.process_count() == 1:
    return ok
  return bool(np.all(multihost_utils.process_allgather(np.asarray(ok, np.int32))))


# What orbax writes besides the arrays' and JSON items' bytes: metadata of about 800 bytes per
# array (measured: 2.4 MB for a state of 3,011 one-element arrays, 34 kB for 41) and 20 to 70
# files, each taking whole 4 KiB blocks on disk (41 arrays: 34 kB of files filled 120 kB of
# blocks). 1 KiB per array and 1 MiB (256 such files) cover both.
_METADATA_BYTES_PER_ARRAY = 1024
_FILES_BYTES = 2**20


def first_step_bytes(state, json_items) -> int:
  """About the most a save of `state` with `json_items` takes on disk: the arrays' bytes as
  they are in memory, the JSON items' text, orbax's metadata and files.

  An upper bound, for the first save only: orbax compresses, so arrays of zeros (the Adam moments
  of a fresh state) take almost nothing, but trained floats hardly compress (measured: random normal
  float32 params and moments took 92% of their bytes). A disk with room between the two is refused a step that fits, and the next step
  would not fit there (orbax writes a step before it deletes the oldest): the run stops one save
  earlier, or, saving only at its end, loses a save that fit.
  """
  arrays = jax.tree.leaves(state)
  array_bytes = sum(
    leaf.nbytes if isinstance(leaf, jax.Array) else np.asarray(leaf).nbytes for leaf in arrays
  )
  json_bytes = sum(len(json.dumps(item).encode()) for item in json_items)
  return array_bytes + json_bytes + _METADATA_BYTES_PER_ARRAY * len(arrays) + _FILES_BYTES


def _short(error: BaseException) -> str:
  text = " ".join(str(error).split())
  return f"{type(error).__name__}: {text[:300]}{' ...' if len(text) > 300 else ''}"


class Checkpointer:
  """Thin wrapper over `ocp.CheckpointManager` with the two items of a training checkpoint.

  Args:
    directory: where step-numbered checkpoints go (created if missing).
    max_to_keep: checkpoints kept (oldest deleted first); None keeps all.
    async_save: write in a background thread.
    process_index, process_count: whose host state this process saves and restores; default
      `jax.process_index()` / `jax.process_count()` (other values only simulate hosts in tests).
  """

  def __init__(
    self,
    directory: str | pathlib.Path,
    max_to_keep: int | None = 3,
    async_save: bool = True,
    process_index: int | None = None,
    process_count: int | None = None,
  ):
    self.directory = pathlib.Path(directory).resolve()
    self.process_index = jax.process_index() if process_index is None else process_index
    self.process_count = jax.process_count() if process_count is None else process_count
    self._pending_step = None  # the step of a save that may still be writing
    with self._naming_refused_writes(None):
      self._set_aside_foreign_steps()
      self._manager = self._open_manager(max_to_keep, async_save)

  def _open_manager(self, max_to_keep: int | None, async_save: bool) -> ocp.CheckpointManager:
    registry = ocp.handlers.DefaultCheckpointHandlerRegistry()
    for item in ("data", "checksums"):
      handler = data_state_handler(self.process_index, self.process_count)
      for args in (ocp.args.JsonSave, ocp.args.JsonRestore):
        registry.add(item, args, handler)
    state_handler = ocp.StandardCheckpointHandler()
    for args in (ocp.args.StandardSave, ocp.args.StandardRestore):
      registry.add("state", args, state_handler)
    return ocp.CheckpointManager(
      self.directory,
      handler_registry=registry,
      options=ocp.CheckpointManagerOptions(
        max_to_keep=max_to_keep, enable_async_checkpointing=async_save
      ),
    )

  def save(self, state, data_state: Any = None) -> None:
    """Saves `state` under step `int(state.step)` with this process's JSON-able host state.

    Every process must call it (orbax coordinates the step directory across processes). The
    checksums are taken here, from the arrays being saved, before the asynchronous write.
    """
    step = int(jax.device_get(state.step))
    self.wait()  # orbax waits too: a failure of the previous save is reported as that step's
    host = {"iterator": data_state}
    checksums = {**array_checksums(state), HOST_STATE: host_state_checksum(host)}
    self._check_free_space(step, state, (host, checksums))
    self._pending_step = step
    with self._naming_refused_writes(step):
      self._manager.save(
        step,
        args=ocp.args.Composite(
          state=ocp.args.StandardSave(state),
          data=ocp.args.JsonSave(host),
          checksums=ocp.args.JsonSave(checksums),
        ),
        force=True,
      )

  def _check_free_space(self, step: int, state, json_items: tuple) -> None:
    """Refuses a save that cannot fit before orbax writes a byte (a write failing on a full disk
    logs a traceback per writer thread). A step takes about what the latest one took on disk
    (orbax compresses: that size counts it); the first, with no step to go by, is sized from
    what it saves (`first_step_bytes`)."""
    latest = self.latest_step()
    if latest is None:
      needed = first_step_bytes(state, json_items)
    else:
      needed = step_bytes(self.directory / str(latest))
    free = shutil.disk_usage(self.directory).free
    if not _all_agree(free >= needed):
      raise missing_space(self.directory, step, needed, free)

  def latest_step(self) -> int | None:
    return self._manager.latest_step()

  def all_steps(self) -> list[int]:
    return list(self._manager.all_steps())

  def restore(self, like_state, step: int | None = None):
    """Restores (state, data_state) of `step`, or of the newest step that restores and verifies.

    Args:
      like_state: a state (or tree of `jax.ShapeDtypeStruct` with shardings) whose structure,
        dtypes and shardings the restored arrays take.
      step: restore exactly this step (no walking back); default the newest usable one.

    Returns:
      `(state, data_state)`: the data state is this process's.

    Raises:
      FileNotFoundError: no checkpoint, or the checkpoint was written by another process count.
      UnusableCheckpointError: no step restores and verifies (each one's reason is listed).
    """
    self.wait()
    abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, like_state)
    if step is not None:
      self._check_process_count(step)
      return self._restore_verified(step, abstract)
    steps = sorted(self.all_steps(), reverse=True)
    if not steps:
      raise FileNotFoundError(f"no checkpoint in {self.directory}")
    skipped = []
    for candidate in steps:
      self._check_process_count(candidate)
      restored, error = None, None
      try:
        # This process's own JSON files first, agreed on before orbax's restore: orbax ends a
        # restore with a barrier that a process failing alone would leave the others waiting at.
        self._read_own_files(candidate)
      except Exception as failure:
        error = failure
      if _all_agree(error is None):
        try:
          restored = self._restore_verified(candidate, abstract)
        except Exception as failure:  # orbax/tensorstore/json raise many types for damaged files
          error = failure
        if _all_agree(error is None):
          if skipped:
            self._set_aside(skipped, f"tokengs_checkpoint_set_aside_{skipped[-1][0]}")
            self._manager.reload()
          return restored
      reason = _short(error) if error is not None else "another process could not restore it"
      log.warning(
        "checkpoint step %d in %s is unusable, skipped (%s)", candidate, self.directory, reason
      )
      skipped.append((candidate, reason))
    raise UnusableCheckpointError(
      f"no usable checkpoint in {self.directory}; every step failed to restore or verify:\n"
      + "\n".join(f"  step {s}: {reason}" for s, reason in skipped)
      + "\nMove the directory away to start afresh, or point checkpoint_dir elsewhere."
    )

  def _saved_average(self, step: int, default: bool) -> bool:
    """Whether step `step`'s state holds a parameter average (`TrainState.ema_params`);
    `default` when its metadata does not say (then orbax's restore names the damage)."""
    try:
      tree = ocp.StandardCheckpointHandler().metadata(self.directory / str(step) / "state").tree
    except Exception:  # a damaged step: its restore below fails with the reason
      return default
    return isinstance(tree, dict) and tree.get("ema_params") is not None

  def _restore_verified(self, step: int, abstract):
    wants = saved = None
    if isinstance(abstract, TrainState):  # restore what was saved; fit it to the run below
      wants = abstract.ema_params is not None
      saved = self._saved_average(step, default=wants)
      abstract = abstract.replace(ema_params=abstract.params if saved else None)
    restored = self._manager.restore(
      step,
      args=ocp.args.Composite(
        state=ocp.args.StandardRestore(abstract), data=ocp.args.JsonRestore()
      ),
    )
    state, host = restored["state"], restored["data"]
    name = data_state_file(self.process_index, self.process_count)
    if not isinstance(host, dict) or "iterator" not in host:
      raise ValueError(f"data/{name} holds no iterator state")
    # Read directly, not as an orbax item: a checkpoint without this file (older versions, or a
    # process simulated in tests) still restores, unverified and said so.
    checksums = self.directory / str(step) / "checksums" / name
    if checksums.is_file():
      manifest = json.loads(checksums.read_text())
      verify_checksums(state, manifest)
      if HOST_STATE in manifest and manifest[HOST_STATE] != host_state_checksum(host):
        raise ChecksumError(f"checksum mismatch in data/{name} (the iterator state)")
    else:
      log.warning(
        "checkpoint step %d in %s has no checksums/%s: restored unverified",
        step,
        self.directory,
        name,
      )
    if wants and not saved:
      log.warning(
        "checkpoint step %d in %s holds no parameter average: it starts from the restored params",
        step,
        self.directory,
      )
      state = state.replace(ema_params=jax.tree.map(jnp.copy, state.params))
    elif saved and not wants:
      log.warning(
        "checkpoint step %d in %s holds a parameter average this run does not keep: dropped",
        step,
        self.directory,
      )
      state = state.replace(ema_params=None)
    return state, host["iterator"]

  def _read_own_files(self, step: int) -> None:
    """Parses this process's JSON files of `step` (raises on a missing or damaged data file)."""
    name = data_state_file(self.process_index, self.process_count)
    json.loads((self.directory / str(step) / "data" / name).read_text())
    checksums = self.directory / str(step) / "checksums" / name
    if checksums.is_file():
      json.loads(checksums.read_text())

  def _check_process_count(self, step: int) -> None:
    """Refuses a step written by another number of processes (not damage: walking back would
    find the same everywhere)."""
    data_dir = self.directory / str(step) / "data"
    written = sorted(p.name for p in data_dir.glob("process_*-of-*.json"))
    counts = {int(re.search(r"-of-(\d+)", name).group(1)) for name in written}
    if written and self.process_count not in counts:
      raise FileNotFoundError(
        f"checkpoint step {step} in {self.directory} has no iterator state for process "
        f"{self.process_index} of {self.process_count} "
        f"(expected data/{data_state_file(self.process_index, self.process_count)}; found "
        f"{written}): resume with the process count it was written with"
      )

  def _set_aside_foreign_steps(self) -> None:
    """Sets aside the steps orbax would follow a link out of the directory in, or block on (a
    FIFO), before orbax lists them. Every process must call it."""
    foreign = []
    if jax.process_index() == 0 and self.directory.is_dir():
      for entry in sorted(self.directory.iterdir()):
        if STEP_NAME.fullmatch(entry.name) and (reason := foreign_step_reason(entry)):
          foreign.append((int(entry.name), reason))
    self._set_aside(foreign, "tokengs_checkpoint_foreign_steps_set_aside")

  def _set_aside(self, skipped: list[tuple[int, str]], barrier: str) -> None:
    """Renames the (step, reason) steps to `<step>.unusable[.k]` (kept for inspection, invisible
    to orbax). Every process must call it; process 0 renames."""
    if jax.process_index() == 0:
      with self._naming_refused_writes(None):
        for step, reason in skipped:
          target = set_aside(self.directory / str(step), reason)
          log.warning("moved unusable checkpoint step %d to %s (%s)", step, target, reason)
    if jax.process_count() > 1:
      multihost_utils.sync_global_devices(barrier)

  @contextlib.contextmanager
  def _naming_refused_writes(self, step: int | None):
    """Re-raises a full or unwritable disk as one `CheckpointWriteError` line (orbax has logged
    the details); other errors as they are."""
    try:
      yield
    except Exception as error:
      refused = write_error(error, self.directory, step)
      if refused is None:
        raise
      raise refused from None

  def wait(self) -> None:
    """Blocks until every pending asynchronous save is on disk."""
    with self._naming_refused_writes(self._pending_step):
      self._manager.wait_until_finished()
    self._pending_step = None

  def close(self) -> None:
    self._manager.close()

  def __enter__(self) -> Checkpointer:
    return self

  def __exit__(self, *exc_info) -> None:
    """Waits for pending saves (a save in flight completes even when training failed), closes."""
    try:
      self.wait()
    finally:
      self.close()


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
  iterator.set_state(
    state["utf8"].encode() if isinstance(state, dict) and set(state) == {"utf8"} else state
  )
