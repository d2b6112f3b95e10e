"""The optimiser (`train.optim`) on a toy regression model: schedules, the weight-decay mask,
gradient accumulation."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from toy_training import noiseless_loss, run_steps, toy_batch, toy_params

from tokengs_jax.train import OptimConfig, learning_rate_schedule, make_mesh, make_optimizer
from tokengs_jax.train.optim import beta1_schedule, weight_decay_mask


def test_warmup_cosine_key_steps():
  config = OptimConfig(
    learning_rate=4e-4, schedule="warmup_cosine", total_steps=1000, warmup_steps=100
  )
  lr = learning_rate_schedule(config)
  np.testing.assert_allclose(
    [lr(0), lr(50), lr(100), lr(550), lr(1000)], [0.0, 2e-4, 4e-4, 2e-4, 0.0], atol=1e-9
  )


def test_one_cycle_matches_torch_formula():
  """torch OneCycleLR(cos): peak at step pct*T-1, end at T-1, initial peak/25, final /1000."""
  total, warmup, peak = 1000, 100, 4e-4
  config = OptimConfig(
    learning_rate=peak, schedule="one_cycle", total_steps=total, warmup_steps=warmup
  )
  lr, b1 = learning_rate_schedule(config), beta1_schedule(config)
  start, end = peak / 25, peak / 25 / 1000

  def cos(a, b, t):
    return b + (a - b) / 2 * (math.cos(math.pi * t) + 1)

  for step in (0, 37, 99, 100, 500, 999):
    if step <= warmup - 1:
      want, want_b1 = cos(start, peak, step / (warmup - 1)), cos(0.95, 0.85, step / (warmup - 1))
    else:
      t = (step - (warmup - 1)) / (total - 1 - (warmup - 1))
      want, want_b1 = cos(peak, end, t), cos(0.85, 0.95, t)
    np.testing.assert_allclose(lr(step), want, rtol=1e-5)
    np.testing.assert_allclose(b1(step), want_b1, rtol=1e-6)
  np.testing.assert_allclose([lr(99), lr(999)], [peak, end], rtol=1e-5)


def test_weight_decay_mask_and_effect():
  params = toy_params()
  mask = weight_decay_mask(params)
  assert mask == {
    "dense1": {"kernel": True, "bias": False},
    "dense2": {"kernel": True, "bias": False},
    "gs_tokens": False,
  }
  # prefixes of path components: dynamic tokens and latent queries exempt, latent projections not
  names = {
    "gs_tokens_dynamic": jnp.ones((2, 2)),
    "latents": jnp.ones((2, 2)),
    "latent_kv_proj": {"kernel": jnp.ones((2, 2))},
  }
  assert weight_decay_mask(names) == {
    "gs_tokens_dynamic": False,
    "latents": False,
    "latent_kv_proj": {"kernel": True},
  }
  config = OptimConfig(learning_rate=0.1, schedule="constant", weight_decay=0.5)
  optimizer = make_optimizer(config)
  zero_grads = jax.tree.map(jnp.zeros_like, params)
  updates, _ = optimizer.update(zero_grads, optimizer.init(params), params)
  # zero gradient: Adam's direction is 0, only decoupled decay -lr*wd*w remains
  np.testing.assert_allclose(
    updates["dense1"]["kernel"], -0.05 * params["dense1"]["kernel"], rtol=1e-6
  )
  assert not np.any(updates["gs_tokens"]) and not np.any(updates["dense2"]["bias"])


def test_accumulation_equals_full_batch():
  """Two accumulated half batches make the same update as one step on the full batch."""
  full = toy_batch(0, 8)
  halves = [jax.tree.map(lambda v: v[:4], full), jax.tree.map(lambda v: v[4:], full)]
  mesh = make_mesh(devices=jax.devices()[:1])
  base = {"learning_rate": 1e-2, "schedule": "constant"}
  state_full, _ = run_steps(mesh, OptimConfig(**base), [full], loss_fn=noiseless_loss)
  state_acc, _ = run_steps(
    mesh, OptimConfig(**base, accumulation_steps=2), halves, loss_fn=noiseless_loss
  )
  jax.tree.map(
    lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7),
    jax.device_get(state_full.params),
    jax.device_get(state_acc.params),
  )
  assert not np.allclose(state_full.params["dense1"]["kernel"], toy_params()["dense1"]["kernel"])


def test_the_average_decay_is_off_by_default_and_outside_0_to_1_refused():
  assert OptimConfig().ema_decay == 0.0
  assert OptimConfig(ema_decay=0.999).ema_decay == 0.999
  for bad in (-0.1, 1.0, 1.5, float("nan")):
    with pytest.raises(ValueError, match="ema_decay must be in"):
      OptimConfig(ema_decay=bad)
