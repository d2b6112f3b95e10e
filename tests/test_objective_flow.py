"""Tests for tokengs_jax.objective.flow: the scene-flow term and its place in the dynamic loss."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scenes import DYNAMIC_CONFIG, DYNAMIC_SIZE, dynamic_batch, dynamic_params

from tokengs_jax import losses, splatting
from tokengs_jax.gaussians import Gaussians
from tokengs_jax.objective import ObjectiveConfig, supervised_views, tokengs_loss_fn
from tokengs_jax.objective.flow import FLOW_TIME_STEP, flow_loss, velocities

SIZE = 16


def _scene(num=24, seed=0):
  """Gaussians [1, 1, N] in front of an identity camera, their velocities [1, 1, N, 3]."""
  rng = np.random.default_rng(seed)
  means = np.concatenate([rng.uniform(-1, 1, (num, 2)), rng.uniform(2, 4, (num, 1))], -1)
  gaussians = Gaussians(
    means=jnp.asarray(means[None, None], jnp.float32),
    opacities=jnp.full((1, 1, num), 0.8),
    scales=jnp.asarray(rng.uniform(0.1, 0.4, (1, 1, num, 3)), jnp.float32),
    quats=jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (1, 1, num, 1)),
    colors=jnp.full((1, 1, num, 3), 0.5),
  )
  velocity = jnp.asarray(rng.normal(size=(1, 1, num, 3)), jnp.float32)
  cameras = jnp.eye(4)[None, None], jnp.array([[[SIZE, SIZE, SIZE / 2, SIZE / 2]]], jnp.float32)
  return gaussians, velocity, cameras


def test_flow_loss_vanishes_at_the_rendered_velocity_and_trains_only_the_velocity():
  """Flows equal to the Gaussians' rendered velocity over their alpha (on the pixels they cover
  well; 0, i.e. still, elsewhere) give a zero loss; still Gaussians give the mean absolute alpha x
  flow over the moving pixels; only the velocities get a gradient."""
  gaussians, velocity, (world_to_camera, intrinsics) = _scene()
  config, objective = splatting.RenderConfig(), ObjectiveConfig()
  seen = splatting.render(
    dataclasses.replace(gaussians, colors=velocity),
    world_to_camera[:, :, None],
    intrinsics[:, :, None],
    height=SIZE,
    width=SIZE,
  )
  alpha = seen.alpha[:, :, 0]
  covered = alpha > 0.5
  flows = jnp.where(covered, seen.rgb[:, :, 0] / jnp.maximum(alpha, 0.5), 0.0)
  assert 0.2 < float(jnp.mean(covered)) < 1.0  # moving and still pixels both

  def loss(gaussians, velocity):
    return flow_loss(gaussians, velocity, flows, world_to_camera, intrinsics, config, objective)

  assert float(loss(gaussians, velocity)) < 1e-6
  moving = jnp.broadcast_to(covered, flows.shape)
  still_error = jnp.sum(jnp.abs(alpha * flows) * moving) / jnp.sum(moving)
  np.testing.assert_allclose(loss(gaussians, 0 * velocity), still_error, rtol=1e-5)
  grads = jax.grad(loss, argnums=(0, 1))(gaussians, 0 * velocity)
  for field in jax.tree.leaves(grads[0]):
    assert not np.any(np.asarray(field))  # geometry and opacity are constants here
  assert np.any(np.asarray(grads[1]))


def test_velocities_are_the_centres_difference_quotient():
  gaussians, velocity, _ = _scene()
  later = gaussians.means + FLOW_TIME_STEP * velocity
  np.testing.assert_allclose(velocities(gaussians, later), velocity, rtol=1e-4, atol=1e-4)


# "first" is slow: "per_view" decodes at every view's time, the harder case of the same sum
@pytest.mark.parametrize(
  "decode_times", [pytest.param("first", marks=pytest.mark.slow), "per_view"]
)
def test_the_dynamic_loss_adds_the_weighted_flow_term(decode_times):
  """`lambda_flow` adds lambda x "flow" to the loss, and a flow map the model's motion cannot
  match gives the term a gradient in the network's parameters; without the weight (or without
  the batch's flows) the term is absent."""
  params = dynamic_params()
  batch = dynamic_batch([[0.0, 1.0]], [[0.3, 0.6]])
  rng = np.random.default_rng(0)
  batch["target_flows"] = rng.normal(size=(1, 2, DYNAMIC_SIZE, DYNAMIC_SIZE, 3)).astype(np.float32)
  objective = ObjectiveConfig(decode_times=decode_times)

  def loss_fn(lambda_flow):
    return tokengs_loss_fn(
      DYNAMIC_CONFIG, losses.LossConfig(lambda_flow=lambda_flow), objective=objective
    )

  base_loss, base_terms = jax.jit(loss_fn(0.0))(params, batch, None, 0)
  assert "flow" not in base_terms
  (loss, terms), grads = jax.jit(jax.value_and_grad(loss_fn(2.0), has_aux=True))(
    params, batch, None, 0
  )
  assert float(terms["flow"]) > 0
  np.testing.assert_allclose(loss, base_loss + 2.0 * terms["flow"], rtol=1e-5)
  (_, _), base_grads = jax.jit(jax.value_and_grad(loss_fn(0.0), has_aux=True))(
    params, batch, None, 0
  )
  differ = jax.tree.map(
    lambda a, b: bool(np.any(np.asarray(a) != np.asarray(b))), grads, base_grads
  )
  assert any(jax.tree.leaves(differ))


def test_input_supervision_refuses_the_targets_flows():
  batch = dynamic_batch([[0.0, 1.0]], [[0.3, 0.6]])
  batch["target_flows"] = np.zeros((1, 2, DYNAMIC_SIZE, DYNAMIC_SIZE, 3), np.float32)
  with pytest.raises(ValueError, match="target_flows"):
    supervised_views(batch, ObjectiveConfig(use_input_supervision=True))


def test_the_flow_term_scores_the_dynamic_gaussians_only():
  """Gaussians whose centres move with time: with every Gaussian static (`num_static_gaussians`
  = N) the flow term renders no velocity and is 0 against zero flows; scored as dynamic (None) it
  is their moving render's error; the static ones are never scored."""
  from tokengs_jax.objective import time_conditioned_loss

  gaussians, velocity, (world_to_camera, intrinsics) = _scene()
  num = gaussians.means.shape[-2]

  def gaussians_at(times, _):
    means = gaussians.means[:, :1] + times[..., None, None] * velocity[:, :1]
    return dataclasses.replace(
      jax.tree.map(
        lambda x: jnp.broadcast_to(x[:, :1], (1, times.shape[1]) + x.shape[2:]), gaussians
      ),
      means=means,
    )

  images = jnp.zeros((1, 1, SIZE, SIZE, 3))
  flows = jnp.full((1, 1, SIZE, SIZE, 3), 0.5)
  config = losses.LossConfig(lambda_flow=1.0)

  def flow_term(num_static):
    _, terms = time_conditioned_loss(
      gaussians_at,
      jnp.array([[0.3]]),
      images,
      world_to_camera,
      intrinsics,
      config,
      splatting.RenderConfig(),
      ObjectiveConfig(decode_times="per_view"),
      num_static_gaussians=num_static,
      flows=flows,
    )
    return float(terms["flow"])

  assert flow_term(num) == 0.0
  assert flow_term(None) > 0.01
