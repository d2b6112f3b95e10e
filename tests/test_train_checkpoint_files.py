"""Checkpoint directories as a user may leave them (issue 28): symbolic links, FIFOs, a full or
unwritable disk. Nothing is followed out of the directory to write, nothing hangs, and a refused
write is one line naming the step and the directory."""

import errno
import logging
import os
import re
import shutil
import threading

import jax
import pytest
from etils import epath
from checkpoints import flip_one_bit, largest_array_file, state_at

from tokengs_jax.train import Checkpointer
from tokengs_jax.train.checkpoint_files import CheckpointWriteError, refused_write_errno

LOGGER = "tokengs_jax.train.checkpoint"


def save_steps(directory, steps, **options):
  with Checkpointer(directory, async_save=False, **options) as checkpointer:
    for step in steps:
      checkpointer.save(state_at(step), {"position": step})


def move_out_and_link(step_dir, outside):
  """Moves a step directory to `outside` and leaves a symbolic link to it in its place."""
  outside.mkdir(exist_ok=True)
  moved = outside / step_dir.name
  shutil.move(step_dir, moved)
  step_dir.symlink_to(moved)
  return moved


def listing(directory):
  return sorted(str(p.relative_to(directory)) for p in directory.rglob("*"))


def test_a_damaged_step_linked_from_outside_gets_no_marker_outside(tmp_path, caplog):
  run, outside = tmp_path / "run", tmp_path / "outside"
  save_steps(run, (2, 4))
  moved = move_out_and_link(run / "4", outside)
  flip_one_bit(moved)
  before = listing(outside)
  with caplog.at_level(logging.WARNING, logger=LOGGER):
    with Checkpointer(run) as checkpointer:
      state, data_state = checkpointer.restore(state_at(0))
  assert int(state.step) == 2 and data_state == {"position": 2}
  assert listing(outside) == before  # no UNUSABLE.txt written through the link
  assert (run / "4.unusable").is_symlink()
  assert any("step 4" in m and "symbolic link" in m for m in caplog.messages), caplog.messages


def test_an_old_step_linked_from_outside_does_not_break_later_saves(tmp_path, caplog):
  """orbax deletes the oldest step with rmtree, which refuses a link: every save raised."""
  run, outside = tmp_path / "run", tmp_path / "outside"
  save_steps(run, (1,))
  move_out_and_link(run / "1", outside)
  with caplog.at_level(logging.WARNING, logger=LOGGER):
    for rerun in (0, 1):
      with Checkpointer(run, max_to_keep=2, async_save=True) as checkpointer:
        for step in (2, 3, 4):
          checkpointer.save(state_at(step + 10 * rerun), {"position": step})
  assert Checkpointer(run).all_steps() == [13, 14]
  assert listing(outside)[0] == "1" and (outside / "1" / "state").is_dir()  # left as it was
  assert any("step 1" in m and "symbolic link" in m for m in caplog.messages), caplog.messages


def array_chunk(step_dir):
  return largest_array_file(step_dir).relative_to(step_dir)


# The files a restore (or orbax's start-up) opens; a FIFO in their place blocked forever.
FIFO_PLACES = {
  "iterator_json": lambda step_dir: "data/process_0-of-1.json",
  "checksums_json": lambda step_dir: "checksums/process_0-of-1.json",
  "step_metadata": lambda step_dir: "_CHECKPOINT_METADATA",
  "array_chunk": array_chunk,
}


def unblock(fifo):
  """Opens the FIFO's writing end and closes it: a reader blocked on it gets end-of-file."""
  try:
    os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
  except OSError:  # no reader waiting
    pass


@pytest.mark.parametrize("place", FIFO_PLACES)
def test_a_fifo_in_a_step_is_refused_not_opened(tmp_path, place, caplog):
  run = tmp_path / "run"
  save_steps(run, (2, 4))
  fifo = run / "4" / FIFO_PLACES[place](run / "4")
  fifo.unlink()
  os.mkfifo(fifo)
  outcome = {}

  def resume():
    with Checkpointer(run) as checkpointer:
      outcome["state"], outcome["data"] = checkpointer.restore(state_at(0))

  with caplog.at_level(logging.WARNING, logger=LOGGER):
    worker = threading.Thread(target=resume, daemon=True)
    worker.start()
    worker.join(timeout=30)
    hung = worker.is_alive()
    unblock(fifo)
  assert not hung, f"resuming blocked on the FIFO at {fifo.relative_to(run)}"
  assert int(outcome["state"].step) == 2 and outcome["data"] == {"position": 2}
  assert any("step 4" in m and "FIFO" in m for m in caplog.messages), caplog.messages
  assert (run / "4.unusable" / "UNUSABLE.txt").is_file()


def refuse_writing(monkeypatch, code):
  """Makes the writes of the iterator JSON fail as the disk would, with `code`, inside orbax's
  own write (its threads, its error handling)."""
  write_text = type(epath.Path("/")).write_text

  def refused(path, *args, **kwargs):
    if path.name == "process_0-of-1.json" and path.parent.name.startswith("data"):
      raise OSError(code, os.strerror(code), str(path))
    return write_text(path, *args, **kwargs)

  monkeypatch.setattr(type(epath.Path("/")), "write_text", refused)


