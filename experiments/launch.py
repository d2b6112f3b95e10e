"""Runs one command as N local processes of a multi-process JAX job (one machine, e.g. CPU tests).

    python -m experiments.launch --processes 2 -- python -m experiments.re10k run smoke
    python -m experiments.launch --processes 2 --devices-per-process 2 -- python my_script.py

Each process gets `TOKENGS_COORDINATOR=127.0.0.1:<free port>`, `TOKENGS_NUM_PROCESSES=N` and
`TOKENGS_PROCESS_ID=i` (read by `tokengs_jax.train.initialize()`, which calls
`jax.distributed.initialize`), plus `JAX_NUM_CPU_DEVICES` with `--devices-per-process` (CPU
devices per process; CPU collectives are gloo, jax's default). Output lines are prefixed `[p<i>]`.

The job ends as one: if a process exits with an error or is killed, the launcher says which and
how, stops the others and exits with that process's status (128 + signal for a signal), so a
surviving process blocked in a collective never hangs the job. A process that exits 0 while others
still run is named; the processes of a JAX job end together (`jax.distributed` waits at
exit for all of them), so those still running `--finish-timeout` seconds later are stopped and the
job fails (status 1). SIGTERM or SIGINT to the launcher stops the job (status 128 + signal).
A launcher killed outright (SIGKILL) takes its processes with it on Linux (`_dying_with_launcher`);
elsewhere they live on.

Stopping a process: SIGTERM to it (the training loop then finishes its step, saves it and exits
143), SIGKILL to its process group (it and its data workers) after `--grace` seconds, or at once
on a second SIGTERM/SIGINT to the launcher. Rerunning the same command resumes from the last
checkpoint (the training loop's job). On clusters use the scheduler instead (docs/multihost.md):
the launcher is for one machine.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import os
import signal
import socket
import subprocess
import sys
import threading
import time


def free_port() -> int:
  """A TCP port free on 127.0.0.1 now (the coordinator binds it moments later)."""
  with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
    sock.bind(("127.0.0.1", 0))
    return sock.getsockname()[1]


def describe(returncode: int) -> str:
  if returncode < 0:
    return f"was killed by {signal.Signals(-returncode).name}"
  return f"exited with status {returncode}"


def exit_status(returncode: int) -> int:
  return 128 - returncode if returncode < 0 else returncode


def _forward(prefix: str, stream, out) -> None:
  for line in iter(stream.readline, b""):
    out.buffer.write(prefix.encode() + line)
    out.flush()


class _Interrupted(Exception):
  """SIGTERM or SIGINT reached the launcher."""

  def __init__(self, signum: int):
    super().__init__(signal.Signals(signum).name)
    self.signum = signum


def _interrupt(signum: int, frame) -> None:
  raise _Interrupted(signum)


_STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)
# The processes of a JAX job end within about a second of each other: one still running this long
# after another exited 0 is worth a line (and is stopped after --finish-timeout).
_NOTE_AFTER_S = 5.0


_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def _dying_with_launcher():
  """The `preexec_fn` that makes a started process get SIGKILL when the launcher ends, however it
  ended (the kernel's `PR_SET_PDEATHSIG`, kept across exec); None where there is no such setting
  (not Linux: the processes outlive a killed launcher).

  SIGKILL, not the SIGTERM the launcher's own stop starts with: a killed launcher cannot send the
  SIGKILL that follows it after `--grace`, and with it gone the process's output pipe is broken,
  so it would fail on its next line, perhaps halfway through saving. A rerun resumes from the
  last complete checkpoint. The data workers end with their process (`process.exit_with_parent`).

  The signal comes when the thread that started the process ends: `launch` runs in the main one.
  """
  if not sys.platform.startswith("linux"):
    return None
  prctl = ctypes.CDLL(None).prctl  # looked up before the fork: the child only calls it
  launcher = os.getpid()

  def die_with_launcher() -> None:
    prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != launcher:  # the launcher ended before the setting took: no signal comes
      os.kill(os.getpid(), signal.SIGKILL)

  return die_with_launcher


def _start(command: list[str], index: int, processes: int, address: str, devices: int | None):
  """Process `index` of the job, in its own process group, its output piped."""
  env = {
    **os.environ,
    "TOKENGS_COORDINATOR": address,
    "TOKENGS_NUM_PROCESSES": str(processes),
    "TOKENGS_PROCESS_ID": str(index),
  }
  if devices is not None:
    env["JAX_NUM_CPU_DEVICES"] = str(devices)
  # Own process group: killing the group also kills its data workers.
  return subprocess.Popen(
    command,
    env=env,
    stdout=subprocess.PIPE,
    stderr=subprocess.STDOUT,
    start_new_session=True,
    preexec_fn=_dying_with_launcher(),
  )


def _forward_output(child: subprocess.Popen, index: int) -> threading.Thread:
  """The thread copying the output of process `index` to the launcher's, each line prefixed."""
  forwarder = threading.Thread(
    target=_forward, args=(f"[p{index}] ", child.stdout, sys.stdout), daemon=True
  )
  forwarder.start()
  return forwarder


def _watch(children: list[subprocess.Popen], timeout: float | None, finish_timeout: float) -> int:
  """Waits until every process exited 0 (-> 0), one failed (-> its status), the job ran past
  `timeout` (-> 124), or some still run `finish_timeout` s after one exited 0 (-> 1)."""
  started, first_finished, noted = time.monotonic(), None, False
  while True:
    codes = [child.poll() for child in children]  # a list: poll every child
    running = [index for index, code in enumerate(codes) if code is None]
    failed = [(index, code) for index, code in enumerate(codes) if code not in (None, 0)]
    if failed:
      index, code = failed[0]
      print(f"[launch] process {index} {describe(code)}; stopping the other processes", flush=True)
      return exit_status(code)
    if not running:
      return 0
    now = time.monotonic()
    if first_finished is None and len(running) < len(children):
      first_finished = now
    if first_finished is not None and not noted and now - first_finished > _NOTE_AFTER_S:
      noted = True
      print(
        f"[launch] process {codes.index(0)} exited with status 0 while processes {running} still "
        f"run; stopping them if they have not ended in {finish_timeout:g} s",
        flush=True,
      )
    if first_finished is not None and now - first_finished > finish_timeout:
      print(f"[launch] processes {running} did not end with the others; stopping them", flush=True)
      return 1
    if timeout is not None and now - started > timeout:
      print(f"[launch] timeout after {timeout:g} s; stopping all processes", flush=True)
      return 124
    time.sleep(0.05)


def _stop(processes: list[subprocess.Popen], grace: float) -> None:
  """SIGTERM to each running process; after `grace` s (sooner on a second SIGTERM/SIGINT to the
  launcher), SIGKILL to every process group, which also ends workers left by exited processes."""
  hurry = threading.Event()
  for signum in _STOP_SIGNALS:
    signal.signal(signum, lambda *_: hurry.set())
  running = [process for process in processes if process.poll() is None]
  for process in running:
    with contextlib.suppress(ProcessLookupError):
      os.kill(process.pid, signal.SIGTERM)
  deadline = time.monotonic() + grace
  while running and time.monotonic() < deadline and not hurry.is_set():
    running = [process for process in running if process.poll() is None]
    time.sleep(0.05)
  for process in processes:
    with contextlib.suppress(ProcessLookupError):
      os.killpg(process.pid, signal.SIGKILL)
  for process in processes:
    process.wait()


def launch(
  command: list[str],
  processes: int,
  devices_per_process: int | None = None,
  grace: float = 5.0,
  timeout: float | None = None,
  port: int | None = None,
  finish_timeout: float = 60.0,
) -> int:
  """Starts `processes` copies of `command`; returns the job's exit status (0: all succeeded).
  Call from the main thread (it handles SIGTERM and SIGINT while the job runs)."""
  address = f"127.0.0.1:{port or free_port()}"
  print(f"[launch] {processes} processes, coordinator {address}: {' '.join(command)}", flush=True)
  children, forwarders = [], []
  previous = {signum: signal.signal(signum, _interrupt) for signum in _STOP_SIGNALS}
  try:
    # Every process before the first output thread: `preexec_fn` runs Python in the forked
    # launcher, which is safe only while it has no other thread (one could hold a lock forever).
    for index in range(processes):
      children.append(_start(command, index, processes, address, devices_per_process))
    forwarders = [_forward_output(child, index) for index, child in enumerate(children)]
    status = _watch(children, timeout, finish_timeout)
  except _Interrupted as interrupted:
    print(f"[launch] {interrupted}; stopping all processes", flush=True)
    status = 128 + interrupted.signum
  finally:
    _stop(children, grace)
    for signum, handler in previous.items():
      signal.signal(signum, handler)
  for forwarder in forwarders:
    forwarder.join(timeout=5.0)
  if status != 0:
    for index, child in enumerate(children):
      print(f"[launch] process {index} {describe(child.returncode)}", flush=True)
  return status


def main(argv: list[str] | None = None) -> int:
  argv = sys.argv[1:] if argv is None else argv
  if "--" not in argv:
    raise SystemExit("usage: python -m experiments.launch --processes N [options] -- COMMAND ...")
  split = argv.index("--")
  parser = argparse.ArgumentParser(
    prog="python -m experiments.launch", description=__doc__.split("\n\n")[0]
  )
  parser.add_argument("--processes", type=int, required=True, help="local processes")
  parser.add_argument(
    "--devices-per-process",
    type=int,
    default=None,
    help="CPU devices per process (sets JAX_NUM_CPU_DEVICES)",
  )
  parser.add_argument(
    "--grace",
    type=float,
    default=5.0,
    help="seconds between SIGTERM and SIGKILL when stopping processes",
  )
  parser.add_argument("--timeout", type=float, default=None, help="stop the job after this long")
  parser.add_argument(
    "--finish-timeout",
    type=float,
    default=60.0,
    help="seconds the other processes get to end after one exited 0",
  )
  parser.add_argument("--port", type=int, default=None, help="coordinator port (default: free)")
  args = parser.parse_args(argv[:split])
  command = argv[split + 1 :]
  if not command or args.processes < 1:
    parser.error("need a command after -- and --processes >= 1")
  return launch(
    command,
    args.processes,
    args.devices_per_process,
    args.grace,
    args.timeout,
    args.port,
    args.finish_timeout,
  )


if __name__ == "__main__":
  sys.exit(main())
