"""The training state: one pytree that a step maps to the next and a checkpoint stores whole."""

from __future__ import annotations

from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import optax


@flax.struct.dataclass
class TrainState:
  """Everything a step reads and writes; saving it (plus the data-iterator state) is a resume.

  Attributes:
    params: float32 parameter pytree (the master copy; compute may run in bfloat16).
    opt_state: optax state (moments, schedule counts, accumulation buffers).
    step: int32 scalar, micro-steps taken (one per `train_step` call).
    rng: uint32 [2] raw base key; step k uses `fold_in(rng, k)`, so a resumed run draws the same
      randomness as an uninterrupted one.
  """

  params: Any
  opt_state: Any
  step: jax.Array
  rng: jax.Array


def create_train_state(params, optimizer: optax.GradientTransformation, seed: int) -> TrainState:
  """A fresh state at step 0 (call inside `jax.jit(..., out_shardings=...)` to place it)."""
  return TrainState(
    params=params,
    opt_state=optimizer.init(params),
    step=jnp.zeros((), jnp.int32),
    rng=jax.random.PRNGKey(seed),
  )
