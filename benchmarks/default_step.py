"""Steps per second of the default experiment's training (`python -m experiments.re10k`).

Builds exactly what the default run trains (its model, objective, optimiser, data pipeline and
sharded step), compiles the step once, then times `--rounds` steps on a few real batches: wall
and process-CPU milliseconds per step (CPU time is the robust figure on a shared machine; on
an idle one wall ~ CPU / threads busy). `--profile` also attributes the step's CPU time to the
renderer, the model, the SSIM filter and the rest, from a `jax.profiler` trace matched to the
compiled HLO's op names.

    python benchmarks/default_step.py                       # this checkout
    python benchmarks/default_step.py --profile
    python benchmarks/default_step.py --model matmul_dtype=bfloat16
    python benchmarks/default_step.py --model dec_patch_size=2 gaussian_colours=head
        # the session-3/4 default model (512 Gaussians, head colours): issue 11's comparison
    git worktree add /tmp/old b32f2ed && python benchmarks/default_step.py --checkout /tmp/old
        # the session-3 start (issue 11's "now"): its experiments package was one module
    python benchmarks/default_step.py --host-memory default
        # glibc's and JAX's own host memory settings (the experiments set `tokengs_jax.process`'s)

The data set is generated under `--data` when missing (as the default run does).
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import collections
import glob
import gzip
import importlib.util
import json
import pathlib
import re
import sys
import tempfile
import time

import jax
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P


def use_checkout(path: str) -> None:
  """Imports `tokengs_jax` and `experiments` from the checkout at `path` rather than the installed
  one. An editable install resolves them through an import hook that outranks `PYTHONPATH`, so
  that hook is removed; call this before anything imports either package."""
  sys.meta_path[:] = [f for f in sys.meta_path if "editable" not in repr(f).lower()]
  sys.path.insert(0, path)


def this_checkouts_process():
  """This checkout's `tokengs_jax.process`, loaded from its file (it imports nothing of
  `tokengs_jax`) so that `--checkout` can still choose where `tokengs_jax` itself comes from."""
  path = pathlib.Path(__file__).resolve().parent.parent / "tokengs_jax" / "process.py"
  spec = importlib.util.spec_from_file_location("_this_checkouts_process", path)
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module


def parse_and_set_up(parser):
  """Adds `--checkout` and the process flags to a step benchmark's `parser`, parses the command
  line, sets the process up and switches to that checkout's code: call it before importing
  `tokengs_jax` or `experiments`. Returns the parsed arguments."""
  parser.add_argument("--checkout", default=None, help="time the code of this git checkout")
  process = this_checkouts_process()
  process.add_arguments(parser)
  args = parser.parse_args()
  process.setup(host_memory=args.host_memory)
  if args.checkout:
    use_checkout(args.checkout)
  return args


def _value(text: str):
  """A `--model` override value: a Python literal (2, 0.3, None) or else the string itself."""
  try:
    return ast.literal_eval(text)
  except (ValueError, SyntaxError):
    return text


def default_training(data_dir: str, model_overrides: dict):
  """(params, loss_fn, optimiser config, batch iterator) of the default experiment, with
  `model_overrides` (ModelConfig fields) applied."""
  # Imported here, not at the top, so that `--checkout` can choose where they come from.
  try:
    from experiments import tasks, weights
    from experiments.config import Experiment, optim_config
  except ImportError:  # b32f2ed and earlier: everything lived in experiments/common.py
    from experiments import common

    experiment = common.Experiment(synthetic_dir=data_dir, output_dir=tempfile.mkdtemp())
    assert not model_overrides, "model overrides need this checkout's experiments package"
    config, task = common.model_config(experiment), common.Task()
    task.prepare(experiment)
    params = common.initial_params(experiment, config, finetune=False)
    batches = iter(task.training_batches(experiment))
    return params, task.loss_fn(experiment, config), common.optim_config(experiment), batches
  experiment = Experiment(synthetic_dir=data_dir, output_dir=tempfile.mkdtemp())
  experiment = dataclasses.replace(experiment, model=experiment.model.replace(**model_overrides))
  task = tasks.Task()
  task.prepare(experiment)
  params = weights.initial_params(experiment, finetune=False)
  batches = iter(task.training_batches(experiment))
  return params, task.loss_fn(experiment, experiment.model), optim_config(experiment), batches


def _category(op_name: str) -> str:
  if "render" in op_name:
    return "renderer"
  if "hvc" in op_name or "ssim" in op_name or "conv_general" in op_name:
    return "ssim filter"
  return (
    "model"
    if any(k in op_name for k in ("encode", "decode", "attention", "reconstruct"))
    else "rest"
  )


def attribute(trace_dir: str, hlo_text: str, steps: int) -> dict[str, float]:
  """CPU ms per step by category, from the newest perfetto trace under `trace_dir`."""
  op_names = dict(
    (m.group(1), m.group(2))
    for m in re.finditer(r'^\s*(?:ROOT )?%([\w.\-]+) = .*?op_name="([^"]*)"', hlo_text, re.M)
  )
  path = sorted(glob.glob(f"{trace_dir}/plugins/profile/*/perfetto_trace.json.gz"))[-1]
  trace = json.load(gzip.open(path))
  events = trace["traceEvents"] if isinstance(trace, dict) else trace
  totals = collections.Counter()
  for event in events:
    op = event.get("args", {}).get("hlo_op") if event.get("ph") == "X" else None
    if op and not op.startswith("while"):  # a while's time is its body's ops
      totals[_category(op_names.get(op, ""))] += event["dur"] / 1e3 / steps
  return dict(totals.most_common())


def timed_steps(params, loss_fn, optim, batches):
  """The sharded train step of `loss_fn`, compiled once on 4 real batches of `batches`:
  `(run, compiled)`, where `run(rounds)` steps that many times, cycling the batches, and returns
  the wall and process-CPU milliseconds of each step."""
  # Imported here, not at the top, so that `--checkout` can choose where they come from.
  from tokengs_jax.train import (
    Precision,
    create_train_state,
    make_mesh,
    make_optimizer,
    make_train_step,
    replicate,
    shard_batch,
  )

  optimizer, mesh = make_optimizer(optim), make_mesh()
  state = jax.jit(
    lambda p: create_train_state(p, optimizer, 0), out_shardings=NamedSharding(mesh, P())
  )(replicate(params, mesh))
  step = make_train_step(loss_fn, optimizer, mesh, precision=Precision())
  examples = [shard_batch(next(batches), mesh) for _ in range(4)]
  key = jax.random.key(0)
  compiled = step.lower(state, examples[0], key).compile()

  def run(rounds):
    nonlocal state
    wall, cpu = [], []
    for r in range(rounds):
      start, start_cpu = time.perf_counter(), time.process_time()
      state, _ = compiled(state, examples[r % len(examples)], key)
      jax.block_until_ready(state)
      wall.append(time.perf_counter() - start)
      cpu.append(time.process_time() - start_cpu)
    return 1e3 * np.asarray(wall), 1e3 * np.asarray(cpu)

  return run, compiled


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--data", default="outputs/synthetic_re10k")
  parser.add_argument("--rounds", type=int, default=40)
  parser.add_argument("--profile", action="store_true")
  parser.add_argument(
    "--model", nargs="*", default=[], help="ModelConfig overrides, e.g. matmul_dtype=bfloat16"
  )
  args = parse_and_set_up(parser)
  overrides = {key: _value(text) for key, text in (item.split("=", 1) for item in args.model)}
  run, compiled = timed_steps(*default_training(args.data, overrides))
  run(5)
  wall, cpu = run(args.rounds)
  print(
    f"default train step: wall ms min {wall.min():.1f} median {np.median(wall):.1f} "
    f"({1e3 / np.median(wall):.2f} steps/s) | CPU ms min {cpu.min():.1f} "
    f"median {np.median(cpu):.1f}"
  )
  if args.profile:
    trace_dir = tempfile.mkdtemp()
    jax.profiler.start_trace(trace_dir, create_perfetto_trace=True)
    run(10)
    jax.profiler.stop_trace()
    for name, ms in attribute(trace_dir, compiled.as_text(), 10).items():
      print(f"  {name:12s} {ms:7.1f} CPU ms / step")


if __name__ == "__main__":
  main()
