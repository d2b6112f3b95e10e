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


def _launcher(child_code: str, *options: str) -> subprocess.Popen:
  """`experiments.launch` of 2 processes running `python -c CHILD_CODE`, its output piped."""
  return subprocess.Popen(
    [sys.executable, "-m", "experiments.launch", "--processes", "2", *options, "--"]
    + [sys.executable, "-c", child_code],
    cwd=ROOT,
    stdout=subprocess.PIPE,
    stderr=subprocess.STDOUT,
    text=True,
  )


def test_a_process_that_exits_0_early_does_not_leave_the_others_waiting():
  early_exit = textwrap.dedent(
    """
    import os, time
    time.sleep(0 if os.environ["TOKENGS_PROCESS_ID"] == "1" else 120)
    """
  )
  started = time.monotonic()
  job = _launcher(early_exit, "--finish-timeout", "7", "--grace", "1")
  try:
    output, _ = job.communicate(timeout=60)
  finally:
    job.kill()
  assert time.monotonic() - started < 30, output
  assert job.returncode == 1, output
  assert "process 1 exited with status 0 while processes [0] still run" in output, output
  assert "processes [0] did not end with the others; stopping them" in output, output


_STOPPABLE = textwrap.dedent(
  """
  import os, signal, subprocess, sys, time
  index = os.environ["TOKENGS_PROCESS_ID"]

  def stop(signum, frame):
    print(f"stopping cleanly", flush=True)
    sys.exit(128 + signum)

  signal.signal(signal.SIGTERM, stop)
  helper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
  print(f"ready {os.getpid()} {helper.pid}", flush=True)
  time.sleep(120)
  """
)


def test_sigterm_to_the_launcher_stops_each_process_cleanly_and_reaps_their_helpers():
  """Each process gets SIGTERM first (a training process saves its step), then its process group
  SIGKILL: a helper process the child left behind (as a data worker could) ends too."""
  job = _launcher(_STOPPABLE, "--grace", "10")
  pids = []
  try:
    lines = []
    for line in job.stdout:
      lines.append(line)
      if " ready " in line:
        pids += [int(pid) for pid in line.split()[2:]]
        if len(pids) == 4:
          break
    stopped_at = time.monotonic()
    job.send_signal(signal.SIGTERM)
    output = "".join(lines) + job.communicate(timeout=60)[0]
    assert time.monotonic() - stopped_at < 8, output
    assert job.returncode == 128 + signal.SIGTERM, output
    assert "[launch] SIGTERM; stopping all processes" in output, output
    for index in range(2):
      assert f"[p{index}] stopping cleanly" in output, output
      assert f"[launch] process {index} exited with status 143" in output, output
    assert _wait_gone(pids, 5.0) == [], "orphaned processes"
  finally:
    job.kill()
    for pid in pids:
      if _alive(pid):
        os.kill(pid, signal.SIGKILL)


_SLEEPING = textwrap.dedent(
  """
  import os, time
  print(f"ready {os.getpid()}", flush=True)
  time.sleep(120)
  """
)


def test_a_killed_launcher_takes_its_processes_with_it():
  """Nothing runs in a launcher killed by SIGKILL: the kernel ends its processes
  (`PR_SET_PDEATHSIG`); they used to sleep on as orphans."""
  job = _launcher(_SLEEPING)
  pids = []
  try:
    for line in job.stdout:
      if " ready " in line:
        pids.append(int(line.split()[2]))
        if len(pids) == 2:
          break
    job.kill()
    job.wait(timeout=10)
    assert _wait_gone(pids, 5.0) == [], "orphaned processes"
  finally:
    job.kill()
    job.stdout.close()
    for pid in pids:
      if _alive(pid):
        os.kill(pid, signal.SIGKILL)