REFUSALS = {
  "disk_full": (errno.ENOSPC, "no space left on device"),
  "permission_denied": (errno.EACCES, "permission denied"),
}


@pytest.mark.parametrize("async_save", [False, True], ids=["sync", "async"])
@pytest.mark.parametrize("refusal", REFUSALS)
def test_a_refused_write_is_one_line_naming_the_step_and_directory(
  tmp_path, monkeypatch, refusal, async_save
):
  code, what = REFUSALS[refusal]
  run = tmp_path / "run"
  save_steps(run, (1,))
  refuse_writing(monkeypatch, code)
  with pytest.raises(CheckpointWriteError) as raised:
    with Checkpointer(run, async_save=async_save) as checkpointer:
      checkpointer.save(state_at(2), {"position": 2})
  message = str(raised.value)
  assert "\n" not in message
  assert message.startswith(f"{what} writing checkpoint step 2 to {run}: "), message
  assert "--output-dir" in message
  monkeypatch.undo()
  assert Checkpointer(run).all_steps() == [1]  # the refused step never became a checkpoint


def refused_for_space(run, monkeypatch, caplog):
  """Saves step 2 into `run` where 0.1 MiB are free; asserts the one-line refusal, with nothing
  logged as an error on the way."""
  usage = shutil.disk_usage(run.parent)
  monkeypatch.setattr(shutil, "disk_usage", lambda path: usage._replace(free=100_000))
  with caplog.at_level(logging.WARNING):
    with pytest.raises(CheckpointWriteError) as raised:
      with Checkpointer(run, async_save=True) as checkpointer:
        checkpointer.save(state_at(2), {"position": 2})
  assert re.fullmatch(
    rf"no space left on device writing checkpoint step 2 to {re.escape(str(run))}: the step "
    r"needs about \d\.\d MiB, 0\.1 MiB are free; free space there or choose another "
    r"checkpoint directory \(experiments: --output-dir\)",
    str(raised.value),
  ), str(raised.value)
  assert not [r for r in caplog.records if r.levelno >= logging.ERROR]


def test_a_save_that_cannot_fit_is_refused_before_orbax_writes(tmp_path, monkeypatch, caplog):
  """On a full disk orbax logs a traceback per writer thread (measured: 1,490 lines) before the
  error: a step that cannot fit (about the size of the latest one) is refused in one line."""
  run = tmp_path / "run"
  save_steps(run, (1,))
  refused_for_space(run, monkeypatch, caplog)
  assert sorted(p.name for p in run.iterdir()) == ["1"]


def test_a_first_save_that_cannot_fit_is_refused_before_orbax_writes(tmp_path, monkeypatch, caplog):
  """With no step on disk to size it by, the first save is sized from the state it saves."""
  run = tmp_path / "run"
  refused_for_space(run, monkeypatch, caplog)
  assert listing(run) == []


def test_an_unwritable_checkpoint_directory_is_one_line(tmp_path, monkeypatch):
  def refused(path, *args, **kwargs):
    raise PermissionError(errno.EACCES, "Permission denied", str(path))

  monkeypatch.setattr(type(epath.Path("/")), "mkdir", refused)
  directory = re.escape(str(tmp_path / "run"))
  with pytest.raises(
    CheckpointWriteError, match=rf"^permission denied writing checkpoints to {directory}: "
  ):
    Checkpointer(tmp_path / "run")


# Errors as tensorstore words them (the full-disk one as it came from a full tmpfs, spec cut
# short): (message, the errno it carries).
TENSORSTORE_ERRORS = {
  "disk_full": (
    'RESOURCE_EXHAUSTED: Error writing local file "/x/2.orbax-checkpoint-tmp/state/_sharding": '
    'Failed writing: "/x/_sharding.__lock": Failed to write 1935 bytes to file 12: No space '
    "left on device [os_error_code='28']",
    errno.ENOSPC,
  ),
  "permission_denied": (
    'PERMISSION_DENIED: Error opening file "/x/manifest.ocdbt": Permission denied '
    "[tensorstore_spec='{}'] [os_error_code='13']",
    errno.EACCES,
  ),
  "not_a_disk_error": ('INVALID_ARGUMENT: Error parsing object member "driver"', None),
}


@pytest.mark.parametrize("case", TENSORSTORE_ERRORS)
def test_refused_writes_are_recognised_in_tensorstore_errors(case):
  text, code = TENSORSTORE_ERRORS[case]
  assert refused_write_errno(ValueError(text)) == code


def test_a_refused_write_is_recognised_through_the_exception_chain():
  try:
    try:
      raise OSError(errno.ENOSPC, "No space left on device")
    except OSError as disk:
      raise RuntimeError("commit failed") from disk
  except RuntimeError as wrapped:
    assert refused_write_errno(wrapped) == errno.ENOSPC
  assert refused_write_errno(jax.errors.JaxRuntimeError("INTERNAL: x")) is None
