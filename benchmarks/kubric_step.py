"""Milliseconds per training step of the Kubric default (`python -m experiments.kubric`).

Builds the `synthetic-tiny` preset's model (its shipped weights), objective, optimiser (the
`pretrain` preset's schedule: synthetic-tiny trains 0 steps) and sharded step, compiles the step
once, then times `--rounds` steps cycling 4 real batches: wall and process-CPU milliseconds per
step (CPU time is the steadier figure on a shared machine). The data are a few scenes of the
preset's own generator (`--scenes` training scenes at its size, frames and cameras), written under
`--data` when missing; fewer scenes than the preset's change which examples are drawn, not their
shapes.

    python benchmarks/kubric_step.py                           # this checkout
    git worktree add /tmp/old HEAD && python benchmarks/kubric_step.py --checkout /tmp/old
        # another checkout's code on the same data (alternate the two for an A/B)
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile

import numpy as np
from default_step import parse_and_set_up, timed_steps


def kubric_training(data_dir: str, num_scenes: int):
  """(params, loss_fn, optimiser config, batch iterator) of the Kubric default."""
  # Imported here, not at the top, so that `--checkout` can choose where they come from.
  from experiments import kubric, weights
  from experiments.config import optim_config

  preset = kubric.PRESETS["synthetic-tiny"]
  experiment = dataclasses.replace(
    preset,
    synthetic_dir=data_dir,
    output_dir=tempfile.mkdtemp(),
    synthetic=dataclasses.replace(preset.synthetic, num_train=num_scenes, num_test=1, num_ood=0),
    train=kubric.PRESETS["pretrain"].train,  # synthetic-tiny trains 0 steps: no schedule
  )
  task = kubric.KubricTask()
  task.prepare(experiment)
  params = weights.initial_params(experiment, finetune=False)
  batches = iter(task.training_batches(experiment))
  return params, task.loss_fn(experiment, experiment.model), optim_config(experiment), batches


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--data", default="outputs/kubric_step")
  parser.add_argument("--scenes", type=int, default=8)
  parser.add_argument("--rounds", type=int, default=20)
  args = parse_and_set_up(parser)
  run, _ = timed_steps(*kubric_training(args.data, args.scenes))
  run(5)
  wall, cpu = run(args.rounds)
  print(
    f"kubric train step: wall ms min {wall.min():.1f} median {np.median(wall):.1f} | "
    f"CPU ms min {cpu.min():.1f} median {np.median(cpu):.1f}"
  )


if __name__ == "__main__":
  main()
