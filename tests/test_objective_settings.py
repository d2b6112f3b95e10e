"""The objective's settings: the input-mean background behind its renders, its eps2d, checks."""

import jax.numpy as jnp
import numpy as np
import pytest
from scenes import scene_of_two_examples

from tokengs_jax import splatting
from tokengs_jax.objective import ObjectiveConfig, render_views


def test_input_mean_background_is_composited_behind_the_render():
  gaussians, context = scene_of_two_examples()
  w2c = jnp.tile(jnp.eye(4), (2, 2, 1, 1)).at[:, 1, 0, 3].set(0.3)
  intrinsics = jnp.tile(jnp.array([16.0, 16.0, 8.0, 8.0]), (2, 2, 1))
  args = (gaussians, w2c, intrinsics, 16, 16, splatting.RenderConfig())
  composited = render_views(*args, ObjectiveConfig(background="input_mean"), context)
  black = render_views(*args, ObjectiveConfig(background=(0.0, 0.0, 0.0)))
  uncovered = 1.0 - black.alpha
  assert 0.2 < float(jnp.mean(uncovered)) < 0.8  # the background shows, but not everywhere
  mean = jnp.mean(context, axis=(1, 2, 3))[:, None, None, None]  # each example's own
  np.testing.assert_allclose(composited.rgb, black.rgb + uncovered * mean, atol=1e-6)
  with pytest.raises(ValueError, match="context images"):
    render_views(*args, ObjectiveConfig(background="input_mean"))
  with pytest.raises(ValueError, match="background"):
    ObjectiveConfig(background="grey")


def test_the_objectives_eps2d_replaces_the_render_configs():
  """Training, tuning and evaluation render with the filter the objective names, whatever the
  RenderConfig they are handed says; an eps2d of its own changes the render."""
  gaussians, _ = scene_of_two_examples()
  w2c = jnp.tile(jnp.eye(4), (2, 2, 1, 1)).at[:, 1, 0, 3].set(0.3)
  intrinsics = jnp.tile(jnp.array([16.0, 16.0, 8.0, 8.0]), (2, 2, 1))
  args = (gaussians, w2c, intrinsics, 16, 16)
  sharp = render_views(*args, splatting.RenderConfig(eps2d=0.3), ObjectiveConfig(eps2d=0.1))
  direct = splatting.render(
    *args[:3],
    height=16,
    width=16,
    background=jnp.full(3, 0.5),
    config=splatting.RenderConfig(eps2d=0.1),
  )
  np.testing.assert_array_equal(sharp.rgb, direct.rgb)
  default = render_views(*args, splatting.RenderConfig(eps2d=0.1), ObjectiveConfig())
  assert float(jnp.max(jnp.abs(default.rgb - sharp.rgb))) > 1e-3
  with pytest.raises(ValueError, match="eps2d"):
    ObjectiveConfig(eps2d=-0.1)
