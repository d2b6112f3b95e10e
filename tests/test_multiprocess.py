"""Real multi-process training: 2 processes x 2 CPU devices (`jax.distributed`, gloo collectives)
started by `experiments.launch`, against the same steps in this one process on 4 devices."""

import json
import os
import pathlib
import subprocess
import sys
import time

import jax
import numpy as np
import pytest
from multiprocess_worker import OPTIM, init_params, loss_fn, pipeline

from experiments.launch import describe, exit_status
from tokengs_jax.train import LoopConfig, train

ROOT = pathlib.Path(__file__).resolve().parent.parent
TIMEOUT = 600  # seconds per launch; a hang fails the test instead of blocking the suite


def launch_command(arguments: list[str]) -> tuple[int, list[tuple[float, str]]]:
  """Runs `python ARGUMENTS` as a 2-process job of 2 CPU devices each; returns (exit status,
  [(arrival time, output line)])."""
  command = [
    sys.executable,
    "-m",
    "experiments.launch",
    "--processes",
    "2",
    "--devices-per-process",
    "2",
    "--grace",
    "5",
    "--timeout",
    str(TIMEOUT),
    "--",
    sys.executable,
    *arguments,
  ]
  env = {
    **os.environ,
    "JAX_PLATFORMS": "cpu",
    "TOKENGS_JAX_CACHE": os.environ.get("TOKENGS_JAX_CACHE", str(ROOT / ".jax_cache")),
  }
  job = subprocess.Popen(
    command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
  )
  lines = [(time.monotonic(), line.rstrip("\n")) for line in job.stdout]
  return job.wait(timeout=30), lines


def launch(out: pathlib.Path, *worker_args: str) -> tuple[int, list[tuple[float, str]]]:
  """The toy training worker as a 2-process job."""
  return launch_command([str(ROOT / "tests" / "multiprocess_worker.py"), str(out), *worker_args])


class GlobalBatches:
  """The 2-process job's global batch in one process: shard 0's examples, then shard 1's (the
  order of `make_array_from_process_local_data` over process 0's devices, then process 1's)."""

  def __init__(self):
    self.shards = [iter(pipeline(index, 2)) for index in range(2)]

  def __next__(self):
    parts = [next(shard) for shard in self.shards]
    return {key: np.concatenate([part[key] for part in parts]) for key in parts[0]}


def test_launcher_reports_signals_as_shell_statuses():
  assert describe(-9) == "was killed by SIGKILL" and exit_status(-9) == 137
  assert describe(3) == "exited with status 3" and exit_status(3) == 3


def test_two_processes_train_like_one_and_a_killed_job_resumes_exactly(tmp_path):
  """A job is killed mid-run (process 1 SIGKILLs itself once step 6 is logged, before step 6 is
  saved): the launcher stops process 0 within seconds and fails. The same command resumes both
  processes from step 4 (written by both; the half-written step 6 is not a checkpoint), recomputes
  steps 5 and 6 bit-exactly, and keeps the log of steps 1-4. The job matches one process on 4
  devices over the same global batches (to float32 rounding: the all-reduce order differs).
  Each process read only its own shard of the scenes."""
  status, lines = launch(tmp_path, "--kill-at", "6")
  text = "\n".join(line for _, line in lines)
  assert status == 137, text
  assert "[launch] process 1 was killed by SIGKILL; stopping the other processes" in text, text
  killed_at = next(t for t, line in lines if line.startswith("[p1] step 6 "))
  print(f"kill -> job stopped: {lines[-1][0] - killed_at:.1f} s")
  assert lines[-1][0] - killed_at < 30, text
  first_losses = {
    int(line.split()[2]): float(line.split()[4])
    for _, line in lines
    if line.startswith("[p0] step ")
  }
  assert sorted(first_losses) == [1, 2, 3, 4, 5, 6], text
  steps = sorted(int(p.name) for p in (tmp_path / "checkpoints").iterdir() if p.name.isdigit())
  assert steps == [2, 4], steps
  assert sorted(p.name for p in (tmp_path / "checkpoints" / "4" / "data").glob("*.json")) == [
    "process_0-of-2.json",
    "process_1-of-2.json",
  ]

  status, lines = launch(tmp_path)
  text = "\n".join(line for _, line in lines)
  assert status == 0, text
  for index in range(2):
    assert f"[p{index}] [train] resuming from step 4" in text, text
  result = np.load(tmp_path / "result.npz")
  assert list(result["steps"]) == [1, 2, 3, 4, 5, 6]
  assert list(result["losses"]) == [first_losses[step] for step in range(1, 7)]

  reference, history = train(
    loss_fn,
    init_params(),
    GlobalBatches(),
    OPTIM,
    LoopConfig(total_steps=6, log_every=1),
    log_fn=lambda *_: None,
  )
  assert result["losses"][0] == history[0]["loss"]  # the first step's loss is bit-equal
  np.testing.assert_allclose(result["losses"], [entry["loss"] for entry in history], rtol=2e-6)
  for name, value in jax.device_get(reference.params).items():
    np.testing.assert_allclose(result[f"params/{name}"], value, rtol=2e-5, atol=1e-7, err_msg=name)

  seen = [set(json.loads((tmp_path / f"scenes_{index}.json").read_text())) for index in range(2)]
  assert seen[0] == {0, 2, 4, 6} and seen[1] == {1, 3, 5, 7}, seen


