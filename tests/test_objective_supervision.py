"""Supervision of renders: the depth term, and the mean over view chunks (the gradient of the
one-shot mean, the memory of one chunk)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scenes import gaussians_in_front
from toy_training import toy_params

from tokengs_jax import losses, splatting
from tokengs_jax.gaussians import Gaussians
from tokengs_jax.objective import ObjectiveConfig, mean_over_view_chunks, supervision_loss


def test_supervision_adds_the_depth_term_only_with_depths_and_a_weight():
  key = jax.random.split(jax.random.key(0), 2)
  gaussians = gaussians_in_front(*key, (1, 64), spread=0.5, opacity=0.9, scale=0.2)
  means = gaussians.means
  images = jnp.full((1, 1, 16, 16, 3), 0.5)
  w2c = jnp.eye(4)[None, None]
  intrinsics = jnp.array([[[16.0, 16.0, 8.0, 8.0]]])
  depths = jnp.full((1, 1, 16, 16), 4.0)  # twice as far as the Gaussians
  args = (gaussians, images, w2c, intrinsics)
  render = splatting.RenderConfig()
  plain, plain_terms = supervision_loss(*args, losses.LossConfig(), render)
  weighted = losses.LossConfig(lambda_depth=0.5)
  assert "depth" not in supervision_loss(*args, weighted, render)[1]  # no depths: no term
  loss, terms = supervision_loss(*args, weighted, render, depths=depths)
  assert 0.2 < float(terms["depth"]) < 0.6  # about half the covered pixels' depth is off
  np.testing.assert_allclose(loss, plain + 0.5 * terms["depth"], rtol=1e-5)
  assert "depth" not in supervision_loss(*args, losses.LossConfig(), render, depths=depths)[1]

  def depth_of(means):
    g = Gaussians(means, gaussians.opacities, gaussians.scales, gaussians.quats, gaussians.colors)
    return supervision_loss(g, images, w2c, intrinsics, weighted, render, depths=depths)[1]["depth"]

  # The term pulls the Gaussians back towards the true depth (+z).
  assert float(jax.grad(depth_of)(means)[..., 2].sum()) < 0


def test_coverage_term_charges_the_uncovered_share_and_grows_opacity():
  key = jax.random.split(jax.random.key(1), 2)
  gaussians = gaussians_in_front(*key, (1, 16), spread=0.5, opacity=0.3, scale=0.05)
  images = jnp.full((1, 1, 16, 16, 3), 0.5)
  w2c = jnp.eye(4)[None, None]
  intrinsics = jnp.array([[[16.0, 16.0, 8.0, 8.0]]])
  render = splatting.RenderConfig()
  weighted = losses.LossConfig(lambda_coverage=2.0)
  plain, plain_terms = supervision_loss(
    gaussians, images, w2c, intrinsics, losses.LossConfig(), render
  )
  assert "coverage" not in plain_terms
  loss, terms = supervision_loss(gaussians, images, w2c, intrinsics, weighted, render)
  alpha = splatting.render(gaussians, w2c, intrinsics, height=16, width=16).alpha
  np.testing.assert_allclose(terms["coverage"], 1.0 - jnp.mean(alpha), rtol=1e-5)
  assert 0.3 < float(terms["coverage"]) < 1.0  # 16 small faint Gaussians leave most of it bare
  np.testing.assert_allclose(loss, plain + 2.0 * terms["coverage"], rtol=1e-5)

  def coverage_of(opacities):
    g = Gaussians(gaussians.means, opacities, gaussians.scales, gaussians.quats, gaussians.colors)
    return supervision_loss(g, images, w2c, intrinsics, weighted, render)[1]["coverage"]

  # more opaque Gaussians leave less uncovered: every visible one's gradient is negative
  grad = jax.grad(coverage_of)(gaussians.opacities)
  assert float(jnp.max(grad)) <= 0 and float(jnp.min(grad)) < 0


def test_supervision_adds_the_mask_term_only_with_a_weight_and_needs_the_masks():
  """Official `lambda_mask`: + weight * mean (alpha - mask)^2 over the views' pixels; no term at
  weight 0 (masks or not), and a ValueError for a weight without masks."""
  key = jax.random.split(jax.random.key(2), 2)
  gaussians = gaussians_in_front(*key, (1, 32), spread=0.5, opacity=0.6, scale=0.1)
  images = jnp.full((1, 2, 16, 16, 3), 0.5)
  w2c = jnp.tile(jnp.eye(4)[None, None], (1, 2, 1, 1))
  intrinsics = jnp.tile(jnp.array([[[16.0, 16.0, 8.0, 8.0]]]), (1, 2, 1))
  masks = jnp.zeros((1, 2, 16, 16)).at[:, :, 8:].set(1.0)  # the bottom half is foreground
  args = (gaussians, images, w2c, intrinsics)
  render = splatting.RenderConfig()
  plain, plain_terms = supervision_loss(*args, losses.LossConfig(), render, masks=masks)
  assert "mask" not in plain_terms
  weighted = losses.LossConfig(lambda_mask=2.0)
  for chunk in (None, 1):
    objective = ObjectiveConfig(view_chunk_size=chunk)
    loss, terms = supervision_loss(*args, weighted, render, objective, masks=masks)
    alpha = splatting.render(gaussians, w2c, intrinsics, height=16, width=16).alpha
    expected = jnp.mean(jnp.square(alpha[..., 0] - masks))
    np.testing.assert_allclose(terms["mask"], expected, rtol=1e-5)
    assert 0.05 < float(terms["mask"]) < 1.0
    np.testing.assert_allclose(loss, plain + 2.0 * terms["mask"], rtol=1e-5)
  with pytest.raises(ValueError, match="target_masks"):
    supervision_loss(*args, weighted, render)


def toy_render_loss(params, views):
  """A per-view nonlinear 'render' [B, C, 64] of params and a camera vector, MSE to targets."""
  rendered = jnp.tanh(
    jnp.einsum("bvc,cp->bvp", views["camera"], params["dense1"]["kernel"])
    @ params["dense2"]["kernel"][:, :1]
    * jnp.linspace(0, 1, 64)
  )
  loss = jnp.mean((rendered - views["target"]) ** 2)
  return loss, {"rendered_mean": jnp.mean(rendered)}


def test_chunked_views_gradient_equals_one_shot():
  rng = np.random.default_rng(0)
  views = {
    "camera": rng.normal(size=(2, 8, 3)).astype(np.float32),
    "target": rng.normal(size=(2, 8, 64)).astype(np.float32),
  }
  params = toy_params()

  def loss(p, chunk_size):
    return mean_over_view_chunks(lambda v: toy_render_loss(p, v), views, chunk_size)

  (one_shot, aux), grad = jax.value_and_grad(loss, has_aux=True)(params, None)
  for chunk_size in (1, 2, 4):
    (chunked, chunked_aux), chunked_grad = jax.jit(
      jax.value_and_grad(loss, has_aux=True), static_argnums=1
    )(params, chunk_size)
    np.testing.assert_allclose(chunked, one_shot, rtol=1e-6)
    np.testing.assert_allclose(
      chunked_aux["rendered_mean"], aux["rendered_mean"], rtol=1e-5, atol=1e-7
    )
    jax.tree.map(
      lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-8), chunked_grad, grad
    )
  with pytest.raises(ValueError, match="must divide"):
    loss(params, 3)


def test_chunked_views_peak_memory_is_one_chunks():
  """Compiled temp memory of the gradient: chunks of 2 views need far less than 32 views at once."""
  views = {"camera": jnp.ones((1, 32, 3)), "target": jnp.zeros((1, 32, 64))}

  def big_render_loss(p, v):  # [B, C, 64 * 64, 16] intermediates dominate memory
    features = jnp.einsum("bvc,cp->bvp", v["camera"], p["dense1"]["kernel"])[..., None, :]
    field = jnp.tanh(features * jnp.linspace(0, 1, 64 * 64)[:, None]).sum(-1)
    return jnp.mean(field.reshape(*field.shape[:2], 64, 64).mean(-1) - v["target"]) ** 2, {}

  def temp_bytes(chunk_size):
    grad = jax.grad(
      lambda p: mean_over_view_chunks(lambda v: big_render_loss(p, v), views, chunk_size)[0]
    )
    return jax.jit(grad).lower(toy_params()).compile().memory_analysis().temp_size_in_bytes

  assert temp_bytes(2) * 4 < temp_bytes(None)
