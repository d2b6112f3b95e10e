"""Training the TokenGS objective with the real model and renderer (tiny preset; slow: renderer
compiles)."""

import jax
import pytest
from scenes import synthetic_batch

from tokengs_jax.objective import tokengs_loss_fn
from tokengs_jax.train import LoopConfig, OptimConfig, make_mesh, train


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
