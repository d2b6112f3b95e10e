"""Small experiments shared by the tests of `experiments/` (test_tasks, test_experiments_data,
test_kubric_task): the `smoke` preset on 2 + 1 scenes, the Kubric default on 1 + 1 tiny ones;
and the entry points run end to end in a subprocess (test_re10k, test_dl3dv,
test_kubric_entry_point)."""

import dataclasses
import pathlib
import subprocess
import sys

from experiments import re10k

REPO = pathlib.Path(__file__).resolve().parent.parent


def small_smoke(tmp_path, eval_changes=None, **train_changes):
  """The smoke preset on 2 training scenes and 1 test scene under `tmp_path`, with these
  training (and evaluation) settings changed."""
  smoke = re10k.PRESETS["smoke"]
  return dataclasses.replace(
    smoke,
    synthetic_dir=str(tmp_path / "data"),
    synthetic=dataclasses.replace(smoke.synthetic, num_train=2, num_test=1, workers=1),
    train=dataclasses.replace(smoke.train, **train_changes),
    eval=dataclasses.replace(smoke.eval, **(eval_changes or {})),
  )


def tiny_kubric(tmp_path, **changes):
  """The Kubric default on one training and one test scene of 2 cameras x 4 frames at 16x16 (no
  held-out family) under `tmp_path / "data"`, with these settings changed."""
  from experiments import kubric
  from experiments.config import SyntheticSettings

  tiny = kubric.PRESETS["synthetic-tiny"]
  return dataclasses.replace(
    tiny,
    synthetic_dir=str(tmp_path / "data"),
    output_dir=str(tmp_path / "out"),
    model=tiny.model.replace(image_size=(16, 16)),
    num_cameras=2,
    synthetic=SyntheticSettings(num_train=1, num_test=1, frames=4, num_ood=0, workers=1),
    **changes,
  )


def run_entry_point(*args, timeout=600):
  """`python ARGS` (`-m experiments.re10k run ...`, or `-c SCRIPT ...`) from the repository's
  root, asserted to succeed (the tail of its stderr if not); its completed process (`stdout`,
  `stderr` as text)."""
  completed = subprocess.run(
    [sys.executable, *map(str, args)],
    cwd=REPO,
    capture_output=True,
    text=True,
    timeout=timeout,
    check=False,
  )
  assert completed.returncode == 0, completed.stderr[-4000:]
  return completed
