"""AdamW with the official weight-decay grouping, learning-rate schedules, clipping, accumulation.

Two schedules are offered:
- `"warmup_cosine"` (the paper, Sec. 5): linear warm-up from 0 to the peak over `warmup_steps`,
  then cosine decay to `end_learning_rate` at `total_steps`.
- `"one_cycle"` (the official `train.py`): torch's `OneCycleLR` with cosine annealing,
  `pct_start = min(warmup_steps / total_steps, 0.99)`, start at `peak / div_factor`, end at
  `peak / div_factor / final_div_factor`. torch's `OneCycleLR` also cycles AdamW's beta1
  (0.95 -> 0.85 during warm-up, back to 0.95 after) because `cycle_momentum=True` is its default;
  `cycle_momentum` reproduces that, so the official run's beta1 is not the 0.9 it was built with.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

import jax
import jax.numpy as jnp
import optax


@dataclasses.dataclass(frozen=True)
class OptimConfig:
  """Optimiser and schedule settings (defaults: the paper's base training).

  Attributes:
    learning_rate: peak learning rate.
    schedule: "warmup_cosine" (paper), "one_cycle" (official code) or "constant".
    total_steps: optimiser updates in the whole run (after accumulation).
    warmup_steps: linear warm-up length (one-cycle: the rising phase, official `pct_start_steps`).
    end_learning_rate: warmup_cosine's final value.
    div_factor: one-cycle start = peak / div_factor (torch default 25).
    final_div_factor: one-cycle end = start / final_div_factor (official 1000).
    cycle_momentum: one-cycle only: cycle beta1 between `max_b1` and `base_b1` as torch does.
    base_b1, max_b1: torch `OneCycleLR` momentum bounds (defaults 0.85, 0.95).
    b1, b2, eps: AdamW moments (official betas (0.9, 0.95), torch eps 1e-8).
    weight_decay: decoupled weight decay for matrices (official 0.05).
    no_decay_names: parameter-path component prefixes exempt from weight decay besides every
      1-D parameter (biases, norm scales, LayerScale): the Gaussian token tables (static and
      dynamic) and the latent-bottleneck query table.
    grad_clip_norm: global-norm clip of the (accumulated) gradient; None disables it.
    accumulation_steps: micro-batches averaged per optimiser update.
    ema_decay: keep an exponential moving average of the parameters in the training state
      (`TrainState.ema_params`), updated after every optimiser update (not every micro-batch) as
      `ema = ema_decay * ema + (1 - ema_decay) * params`, starting equal to the initial params;
      0 (default): off, no average kept. Not in the paper or the official code.
  """

  learning_rate: float = 4e-4
  schedule: Literal["warmup_cosine", "one_cycle", "constant"] = "warmup_cosine"
  total_steps: int = 150_000
  warmup_steps: int = 2_000
  end_learning_rate: float = 0.0
  div_factor: float = 25.0
  final_div_factor: float = 1000.0
  cycle_momentum: bool = True
  base_b1: float = 0.85
  max_b1: float = 0.95
  b1: float = 0.9
  b2: float = 0.95
  eps: float = 1e-8
  weight_decay: float = 0.05
  no_decay_names: tuple[str, ...] = ("gs_tokens", "latents")
  grad_clip_norm: float | None = 1.0
  accumulation_steps: int = 1
  ema_decay: float = 0.0

  def __post_init__(self):
    if not 0.0 <= self.ema_decay < 1.0:  # also refuses NaN
      raise ValueError(f"ema_decay must be in [0, 1), got {self.ema_decay}")


def _cosine_anneal(start, end, fraction):
  """torch's `_annealing_cos`: start at fraction 0, end at fraction 1."""
  return end + (start - end) / 2.0 * (jnp.cos(math.pi * fraction) + 1.0)


def _one_cycle(step, total_steps, warmup_steps, rise_from, peak, fall_to):
  """Two cosine phases with torch `OneCycleLR`'s step boundaries.

  torch puts the peak at step `pct_start * total - 1` and the end at `total - 1`; steps past the
  end keep following the second phase's cosine, as torch's last phase does.
  """
  pct_start = min(warmup_steps / total_steps, 0.99)
  peak_step = float(pct_start * total_steps) - 1.0
  last_step = float(total_steps - 1)
  step = jnp.asarray(step, jnp.float32)
  rising = _cosine_anneal(rise_from, peak, step / peak_step)
  falling = _cosine_anneal(peak, fall_to, (step - peak_step) / (last_step - peak_step))
  return jnp.where(step <= peak_step, rising, falling)


def learning_rate_schedule(config: OptimConfig) -> optax.Schedule:
  """The learning rate as a function of the optimiser-update count (0 for the first update)."""
  if config.schedule == "constant":
    return optax.constant_schedule(config.learning_rate)
  if config.schedule == "warmup_cosine":
    return optax.warmup_cosine_decay_schedule(
      init_value=0.0,
      peak_value=config.learning_rate,
      warmup_steps=config.warmup_steps,
      decay_steps=config.total_steps,
      end_value=config.end_learning_rate,
    )
  if config.schedule == "one_cycle":
    start = config.learning_rate / config.div_factor
    end = start / config.final_div_factor
    return lambda step: _one_cycle(
      step, config.total_steps, config.warmup_steps, start, config.learning_rate, end
    )
  raise ValueError(f"unknown schedule {config.schedule!r}")


def beta1_schedule(config: OptimConfig) -> optax.Schedule | float:
  """AdamW's beta1: constant, or torch `OneCycleLR`'s inverse cycle (high when lr is low)."""
  if config.schedule == "one_cycle" and config.cycle_momentum:
    return lambda step: _one_cycle(
      step, config.total_steps, config.warmup_steps, config.max_b1, config.base_b1, config.max_b1
    )
  return config.b1


def path_name(path) -> str:
  """A pytree key path as "a/b/c" (dict keys, attribute names, sequence indices)."""
  return "/".join(str(getattr(k, "key", getattr(k, "name", getattr(k, "idx", k)))) for k in path)


def weight_decay_mask(params, no_decay_names: tuple[str, ...] = ("gs_tokens", "latents")):
  """True where AdamW applies weight decay: parameters of rank >= 2 outside the token tables.

  The official code exempts every 1-D parameter (biases, LayerNorm scales and offsets,
  LayerScale gammas); the paper's wording is "except for the bias terms and the Layer
  Normalization layers". Token tables are rank 2 but are embeddings, not weights, so they are
  exempt too (by name: a path component starting with one of `no_decay_names`; the official code
  decays its 2-D `gs_tokens`, see docs/deviations.md).

  Args:
    params: parameter pytree.
    no_decay_names: path-component prefixes that are never decayed.

  Returns:
    A pytree of Python bools with the structure of `params`.
  """

  def decays(path, leaf):
    exempt = any(part.startswith(no_decay_names) for part in path_name(path).split("/"))
    return jnp.ndim(leaf) >= 2 and not exempt

  return jax.tree_util.tree_map_with_path(decays, params)


def make_optimizer(config: OptimConfig) -> optax.GradientTransformation:
  """clip(global norm) -> AdamW(masked decay, scheduled lr/beta1), wrapped for accumulation.

  The learning rate and beta1 are injected hyper-parameters, so their current values live in the
  optimiser state (`current_hyperparams`) and can be logged. With `accumulation_steps > 1`,
  `optax.MultiSteps` averages that many gradients and then runs clip + AdamW once on the mean, as
  torch/accelerate clip the accumulated gradient; the schedule counts optimiser updates.
  """
  adamw = optax.inject_hyperparams(optax.adamw, static_args=("mask",))(
    learning_rate=learning_rate_schedule(config),
    b1=beta1_schedule(config),
    b2=config.b2,
    eps=config.eps,
    weight_decay=config.weight_decay,
    mask=lambda params: weight_decay_mask(params, config.no_decay_names),
  )
  parts = (
    [adamw]
    if config.grad_clip_norm is None
    else [optax.clip_by_global_norm(config.grad_clip_norm), adamw]
  )
  optimizer = optax.chain(*parts)
  if config.accumulation_steps > 1:
    optimizer = optax.MultiSteps(optimizer, every_k_schedule=config.accumulation_steps)
  return optimizer


def current_learning_rate(opt_state) -> jax.Array | None:
  """The learning rate the last update used (read from an injected-hyperparams state)."""

  def has_hyperparams(node):
    return hasattr(node, "hyperparams") and isinstance(node.hyperparams, dict)

  for node in jax.tree_util.tree_leaves(opt_state, is_leaf=has_hyperparams):
    if has_hyperparams(node):
      return node.hyperparams["learning_rate"]
  return None
