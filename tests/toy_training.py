"""A toy regression model that the training tests share (imported by them; no tests here): its
parameters (with a `gs_tokens` table), a noisy and a noiseless loss, batches, and a few sharded
steps of it."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from tokengs_jax.train import (
  Precision,
  create_train_state,
  make_optimizer,
  make_train_step,
  shard_batch,
)


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
