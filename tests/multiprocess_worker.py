"""One process of the multi-process tests (`tests/test_multiprocess.py`), started by the launcher:

    python -m experiments.launch --processes 2 --devices-per-process 2 -- \\
        python tests/multiprocess_worker.py OUT [--steps 6] [--kill-at STEP] [--signal-at STEP]

Trains a toy regressor on an `InputPipeline` over in-memory scenes (this process's shard, chosen
by `jax.process_index()`), checkpointing to `OUT/checkpoints` every 2 steps; process 0 writes
`OUT/result.npz` (final params, history losses), every process writes the scene indices it read to
`OUT/scenes_<i>.json`. `--kill-at S`: process 1 SIGKILLs itself when step S is logged;
`--signal-at S`: process 1 sends itself SIGTERM then, and every process exits as the experiments
do when the loop stops (status 143).
The scene source, pipeline and loss are shared with the in-process reference run of the test.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import signal

import jax
import jax.numpy as jnp
import numpy as np

from tokengs_jax.data import BoundedSamplerConfig, ExampleConfig, InputPipeline
from tokengs_jax.train import LoopConfig, OptimConfig, initialize, train
from tokengs_jax.train.loop import TrainingStopped

NUM_SCENES, LOCAL_BATCH = 8, 2
OPTIM = OptimConfig(learning_rate=3e-2, schedule="constant")
EXAMPLES = ExampleConfig((8, 8), BoundedSamplerConfig(2, 1, 2, 4, 0, 0, 2, 4), 0.25)


def scenes() -> list[dict]:
  """Small random walks (8 frames of 12x12) as an in-memory scene source."""
  records = []
  for index in range(NUM_SCENES):
    rng = np.random.default_rng(index)
    c2w = np.tile(np.eye(4), (8, 1, 1))
    c2w[:, :3, 3] = np.cumsum(rng.normal(scale=0.1, size=(8, 3)), axis=0) + rng.normal(size=3)
    records.append(
      {
        "key": f"scene{index}",
        "c2w": c2w,
        "intrinsics": np.tile([10.0, 10.0, 6.0, 6.0], (8, 1)),
        "images": rng.integers(0, 255, (8, 12, 12, 3), dtype=np.uint8),
      }
    )
  return records


def pipeline(shard_index: int | None = None, shard_count: int | None = None) -> InputPipeline:
  """Default shard: `jax.process_index()` of `jax.process_count()` (the multi-host default)."""
  return InputPipeline(
    scenes(),
    EXAMPLES,
    batch_size=LOCAL_BATCH,
    seed=0,
    shard_index=shard_index,
    shard_count=shard_count,
  )


def init_params() -> dict:
  k1, k2 = jax.random.split(jax.random.PRNGKey(0))
  return {
    "hidden": jax.random.normal(k1, (6, 16)) * 0.5,
    "out": jax.random.normal(k2, (16, 3)) * 0.5,
  }


def loss_fn(params, batch, key, step):
  """Predicts the target view's mean colour from the context views' mean colour and position
  (`step`: the train step passes it; unused)."""
  del step
  features = jnp.concatenate(
    [batch["context_images"].mean((1, 2, 3)), batch["context_c2w"][:, :, :3, 3].mean(1)], -1
  )
  features = features + 0.01 * jax.random.normal(key, features.shape)
  prediction = jnp.tanh(features @ params["hidden"]) @ params["out"]
  loss = jnp.mean((prediction - batch["target_images"].mean((1, 2, 3))) ** 2)
  return loss, {}


class RecordingBatches:
  """The pipeline's iterator (checkpointable) that remembers which scenes it handed out."""

  def __init__(self, iterator):
    self.iterator, self.seen = iterator, []

  def __next__(self):
    batch = next(self.iterator)
    self.seen.extend(int(i) for i in batch["scene_index"])
    return batch

  def get_state(self):
    return self.iterator.get_state()

  def set_state(self, state):
    self.iterator.set_state(state)


def main() -> None:
  parser = argparse.ArgumentParser()
  parser.add_argument("out", type=pathlib.Path)
  parser.add_argument("--steps", type=int, default=6)
  parser.add_argument("--kill-at", type=int, default=None)
  parser.add_argument("--signal-at", type=int, default=None)
  args = parser.parse_args()
  initialize()
  index = jax.process_index()
  assert jax.process_count() == int(os.environ["TOKENGS_NUM_PROCESSES"]), "not initialised"

  def log(step, metrics):
    print(f"step {step} loss {metrics['loss']!r}", flush=True)  # repr: the exact float
    if index == 1 and step in (args.kill_at, args.signal_at):
      os.kill(os.getpid(), signal.SIGKILL if step == args.kill_at else signal.SIGTERM)

  batches = RecordingBatches(iter(pipeline()))
  try:
    state, history = train(
      loss_fn,
      init_params(),
      batches,
      OPTIM,
      LoopConfig(
        total_steps=args.steps,
        log_every=1,
        checkpoint_every=2,
        checkpoint_dir=str(args.out / "checkpoints"),
        max_to_keep=None,
        async_checkpoint=False,
      ),
      log_fn=log,
    )
  except TrainingStopped as stopped:
    raise SystemExit(stopped.exit_status) from None
  (args.out / f"scenes_{index}.json").write_text(json.dumps(batches.seen))
  params = jax.device_get(state.params)
  if index == 0:
    np.savez(
      args.out / "result.npz",
      losses=[entry["loss"] for entry in history],
      steps=[entry["step"] for entry in history],
      **{f"params/{name}": value for name, value in params.items()},
    )
  print(
    f"done on process {index} of {jax.process_count()}, devices {jax.local_devices()}", flush=True
  )


if __name__ == "__main__":
  main()
