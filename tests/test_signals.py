"""Processes end together: the data pipeline's workers (and multiprocessing's resource tracker) end
with a killed main process, and `experiments.launch` stops a job whose process exited early or
that was sent SIGTERM, letting each process stop between two training steps first.
(The training loop's own SIGTERM/SIGINT stop: tests/test_train_loop.py.)"""

import json
import os
import pathlib
import signal
import subprocess
import sys
import textwrap
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent

_KILLED_WITH_WORKERS = textwrap.dedent(
  """
  import json, multiprocessing, os, signal, sys
  from multiprocessing import resource_tracker
  sys.path.insert(0, sys.argv[1])
  from multiprocess_worker import EXAMPLES, scenes
  from tokengs_jax.data import InputPipeline

  batches = iter(InputPipeline(scenes(), EXAMPLES, batch_size=2, shard_index=0, shard_count=1,
                               num_workers=2))
  next(batches)
  helpers = [p.pid for p in multiprocessing.active_children()] + [resource_tracker._resource_tracker._pid]
  print(json.dumps(helpers), flush=True)
  os.kill(os.getpid(), signal.SIGKILL)
  """
)


def _alive(pid: int) -> bool:
  """Whether `pid` runs (a zombie, dead but not yet reaped by its new parent, counts as ended)."""
  try:
    with open(f"/proc/{pid}/stat") as stat:
      return stat.read().rsplit(")", 1)[1].split()[0] != "Z"
  except FileNotFoundError:
    return False


def _wait_gone(pids: list[int], seconds: float) -> list[int]:
  """The pids still running after up to `seconds`."""
  deadline = time.monotonic() + seconds
  while (running := [pid for pid in pids if _alive(pid)]) and time.monotonic() < deadline:
    time.sleep(0.1)
  return running


def test_data_workers_and_the_resource_tracker_end_with_a_killed_main_process(tmp_path):
  # Files, not pipes: orphans would hold a pipe open, and reading it would wait for them.
  out, err = tmp_path / "out", tmp_path / "err"
  with out.open("w") as stdout, err.open("w") as stderr:
    returncode = subprocess.run(
      [sys.executable, "-c", _KILLED_WITH_WORKERS, str(ROOT / "tests")],
      stdout=stdout,
      stderr=stderr,
      timeout=300,
    ).returncode
  assert returncode == -signal.SIGKILL, err.read_text()
  helpers = json.loads(out.read_text().strip().splitlines()[-1])
  assert len(helpers) == 3, helpers  # 2 workers + the tracker
  try:
    assert _wait_gone(helpers, 5.0) == [], "orphaned workers or resource tracker"
  finally:
    for pid in helpers:
      if _alive(pid):
        os.kill(pid, signal.SIGKILL)
