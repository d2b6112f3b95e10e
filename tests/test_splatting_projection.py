"""Projection (`splatting.projection`): the projected means carry the camera's gradient."""

import jax
import jax.numpy as jnp
import numpy as np
from render_scenes import HEIGHT, INTR, W2C, WIDTH, random_scene

from tokengs_jax.gaussians import Gaussians
from tokengs_jax.splatting import render


def test_means2d_carry_gradient_for_visibility_losses():
  g = random_scene(12, num=16)
  grad = jax.grad(
    lambda m: jnp.sum(
      render(
        Gaussians(m, g.opacities, g.scales, g.quats, g.colors),
        W2C[None],
        INTR[None],
        height=HEIGHT,
        width=WIDTH,
      ).means2d[0, :, 0]
    )
  )(g.means)
  # d u / d x = fx / z for a camera looking down +z.
  z = g.means[:, 2] + 3.0
  np.testing.assert_allclose(grad[:, 0], INTR[0] / z, rtol=1e-5)