def test_sigterm_to_one_process_stops_both_at_the_same_step_with_a_checkpoint(tmp_path):
  """Process 1 alone gets SIGTERM while step 3 is logged: both processes stop after step 4 (they
  agree one step later), both save step 4's checkpoint and exit 143. The same command resumes both
  from step 4 and ends as an uninterrupted job."""
  status, lines = launch(tmp_path, "--signal-at", "3")
  text = "\n".join(line for _, line in lines)
  assert status == 143, text
  for index in range(2):
    assert f"[p{index}] [train] SIGTERM: stopped at step 4, resume with the same command" in text
  first_losses = [float(line.split()[4]) for _, line in lines if line.startswith("[p0] step ")]
  assert len(first_losses) == 4, text
  assert sorted(p.name for p in (tmp_path / "checkpoints" / "4" / "data").glob("*.json")) == [
    "process_0-of-2.json",
    "process_1-of-2.json",
  ]

  status, lines = launch(tmp_path)
  text = "\n".join(line for _, line in lines)
  assert status == 0, text
  for index in range(2):
    assert f"[p{index}] [train] resuming from step 4" in text, text
  result = np.load(tmp_path / "result.npz")
  assert list(result["steps"]) == [1, 2, 3, 4, 5, 6]
  assert list(result["losses"][:4]) == first_losses


@pytest.mark.slow
def test_entry_point_in_two_processes_writes_results_from_process_0_only(tmp_path):
  """`python -m experiments.launch --processes 2 -- python -m experiments.re10k run smoke`: trains
  (checkpoints from both processes), evaluates, and only process 0 writes results (metrics,
  pictures, params, history, TensorBoard); rerun with more steps resumes and keeps the history."""
  out, record = tmp_path / "out", tmp_path / "writes"
  experiment = [
    "-m",
    "experiments.re10k",
    "run",
    "smoke",
    "--train.batch-size",
    "4",
    "--train.checkpoint-every",
    "2",
    "--output-dir",
    str(out),
    "--synthetic-dir",
    str(tmp_path / "synthetic"),
  ]
  wrapper = [str(ROOT / "tests" / "multiprocess_writes.py"), str(out), str(record)]
  status, lines = launch_command([*wrapper, *experiment, "--train.steps", "2"])
  text = "\n".join(line for _, line in lines)
  assert status == 0, text
  written = [json.loads(pathlib.Path(f"{record}.{index}.json").read_text()) for index in range(2)]
  results = [[path for path in paths if not path.startswith("checkpoints")] for paths in written]
  assert results[1] == [], results[1]
  for name in ("metrics.json", "metrics.md", "params.msgpack", "train_history.json"):
    assert name in results[0], results[0]
  assert any(path.startswith("tensorboard/") for path in results[0]), results[0]
  assert len(list((out / "tensorboard").iterdir())) == 1
  for index in range(2):  # each process wrote its iterator state (in orbax's temporary step)
    name = f"process_{index}-of-2.json"
    assert any("/data" in path and path.endswith("/" + name) for path in written[index])
    assert (out / "checkpoints" / "2" / "data" / name).is_file()

  status, lines = launch_command([*wrapper, *experiment, "--train.steps", "4"])
  text = "\n".join(line for _, line in lines)
  assert status == 0, text
  assert "[p0] [train] resuming from step 2" in text and "[p1] [train] resuming from step 2" in text
  history = json.loads((out / "train_history.json").read_text())
  assert [entry["step"] for entry in history] == [1, 2, 3, 4]


@pytest.mark.slow
def test_two_processes_walk_back_together_past_a_file_damaged_on_one(tmp_path):
  """Step 4's iterator file of process 1 only is truncated: both processes skip step 4 (process 0
  because process 1 could not read it), resume from step 2 and recompute steps 3-4 bit-exactly."""
  status, lines = launch(tmp_path, "--steps", "4")
  assert status == 0, "\n".join(line for _, line in lines)
  first = [line.split()[4] for _, line in lines if line.startswith("[p0] step ")]
  damaged = tmp_path / "checkpoints" / "4" / "data" / "process_1-of-2.json"
  damaged.write_text(damaged.read_text()[:5])

  status, lines = launch(tmp_path, "--steps", "4")
  text = "\n".join(line for _, line in lines)
  assert status == 0, text
  skipped = {
    index: [
      line
      for _, line in lines
      if line.startswith(f"[p{index}]")
      and "checkpoint step 4" in line
      and "unusable, skipped" in line
    ]
    for index in range(2)
  }
  assert len(skipped[1]) == 1 and "JSONDecodeError" in skipped[1][0], text
  assert len(skipped[0]) == 1 and "another process could not restore it" in skipped[0][0], text
  for index in range(2):
    assert f"[p{index}] [train] resuming from step 2" in text, text
  again = [line.split()[4] for _, line in lines if line.startswith("[p0] step ")]
  assert again == first[2:], (first, again)
  assert (tmp_path / "checkpoints" / "4.unusable").is_dir()  # and step 4 was saved again:
  assert (tmp_path / "checkpoints" / "4" / "data" / "process_1-of-2.json").is_file()
