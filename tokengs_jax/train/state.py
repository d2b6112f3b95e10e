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
    ema_params: the exponential moving average of `params` (`OptimConfig.ema_decay` > 0), a
      pytree of their structure, dtypes and sharding, updated by the step after each optimiser
      update (`ema_update`); None when the average is off (no memory, no compute).
  """

  params: Any
  opt_state: Any
  step: jax.Array
  rng: jax.Array
  ema_params: Any = None


def create_train_state(
  params, optimizer: optax.GradientTransformation, seed: int, ema_decay: float = 0.0
) -> TrainState:
  """A fresh state at step 0 (call inside `jax.jit(..., out_shardings=...)` to place it).

  With `ema_decay > 0` the moving average starts equal to `params` (a copy), so it is a weighted
  mean of parameter values from the first step on and needs no bias correction.
  """
  return TrainState(
    params=params,
    opt_state=optimizer.init(params),
    step=jnp.zeros((), jnp.int32),
    rng=jax.random.PRNGKey(seed),
    ema_params=jax.tree.map(jnp.copy, params) if ema_decay > 0 else None,
  )


def ema_update(ema_params, params, decay: float):
  """One step of the average: `decay * ema + (1 - decay) * params`, leaf by leaf."""
  return jax.tree.map(lambda ema, new: decay * ema + (1.0 - decay) * new, ema_params, params)


def trained_params(state: TrainState):
  """The weights a run hands on (saves, evaluates): the moving average when the state keeps one,
  else the parameters."""
  return state.params if state.ema_params is None else state.ema_params
