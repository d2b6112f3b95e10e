"""The sharded training step (`train.step`) on a toy regression model: one vs four devices, the
loss's arguments, non-finite gradients skipped, bfloat16 compute, the parameters' moving average."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P
from toy_training import noiseless_loss, run_steps, toy_batch, toy_params

from tokengs_jax.train import (
  OptimConfig,
  Precision,
  create_train_state,
  make_mesh,
  make_optimizer,
  make_train_step,
  shard_batch,
)


def test_one_vs_four_devices_equal():
  assert jax.device_count() == 4
  batches = [toy_batch(i) for i in range(3)]
  config = OptimConfig(learning_rate=1e-2, schedule="constant")
  state1, metrics1 = run_steps(make_mesh(devices=jax.devices()[:1]), config, batches)
  state4, metrics4 = run_steps(make_mesh(), config, batches)
  assert state4.params["dense1"]["kernel"].sharding.mesh.shape["data"] == 4
  for m1, m4 in zip(metrics1, metrics4):
    np.testing.assert_allclose(m4["loss"], m1["loss"], rtol=1e-6)
  jax.tree.map(
    lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7),
    jax.device_get(state1.params),
    jax.device_get(state4.params),
  )
  assert int(state4.step) == 3


def test_loss_receives_the_step_and_the_batch_unchanged():
  """The step reaches the loss as its own argument; the batch carries only the data."""
  seen = []

  def loss_fn(params, batch, key, step):
    seen.append(sorted(batch))
    loss, aux = noiseless_loss(params, batch, key, step)
    return loss, {**aux, "step_seen": step.astype(jnp.float32)}

  mesh = make_mesh(devices=jax.devices()[:1])
  _, metrics = run_steps(
    mesh,
    OptimConfig(learning_rate=1e-2, schedule="constant"),
    [toy_batch(0), toy_batch(1), toy_batch(2)],
    loss_fn=loss_fn,
  )
  assert [float(m["step_seen"]) for m in metrics] == [0.0, 1.0, 2.0]
  assert seen[0] == ["x", "y"]


@jax.custom_vjp
def _scale_gradient(x, factor):
  return x


_scale_gradient.defvjp(lambda x, factor: (x, factor), lambda factor, g: (g * factor, 0.0 * factor))


@pytest.mark.parametrize("poison", [np.nan, np.inf, 1e30])
def test_a_step_with_a_non_finite_gradient_changes_nothing(poison):
  """A NaN or an infinity in one gradient leaf, or a finite gradient whose norm overflows
  float32, skips the update (the loss itself stays finite): the state comes back unchanged and
  `finite` is False. The next good step updates as usual."""

  def loss_fn(params, batch, key, step):
    factor = jnp.where(batch["poison"][0], poison, 1.0).astype(jnp.float32)
    dense2 = {**params["dense2"], "bias": _scale_gradient(params["dense2"]["bias"], factor)}
    return noiseless_loss({**params, "dense2": dense2}, batch, key, step)

  mesh = make_mesh(devices=jax.devices()[:1])
  optimizer = make_optimizer(OptimConfig(learning_rate=1e-2, schedule="constant"))
  state = jax.jit(
    lambda p: create_train_state(p, optimizer, 0), out_shardings=NamedSharding(mesh, P())
  )(toy_params())
  before = jax.device_get(state)
  step = make_train_step(loss_fn, optimizer, mesh, donate=False)
  key = jax.random.PRNGKey(7)

  bad = {**toy_batch(0), "poison": np.ones(8, bool)}
  after_bad, metrics = step(state, shard_batch(bad, mesh), key)
  assert np.isfinite(metrics["loss"]) and not bool(metrics["finite"])
  unchanged = jax.tree.map(np.array_equal, jax.device_get(after_bad), before)
  assert all(jax.tree.leaves(unchanged)), unchanged

  good = {**toy_batch(0), "poison": np.zeros(8, bool)}
  after_good, metrics = step(after_bad, shard_batch(good, mesh), key)
  assert bool(metrics["finite"]) and int(after_good.step) == 1
  assert not np.array_equal(
    after_good.params["dense1"]["kernel"], before.params["dense1"]["kernel"]
  )


def test_bf16_compute_keeps_float32_state():
  mesh = make_mesh(devices=jax.devices()[:1])
  state, metrics = run_steps(
    mesh,
    OptimConfig(learning_rate=1e-2, schedule="constant"),
    [toy_batch(0)],
    precision=Precision(jnp.bfloat16),
  )
  assert all(leaf.dtype == jnp.float32 for leaf in jax.tree.leaves(state.params))
  _, metrics32 = run_steps(
    mesh, OptimConfig(learning_rate=1e-2, schedule="constant"), [toy_batch(0)]
  )
  # bf16 has an 8-bit mantissa: same loss to ~1%, not bit-equal
  np.testing.assert_allclose(metrics[0]["loss"], metrics32[0]["loss"], rtol=2e-2)
  assert metrics[0]["loss"] != metrics32[0]["loss"]


def _steps_keeping_an_average(config, batches, mesh):
  """The toy's steps with `config.ema_decay`: (final state, the params before and after each)."""
  optimizer = make_optimizer(config)
  state = jax.jit(
    lambda p: create_train_state(p, optimizer, 0, config.ema_decay),
    out_shardings=NamedSharding(mesh, P()),
  )(toy_params())
  step = make_train_step(noiseless_loss, optimizer, mesh, ema_decay=config.ema_decay)
  seen = [jax.device_get(state.params)]
  for batch in batches:
    state, _ = step(state, shard_batch(batch, mesh), jax.random.PRNGKey(7))
    seen.append(jax.device_get(state.params))
  return state, seen


@pytest.mark.parametrize("accumulation", [1, 2])
def test_the_parameter_average_is_the_hand_computed_one_over_the_optimiser_updates(accumulation):
  """`ema = d * ema + (1 - d) * params` after each optimiser update (with accumulation, not after
  the micro-steps between two), starting from the initial params; sharded as the params."""
  decay = 0.8
  config = OptimConfig(
    learning_rate=5e-2, schedule="constant", ema_decay=decay, accumulation_steps=accumulation
  )
  state, seen = _steps_keeping_an_average(config, [toy_batch(i) for i in range(4)], make_mesh())
  expected = seen[0]
  for params in seen[accumulation::accumulation]:  # the params after each optimiser update
    expected = jax.tree.map(lambda ema, new: decay * ema + (1 - decay) * new, expected, params)
  jax.tree.map(
    lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7),
    jax.device_get(state.ema_params),
    expected,
  )
  kernel = np.asarray(state.ema_params["dense1"]["kernel"])
  assert not np.allclose(kernel, seen[-1]["dense1"]["kernel"])  # an average, not the params
  assert not np.allclose(kernel, seen[0]["dense1"]["kernel"])
  for ema, param in zip(jax.tree.leaves(state.ema_params), jax.tree.leaves(state.params)):
    assert ema.sharding == param.sharding and ema.dtype == param.dtype


def test_without_a_decay_the_state_keeps_no_average():
  config = OptimConfig(learning_rate=5e-2, schedule="constant")
  state, _ = _steps_keeping_an_average(config, [toy_batch(0)], make_mesh())
  assert state.ema_params is None
  with_average = dataclasses.replace(config, ema_decay=0.5)
  kept, _ = _steps_keeping_an_average(with_average, [toy_batch(0)], make_mesh())
  assert len(jax.tree.leaves(kept)) == len(jax.tree.leaves(state)) + len(
    jax.tree.leaves(state.params)
  )
