"""Dynamic (time-conditioned) training: per-time decoding, the time-conditioned loss with the
dynamic auxiliary term, the loop on generated Kubric-like scenes, per-process data states."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tokengs_jax import losses, model, splatting
from tokengs_jax.camera import invert_rigid
from tokengs_jax.train import (
  Checkpointer,
  LoopConfig,
  ObjectiveConfig,
  OptimConfig,
  create_train_state,
  make_mesh,
  make_optimizer,
  supervision_loss,
  tokengs_loss_fn,
  train,
)
from tokengs_jax.train.checkpoint import data_state_file, data_state_handler
from tokengs_jax.train.objective import decode_at_times

HEIGHT = WIDTH = 16
# 4 static + 2 dynamic tokens of 16 Gaussians: 96 Gaussians, cheap to render and compile.
DYNAMIC_CONFIG = model.preset(
  "tiny",
  enc_depth=1,
  dec_depth=1,
  enc_embed_dim=32,
  enc_num_heads=2,
  num_gs_tokens=4,
  num_dynamic_gs_tokens=2,
  dec_patch_size=4,
  time_embedding=True,
  dec_init_values=1.0,
)


def dynamic_params(seed=0):
  """Fresh parameters whose (zero-initialised) time embeddings are made non-zero, so that the
  decoded dynamic Gaussians depend on the time; decoder LayerScale 1 (config) for the same reason."""
  params = model.init_params(jax.random.PRNGKey(seed), DYNAMIC_CONFIG)
  keys = jax.random.split(jax.random.PRNGKey(seed + 1), 2)
  for key, name in zip(keys, ("patch_time_embed", "patch_time_embed_tgt")):
    kernel = params[name]["proj"]["kernel"]
    params[name]["proj"]["kernel"] = 0.5 * jax.random.normal(key, kernel.shape)
  return params


def dynamic_batch(context_times, target_times, seed=0):
  """Random images seen from cameras stepping along x; times [B, Vc] and [B, Vt]."""
  context_times = np.asarray(context_times, np.float32)
  target_times = np.asarray(target_times, np.float32)
  batch_size, num_context = context_times.shape
  views = num_context + target_times.shape[1]
  rng = np.random.default_rng(seed)
  images = rng.random((batch_size, views, HEIGHT, WIDTH, 3)).astype(np.float32)
  c2w = np.tile(np.eye(4, dtype=np.float32), (batch_size, views, 1, 1))
  c2w[:, :, 0, 3] = np.linspace(-0.1, 0.1, views)
  intrinsics = np.tile(np.array([16, 16, 8, 8], np.float32), (batch_size, views, 1))
  batch = {"context_times": context_times, "target_times": target_times}
  for name, value in (("images", images), ("c2w", c2w), ("intrinsics", intrinsics)):
    batch[f"context_{name}"], batch[f"target_{name}"] = (
      value[:, :num_context],
      value[:, num_context:],
    )
  return batch


def test_decode_at_times_equals_reconstruct_at_each_time():
  params = dynamic_params()
  batch = dynamic_batch([[0.0, 1.0], [0.2, 0.9]], [[0.5, 0.0, 1.0], [0.3, 0.6, 0.1]])
  context = (batch["context_images"], batch["context_c2w"], batch["context_intrinsics"])

  @jax.jit
  def decoded(params, images, c2w, intrinsics, times, target_times):
    encoded = model.encode_views(params, images, c2w, intrinsics, DYNAMIC_CONFIG, times=times)
    return decode_at_times(params, encoded, DYNAMIC_CONFIG, target_times)

  reconstruct = jax.jit(
    lambda *args, **kwargs: model.reconstruct(*args, config=DYNAMIC_CONFIG, **kwargs)
  )
  at_times = decoded(params, *context, batch["context_times"], batch["target_times"])
  assert at_times.batch_shape == (2, 3)
  static = DYNAMIC_CONFIG.num_static_gaussians
  for t in range(3):
    expected = reconstruct(
      params, *context, times=batch["context_times"], target_times=batch["target_times"][:, t]
    )
    at_t = jax.tree.map(lambda x, index=t: x[:, index], at_times)
    jax.tree.map(
      lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6), at_t, expected
    )
  # static Gaussians do not depend on the time, dynamic ones do
  means = np.asarray(at_times.means)
  np.testing.assert_allclose(means[:, 1, :static], means[:, 0, :static], rtol=1e-6, atol=1e-7)
  assert np.abs(means[:, 1, static:] - means[:, 0, static:]).max() > 1e-3


def _loss_and_grads(loss_fn, params, batch):
  return jax.jit(jax.value_and_grad(loss_fn, has_aux=True))(params, batch, jax.random.PRNGKey(0), 0)


def _assert_same(result, expected):
  (loss, _), grads = result
  (expected_loss, _), expected_grads = expected
  np.testing.assert_allclose(loss, expected_loss, rtol=1e-5)
  scale = max(float(np.max(np.abs(g))) for g in jax.tree.leaves(expected_grads))
  jax.tree.map(
    lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-5 * scale),
    grads,
    expected_grads,
  )


@pytest.mark.slow
def test_time_conditioned_loss_matches_the_static_path_when_targets_share_a_time():
  """With every target view at one time t, rendering each view from the Gaussians decoded at its
  time (one-shot, chunked with the decoder inside the chunks, or decoding once as official) is
  the static objective on `reconstruct(..., target_times=t)`: same loss, same gradient."""
  params = dynamic_params()
  batch = dynamic_batch([[0.0, 1.0]], [[0.4, 0.4]])
  loss_config = losses.LossConfig()

  def reference(params, batch, key, step):
    del key, step
    gaussians = model.reconstruct(
      params,
      batch["context_images"],
      batch["context_c2w"],
      batch["context_intrinsics"],
      config=DYNAMIC_CONFIG,
      times=batch["context_times"],
      target_times=batch["target_times"][:, 0],
    )
    return supervision_loss(
      gaussians,
      batch["target_images"],
      invert_rigid(batch["target_c2w"]),
      batch["target_intrinsics"],
      loss_config,
      splatting.RenderConfig(),
    )

  expected = _loss_and_grads(reference, params, batch)
  for objective in (
    ObjectiveConfig(),
    ObjectiveConfig(view_chunk_size=1),
    ObjectiveConfig(decode_times="first"),
  ):
    result = _loss_and_grads(
      tokengs_loss_fn(DYNAMIC_CONFIG, loss_config, objective=objective), params, batch
    )
    _assert_same(result, expected)
    for name in ("rgb", "ssim", "visibility"):
      np.testing.assert_allclose(result[0][1][name], expected[0][1][name], rtol=1e-5, atol=1e-7)


@pytest.mark.slow
def test_dynamic_aux_loss_is_the_loss_of_the_dynamic_gaussians_alone_with_its_schedule():
  params = dynamic_params()
  batch = dynamic_batch([[0.0, 1.0]], [[0.4, 0.4]])
  loss_config = losses.LossConfig(
    lambda_dyn_aux=0.3, dyn_aux_hold_steps=2, dyn_aux_decay_steps=4, dyn_aux_min=0.0
  )
  plain = dataclasses.replace(loss_config, lambda_dyn_aux=0.0)
  gaussians = model.reconstruct(
    params,
    batch["context_images"],
    batch["context_c2w"],
    batch["context_intrinsics"],
    config=DYNAMIC_CONFIG,
    times=batch["context_times"],
    target_times=batch["target_times"][:, 0],
  )
  dynamic = jax.tree.map(lambda x: x[:, DYNAMIC_CONFIG.num_static_gaussians :], gaussians)
  views = (batch["target_images"], invert_rigid(batch["target_c2w"]), batch["target_intrinsics"])
  main = float(supervision_loss(gaussians, *views, plain, splatting.RenderConfig())[0])
  dyn = float(supervision_loss(dynamic, *views, plain, splatting.RenderConfig())[0])

  loss_fn = jax.jit(
    tokengs_loss_fn(DYNAMIC_CONFIG, loss_config, objective=ObjectiveConfig(decode_times="first"))
  )
  for step, weight in ((0, 0.3), (2, 0.3), (4, 0.15), (7, 0.0)):
    loss, terms = loss_fn(params, batch, None, step)
    np.testing.assert_allclose(terms["dyn_aux_weight"], weight, rtol=1e-6)
    np.testing.assert_allclose(terms["dyn_aux"], dyn if weight else 0.0, rtol=1e-5)
    np.testing.assert_allclose(loss, main + weight * dyn, rtol=1e-5)


@pytest.fixture(scope="module")
def kubric_batches(tmp_path_factory):
  """One batch of two examples from two generated Kubric-like scenes through the data pipeline."""
  from tokengs_jax.data import kubric
  from tokengs_jax.data.pipeline import DATASET_PRESETS, InputPipeline
  from tokengs_jax.data.synthetic import generate

  root = tmp_path_factory.mktemp("kubric")
  generate.generate_kubric_like(
    root,
    2,
    HEIGHT,
    WIDTH,
    frames=6,
    num_cameras=3,
    seed=1,
    config=generate.KubricLikeConfig(supersample=1),
  )
  example_config = dataclasses.replace(
    DATASET_PRESETS["kubric"], image_shape=(HEIGHT, WIDTH), random_flip=False
  )
  pipeline = InputPipeline(
    kubric.KubricSceneSource(root, num_cameras=3),
    example_config,
    batch_size=2,
    seed=0,
    shuffle=False,
    num_epochs=None,
    shard_index=0,
    shard_count=1,
    select_views=kubric.kubric_view_selector(num_context=2, num_targets=2, min_gap=2, max_gap=5),
  )
  return next(iter(pipeline))


def test_dynamic_training_on_generated_kubric_scenes(kubric_batches):
  batch = kubric_batches
  assert batch["context_times"].shape == batch["target_times"].shape == (2, 2)
  loss_config = losses.LossConfig(
    rgb_loss="l1", lambda_rgb=0.8, lambda_dyn_aux=0.3, dyn_aux_hold_steps=2, dyn_aux_decay_steps=4
  )

  def batches():
    while True:
      yield batch

  history = []
  steps = 30
  # the train step adds "step" to each batch; the auxiliary weight reads it
  train(
    tokengs_loss_fn(DYNAMIC_CONFIG, loss_config, objective=ObjectiveConfig(view_chunk_size=1)),
    dynamic_params(),
    batches(),
    OptimConfig(learning_rate=1e-2, schedule="constant", total_steps=steps),
    LoopConfig(total_steps=steps, log_every=1),
    mesh=make_mesh(devices=jax.devices()[:1]),
    log_fn=lambda step, metrics: history.append(metrics),
  )
  print("rgb per step:", [round(m["rgb"], 4) for m in history])
  assert all(np.isfinite(m["loss"]) and np.isfinite(m["dyn_aux"]) for m in history)
  np.testing.assert_allclose(
    [m["dyn_aux_weight"] for m in history],
    [float(losses.dynamic_aux_weight(s, loss_config)) for s in range(steps)],
    rtol=1e-6,
  )
  # measured: 0.209 -> 0.182 in 30 steps (noisy at first: few, small Gaussians at init)
  assert np.mean([m["rgb"] for m in history[-5:]]) < 0.95 * np.mean([m["rgb"] for m in history[:5]])


def test_data_states_are_saved_and_restored_per_process(tmp_path):
  """Two simulated hosts: each process's iterator position goes to its own file of the step and
  comes back to that process only; another process count is refused with a clear message.

  One real process here: process 0 saves through the Checkpointer, and "process 1" writes its file
  into the same step the way orbax runs the data handler on every host."""
  params = {"w": jnp.arange(3.0)}
  state = create_train_state(params, make_optimizer(OptimConfig(schedule="constant")), seed=0)
  state = state.replace(step=jnp.asarray(4, jnp.int32))
  directory = tmp_path / "run"
  host0 = Checkpointer(directory, process_index=0, process_count=2, async_save=False)
  host0.save(state, {"position": 40})
  host0.wait()
  data_dir = directory / "4" / "data"
  import orbax.checkpoint as ocp

  data_state_handler(1, 2).save(data_dir, args=ocp.args.JsonSave({"iterator": {"position": 41}}))
  assert sorted(p.name for p in data_dir.glob("process_*")) == [
    data_state_file(0, 2),
    data_state_file(1, 2),
  ]
  assert json.loads((data_dir / data_state_file(0, 2)).read_text()) == {
    "iterator": {"position": 40}
  }

  for index, position in ((0, 40), (1, 41)):
    restored, data_state = Checkpointer(directory, process_index=index, process_count=2).restore(
      state
    )
    assert data_state == {"position": position} and int(restored.step) == 4
    np.testing.assert_array_equal(restored.params["w"], params["w"])
  with pytest.raises(FileNotFoundError, match=r"process 0 of 3 .*process_0-of-2\.json"):
    Checkpointer(directory, process_index=0, process_count=3).restore(state)
