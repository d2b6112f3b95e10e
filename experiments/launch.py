"""Runs one command as N local processes of a multi-process JAX job (one machine, e.g. CPU tests).

    python -m experiments.launch --processes 2 -- python -m experiments.re10k run smoke
    python -m experiments.launch --processes 2 --devices-per-process 2 -- python my_script.py

Each process gets `TOKENGS_COORDINATOR=127.0.0.1:<free port>`, `TOKENGS_NUM_PROCESSES=N` and
`TOKENGS_PROCESS_ID=i` (read by `tokengs_jax.train.initialize()`, which calls
`jax.distributed.initialize`), plus `JAX_NUM_CPU_DEVICES` with `--devices-per-process` (CPU
devices per process; CPU collectives are gloo, jax's default). Output lines are prefixed `[p<i>]`.

If a process exits with an error or is killed, the launcher says which and how, stops the others
(SIGTERM to each process group, SIGKILL after `--grace` seconds) and exits with that process's
status (128 + signal for a signal), so a surviving process blocked in a collective never hangs the
job. Rerunning the same command resumes from the last checkpoint (the training loop's job). On
clusters use the scheduler instead (docs/multihost.md): the launcher is for one machine.
"""

from __future__ import annotations

import argparse
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


def _stop(processes: list[subprocess.Popen], grace: float) -> None:
  """SIGTERM to every running process group, SIGKILL to those still alive after `grace` s."""
  running = [p for p in processes if p.poll() is None]
  for sig, wait in ((signal.SIGTERM, grace), (signal.SIGKILL, 5.0)):
    for process in running:
      try:
        os.killpg(process.pid, sig)
      except ProcessLookupError:
        pass
    deadline = time.monotonic() + wait
    while running and time.monotonic() < deadline:
      running = [p for p in running if p.poll() is None]
      time.sleep(0.05)


def launch(
  command: list[str],
  processes: int,
  devices_per_process: int | None = None,
  grace: float = 5.0,
  timeout: float | None = None,
  port: int | None = None,
) -> int:
  """Starts `processes` copies of `command`; returns the job's exit status (0: all succeeded)."""
  address = f"127.0.0.1:{port or free_port()}"
  print(f"[launch] {processes} processes, coordinator {address}: {' '.join(command)}", flush=True)
  children, forwarders = [], []
  for index in range(processes):
    env = {
      **os.environ,
      "TOKENGS_COORDINATOR": address,
      "TOKENGS_NUM_PROCESSES": str(processes),
      "TOKENGS_PROCESS_ID": str(index),
    }
    if devices_per_process is not None:
      env["JAX_NUM_CPU_DEVICES"] = str(devices_per_process)
    # Own process group: stopping a process also stops its data workers.
    child = subprocess.Popen(
      command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True
    )
    forwarder = threading.Thread(
      target=_forward, args=(f"[p{index}] ", child.stdout, sys.stdout), daemon=True
    )
    forwarder.start()
    children.append(child)
    forwarders.append(forwarder)

  deadline = None if timeout is None else time.monotonic() + timeout
  status = 0
  try:
    while None in [child.poll() for child in children]:  # a list: poll every child
      failed = [(i, c.returncode) for i, c in enumerate(children) if c.returncode not in (None, 0)]
      if failed:
        index, returncode = failed[0]
        print(
          f"[launch] process {index} {describe(returncode)}; stopping the other processes",
          flush=True,
        )
        status = exit_status(returncode)
        break
      if deadline is not None and time.monotonic() > deadline:
        print(f"[launch] timeout after {timeout:g} s; stopping all processes", flush=True)
        status = 124
        break
      time.sleep(0.05)
  except KeyboardInterrupt:
    print("[launch] interrupted; stopping all processes", flush=True)
    status = 130
  finally:
    _stop(children, grace)
  for forwarder in forwarders:
    forwarder.join(timeout=5.0)
  if status == 0:
    failed = [(i, c.returncode) for i, c in enumerate(children) if c.returncode != 0]
    if failed:
      index, returncode = failed[0]
      print(f"[launch] process {index} {describe(returncode)}", flush=True)
      status = exit_status(returncode)
  else:
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
  parser.add_argument("--port", type=int, default=None, help="coordinator port (default: free)")
  args = parser.parse_args(argv[:split])
  command = argv[split + 1 :]
  if not command or args.processes < 1:
    parser.error("need a command after -- and --processes >= 1")
  return launch(
    command, args.processes, args.devices_per_process, args.grace, args.timeout, args.port
  )


if __name__ == "__main__":
  sys.exit(main())
