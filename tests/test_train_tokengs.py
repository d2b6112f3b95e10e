"""The TokenGS objective with the real model and renderer (tiny preset; slow: renderer compiles)."""

import jax
import numpy as np
import pytest

from tokengs_jax.train import (
  LoopConfig,
  ObjectiveConfig,
  OptimConfig,
  make_mesh,
  tokengs_loss_fn,
  train,
)

HEIGHT = WIDTH = 32


def synthetic_batch(batch_size=2, context_views=2, target_views=4, seed=0):
  """Smooth colour ramps seen from cameras stepping along x (learnable, unlike noise)."""
  rng = np.random.default_rng(seed)
  views = context_views + target_views
  ramp = np.linspace(0, 1, WIDTH, dtype=np.float32)
  images = np.empty((batch_size, views, HEIGHT, WIDTH, 3), np.float32)
  for b in range(batch_size):
    colour = rng.uniform(0.2, 0.8, 3).astype(np.float32)
    for v in range(views):
      images[b, v] = colour * (0.5 + 0.5 * np.roll(ramp, 2 * v))[None, :, None]
  c2w = np.tile(np.eye(4, dtype=np.float32), (batch_size, views, 1, 1))
  c2w[:, :, 0, 3] = np.linspace(-0.1, 0.1, views)
  intrinsics = np.tile(np.array([32, 32, 16, 16], np.float32), (batch_size, views, 1))
  split = lambda x: (x[:, :context_views], x[:, context_views:])
  batch = {}
  for name, value in (("images", images), ("c2w", c2w), ("intrinsics", intrinsics)):
    batch[f"context_{name}"], batch[f"target_{name}"] = split(value)
  return batch


@pytest.mark.slow
def test_chunked_objective_matches_one_shot(tiny):
  config, params = tiny
  batch = synthetic_batch(batch_size=1, target_views=2)
  key = jax.random.PRNGKey(0)
  results = []
  for chunk_size in (None, 1):
    loss_fn = tokengs_loss_fn(config, objective=ObjectiveConfig(view_chunk_size=chunk_size))
    results.append(jax.jit(jax.value_and_grad(loss_fn, has_aux=True))(params, batch, key, 0))
  ((loss, terms), grads), ((chunked_loss, chunked_terms), chunked_grads) = results
  np.testing.assert_allclose(chunked_loss, loss, rtol=1e-5)
  for name in ("rgb", "ssim", "visibility", "psnr"):
    np.testing.assert_allclose(chunked_terms[name], terms[name], rtol=1e-5, atol=1e-7)
  scale = max(float(np.max(np.abs(g))) for g in jax.tree.leaves(grads))
  jax.tree.map(
    lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-5 * scale),
    chunked_grads,
    grads,
  )


@pytest.mark.slow
def test_input_mean_objective_uses_each_examples_own_inputs(tiny):
  """The loss of two examples with different inputs is the mean of each one's loss over the fixed
  RGB of its own inputs' mean colour (the inputs', not the targets')."""
  config, params = tiny
  batch = synthetic_batch(batch_size=2, target_views=1)
  batch["target_images"] = 1.0 - batch["target_images"]  # mean colours unlike the inputs'
  key = jax.random.PRNGKey(0)
  input_mean = tokengs_loss_fn(config, objective=ObjectiveConfig(background="input_mean"))
  alone = []
  for b in range(2):
    one = {name: value[b : b + 1] for name, value in batch.items()}
    mean = tuple(float(c) for c in one["context_images"].mean(axis=(0, 1, 2, 3)))
    loss_fn = tokengs_loss_fn(config, objective=ObjectiveConfig(background=mean))
    alone.append(float(loss_fn(params, one, key, 0)[0]))
  np.testing.assert_allclose(input_mean(params, batch, key, 0)[0], np.mean(alone), rtol=1e-5)


@pytest.mark.slow
def test_tiny_training_loss_falls(tiny):
  config, params = tiny
  batch = synthetic_batch()

  def batches():
    while True:
      yield batch

  history = []
  # two scenes on a 2-device data mesh: the real model and renderer under sharding
  train(
    tokengs_loss_fn(config),
    params,
    batches(),
    OptimConfig(learning_rate=1e-2, schedule="warmup_cosine", total_steps=30, warmup_steps=3),
    LoopConfig(total_steps=30, log_every=5),
    mesh=make_mesh(devices=jax.devices()[:2]),
    log_fn=lambda step, m: history.append(m),
  )
  print("loss every 5 steps:", [round(m["loss"], 4) for m in history])
  assert history[-1]["loss"] < 0.8 * history[0]["loss"]
