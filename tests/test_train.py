"""Training infrastructure on a toy regression model: schedules, decay mask, sharding,
accumulation, precision, token expansion, Gaussian splitting."""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from tokengs_jax.train import (
  OptimConfig,
  Precision,
  create_train_state,
  dynamic_tokens_from_static,
  expand_tokens,
  learning_rate_schedule,
  make_mesh,
  make_optimizer,
  make_train_step,
  shard_batch,
  split_gaussians,
  transplant_params,
)
from tokengs_jax.train.optim import beta1_schedule, weight_decay_mask


def toy_params(seed=0, num_tokens=4):
  k1, k2, k3 = jax.random.split(jax.random.PRNGKey(seed), 3)
  return {
    "dense1": {"kernel": jax.random.normal(k1, (3, 16)) * 0.5, "bias": jnp.zeros(16)},
    "dense2": {"kernel": jax.random.normal(k2, (16, 2)) * 0.5, "bias": jnp.zeros(2)},
    "gs_tokens": jax.random.normal(k3, (num_tokens, 2)) * 0.1,
  }


def toy_loss(params, batch, key, step, noise=0.01):
  """MLP regression with key-dependent input noise (so the step key matters)."""
  del step
  x = batch["x"] + noise * jax.random.normal(key, batch["x"].shape, batch["x"].dtype)
  hidden = jnp.tanh(
    x.astype(params["dense1"]["kernel"].dtype) @ params["dense1"]["kernel"]
    + params["dense1"]["bias"]
  )
  pred = (
    hidden @ params["dense2"]["kernel"] + params["dense2"]["bias"] + params["gs_tokens"].mean(0)
  )
  loss = jnp.mean((pred.astype(jnp.float32) - batch["y"]) ** 2)
  return loss, {"mse": loss}


noiseless_loss = functools.partial(toy_loss, noise=0.0)


def toy_batch(seed, batch_size=8):
  rng = np.random.default_rng(seed)
  x = rng.normal(size=(batch_size, 3)).astype(np.float32)
  return {"x": x, "y": np.stack([np.sin(x[:, 0]), x[:, 1] * x[:, 2]], -1).astype(np.float32)}


def run_steps(mesh, optim_config, batches, precision=None, loss_fn=toy_loss):
  optimizer = make_optimizer(optim_config)
  state = jax.jit(
    lambda p: create_train_state(p, optimizer, 0), out_shardings=NamedSharding(mesh, P())
  )(toy_params())
  step = make_train_step(loss_fn, optimizer, mesh, precision=precision or Precision())
  key = jax.random.PRNGKey(7)
  metrics = []
  for batch in batches:
    state, m = step(state, shard_batch(batch, mesh), key)
    metrics.append(m)
  return state, jax.device_get(metrics)


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


def test_expand_tokens_statistics():
  tokens = jax.random.normal(jax.random.PRNGKey(0), (256, 32))
  grown = expand_tokens(jax.random.PRNGKey(1), tokens, 1024, noise_std=0.01)
  assert grown.shape == (1024, 32)
  np.testing.assert_array_equal(grown[:256], tokens)
  noise = np.asarray(grown[256:]) - np.tile(np.asarray(tokens), (3, 1))
  assert abs(noise.mean()) < 1e-3 and abs(noise.std() - 0.01) < 5e-4
  shrunk = expand_tokens(jax.random.PRNGKey(1), tokens, 4)
  np.testing.assert_array_equal(shrunk, tokens[np.array([0, 85, 170, 255])])


def test_dynamic_tokens_from_static():
  static = jnp.arange(12.0).reshape(4, 3)
  np.testing.assert_array_equal(
    dynamic_tokens_from_static(jax.random.PRNGKey(0), static, 6),
    static[np.array([0, 1, 2, 3, 0, 1])],
  )
  subset = np.asarray(dynamic_tokens_from_static(jax.random.PRNGKey(0), static, 2))
  assert subset.shape == (2, 3) and len({tuple(r) for r in subset}) == 2
  assert all(any((r == s).all() for s in np.asarray(static)) for r in subset)


def test_transplant_grows_tokens_and_reports():
  pretrained, fresh = toy_params(0, num_tokens=4), toy_params(1, num_tokens=16)
  fresh["dense2"]["kernel"] = jnp.zeros((16, 5))
  params, report = transplant_params(jax.random.PRNGKey(0), pretrained, fresh)
  np.testing.assert_array_equal(params["dense1"]["kernel"], pretrained["dense1"]["kernel"])
  np.testing.assert_array_equal(params["gs_tokens"][:4], pretrained["gs_tokens"])
  assert params["gs_tokens"].shape == (16, 2)
  np.testing.assert_array_equal(params["dense2"]["kernel"], fresh["dense2"]["kernel"])
  assert sorted(report) == [
    "dense2/kernel: kept fresh (shape (16, 2))",
    "gs_tokens: tokens 4 -> 16",
  ]
  fresh["gs_tokens_dynamic"] = jnp.zeros((6, 2))
  params, report = transplant_params(jax.random.PRNGKey(0), pretrained, fresh)
  np.testing.assert_array_equal(
    params["gs_tokens_dynamic"], pretrained["gs_tokens"][np.array([0, 1, 2, 3, 0, 1])]
  )
  assert "gs_tokens_dynamic: from static gs_tokens" in report


def test_split_gaussians_copies_each_parent_and_refuses_non_multiples():
  kernel = jax.random.normal(jax.random.PRNGKey(0), (5, 2 * 3))
  split = np.asarray(split_gaussians(jax.random.PRNGKey(1), kernel, 3, 6, noise_std=0.01))
  parents = np.asarray(kernel).reshape(5, 2, 3)
  children = split.reshape(5, 6, 3)
  np.testing.assert_allclose(children, np.repeat(parents, 3, axis=1), atol=0.01 * 6)
  assert (children[:, 0] != children[:, 1]).any()  # noise parts identical children
  bias = jnp.arange(6.0)
  np.testing.assert_array_equal(
    split_gaussians(jax.random.PRNGKey(1), bias, 3, 4), [0, 1, 2] * 2 + [3, 4, 5] * 2
  )
  with pytest.raises(ValueError, match="cannot split 2"):
    split_gaussians(jax.random.PRNGKey(1), kernel, 3, 5)


def test_transplant_splits_the_head_into_more_gaussians_per_token():
  """A head grown from 4 to 16 Gaussians per token decodes each pretrained Gaussian 4 times."""
  from scenes import MICRO, micro_params

  from tokengs_jax import model

  grown_config = MICRO.replace(dec_patch_size=4)
  fresh = model.init_params(jax.random.key(3), grown_config)
  params, report = transplant_params(jax.random.key(0), micro_params(), fresh, noise_std=0.0)
  assert sorted(r for r in report if "deconv" in r) == [
    "activation_head/deconv/bias: Gaussians per token 4 -> 16 (split)",
    "activation_head/deconv/kernel: Gaussians per token 4 -> 16 (split)",
  ]
  images = jax.random.normal(jax.random.key(4), (1, MICRO.num_input_views, 16, 16, 3))
  plucker = jax.random.normal(jax.random.key(5), (1, MICRO.num_input_views, 16, 16, 6))
  before = model.predict_gaussians(micro_params(), images, plucker, MICRO)
  after = model.predict_gaussians(params, images, plucker, grown_config)
  assert after.shape[1] == 4 * before.shape[1]
  np.testing.assert_allclose(after, np.repeat(np.asarray(before), 4, axis=1), atol=1e-5)
