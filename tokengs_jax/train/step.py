"""One jitted, sharded training step around a model-agnostic `loss_fn(params, batch, key, step)`.

Sharding is GSPMD over a `jax.make_mesh` mesh with axes ("data", "model"): the batch is split over
"data" along its leading axis, the state is replicated (a `state_sharding` pytree can put
parameters on "model" later without touching this code). The gradient all-reduce that makes the
multi-device step equal to the single-device one is inserted by the partitioner because the loss
is a mean over the global batch.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import optax
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from tokengs_jax.train.optim import current_learning_rate
from tokengs_jax.train.state import TrainState, ema_update

# (params, batch, key, step [] int32) -> (scalar loss, aux dict of scalars)
LossFn = Callable[[Any, dict, jax.Array, jax.Array], tuple[jax.Array, dict]]


@dataclasses.dataclass(frozen=True)
class Precision:
  """Mixed-precision policy: float32 master parameters, `compute_dtype` inside the loss.

  The step casts floating parameters to `compute_dtype` before calling the loss; the cast's
  transpose returns float32 gradients, so the optimiser and its state stay float32. The loss
  function decides what else runs in higher precision. The default is no cast: the TokenGS
  network has its own policy (`ModelConfig.dtype="bfloat16"`: bf16 matmuls, float32 parameters
  and norms) and its objective renders in float32; use `Precision(jnp.bfloat16)` for models
  without one.
  """

  compute_dtype: Any = jnp.float32


def cast_floating(tree, dtype):
  """Casts every floating leaf of `tree` to `dtype`; integer and key leaves are left alone."""

  def cast(leaf):
    return leaf.astype(dtype) if jnp.issubdtype(jnp.result_type(leaf), jnp.floating) else leaf

  return jax.tree.map(cast, tree)


def _with_average(state: TrainState, decay: float) -> TrainState:
  """`state` with its parameter average moved towards its (just updated) params, when it keeps
  one. Under gradient accumulation (`optax.MultiSteps`) only on the micro-steps that updated the
  parameters, so the decay counts optimiser updates."""
  if state.ema_params is None:
    return state
  if not decay > 0:
    raise ValueError("the state keeps a parameter average (ema_params) but ema_decay is 0")

  def average(ema):
    return ema_update(ema, state.params, decay)

  if isinstance(state.opt_state, optax.MultiStepsState):
    updated = state.opt_state.mini_step == 0
    return state.replace(ema_params=jax.lax.cond(updated, average, lambda e: e, state.ema_params))
  return state.replace(ema_params=average(state.ema_params))


def train_step_fn(
  loss_fn: LossFn,
  optimizer: optax.GradientTransformation,
  precision: Precision = Precision(),
  ema_decay: float = 0.0,
):
  """The unjitted step `(state, batch, key) -> (state, metrics)`.

  The loss is called as `loss_fn(params, batch, fold_in(key, state.step), state.step)`: the step
  is passed explicitly for step-scheduled terms (the dynamic auxiliary weight). When the loss or
  the gradient's global norm is non-finite (a NaN or infinity in any gradient, or a norm that
  overflows float32) the returned state is the input state (update skipped, step not advanced)
  and `metrics["finite"]` is False; the loop turns that into a loud stop. A state that keeps a
  parameter average (`TrainState.ema_params`, from `create_train_state(..., ema_decay)`) has it
  moved with `ema_decay` after each kept optimiser update; a state without one is left without.
  """

  def step(state: TrainState, batch: dict, key: jax.Array):
    step_key = jax.random.fold_in(key, state.step)

    def compute_loss(params):
      loss, aux = loss_fn(
        cast_floating(params, precision.compute_dtype), batch, step_key, state.step
      )
      return loss.astype(jnp.float32), aux

    (loss, aux), grads = jax.value_and_grad(compute_loss, has_aux=True)(state.params)
    # One reduction over every gradient serves the metric and the check: a NaN or an infinity
    # anywhere makes the norm non-finite (a test per leaf cost ~200 small ops per step).
    grad_norm = optax.tree.norm(grads)
    finite = jnp.isfinite(loss) & jnp.isfinite(grad_norm)

    def apply_update(state):
      updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
      state = state.replace(
        params=optax.apply_updates(state.params, updates), opt_state=opt_state, step=state.step + 1
      )
      return _with_average(state, ema_decay)

    # A branch rather than a select per leaf: the update runs only when it is kept, and the
    # state is written in place (a select keeps both versions alive, so XLA copied the params).
    new_state = jax.lax.cond(finite, apply_update, lambda state: state, state)
    metrics = {
      "loss": loss,
      "grad_norm": grad_norm,
      "finite": finite,
      "learning_rate": current_learning_rate(new_state.opt_state),
      **aux,
    }
    return new_state, metrics

  return step


def make_train_step(
  loss_fn: LossFn,
  optimizer: optax.GradientTransformation,
  mesh: Mesh,
  *,
  precision: Precision = Precision(),
  state_sharding=None,
  donate: bool = True,
  ema_decay: float = 0.0,
):
  """Jits the step with shardings over `mesh` and the state buffers donated.

  Args:
    loss_fn: `(params, batch, key, step) -> (scalar loss, aux dict of scalars)`, a mean over the
      batch.
    optimizer: from `make_optimizer`.
    mesh: a mesh with a "data" axis (see `distributed.make_mesh`).
    precision: compute-dtype policy.
    state_sharding: sharding (or pytree prefix of shardings) for the state; default replicated.
    donate: donate the input state's buffers (the caller must not reuse the passed state).
    ema_decay: decay of the state's parameter average (`OptimConfig.ema_decay`), used when the
      state keeps one (`TrainState.ema_params`); a `state_sharding` pytree then gives it the
      params' shardings.

  Returns:
    `train_step(state, batch, key) -> (state, metrics)`; batch leaves `[B, ...]` with B divisible
    by the "data" axis size; metrics are replicated scalars.
  """
  replicated = NamedSharding(mesh, P())
  batch_sharding = NamedSharding(mesh, P("data"))
  state_sharding = replicated if state_sharding is None else state_sharding
  return jax.jit(
    train_step_fn(loss_fn, optimizer, precision, ema_decay),
    in_shardings=(state_sharding, batch_sharding, replicated),
    out_shardings=(state_sharding, replicated),
    donate_argnums=(0,) if donate else (),
  )
