"""Checkpoint helpers that the checkpoint and loop tests share (imported by them; no tests here):
a train state per step, and ways to damage a saved step."""

import pathlib

import jax.numpy as jnp

from tokengs_jax.train import OptimConfig, create_train_state, make_optimizer

OPTIMIZER = make_optimizer(OptimConfig(learning_rate=1e-2, schedule="constant"))


def state_at(step):
  """A train state whose arrays depend on `step`; "big" (256 KiB) is the large array file."""
  params = {
    "big": jnp.arange(64 * 1024, dtype=jnp.float32).reshape(64, 1024) + step,
    "bias": jnp.full((3,), float(step)),
  }
  state = create_train_state(params, OPTIMIZER, seed=0)
  return state.replace(step=jnp.asarray(step, jnp.int32))


def largest_array_file(step_dir: pathlib.Path) -> pathlib.Path:
  """The largest file of array chunks (`state/ocdbt.process_*/d/*`)."""
  return max((step_dir / "state").glob("ocdbt.process_*/d/*"), key=lambda p: p.stat().st_size)


def truncate_json(step_dir):
  path = step_dir / "data" / "process_0-of-1.json"
  path.write_text(path.read_text()[:7])


def flip_one_bit(step_dir):
  path = largest_array_file(step_dir)
  data = bytearray(path.read_bytes())
  data[len(data) // 2] ^= 0x10
  path.write_bytes(bytes(data))
