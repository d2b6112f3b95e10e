"""`splatting.reference.render_dense`, the dense renderer the tiled one is checked against: its
pixels on scenes of one or two Gaussians, computed by hand from gsplat's per-pixel rule."""

import math

import jax.numpy as jnp
import numpy as np

from tokengs_jax.gaussians import Gaussians
from tokengs_jax.splatting.config import RenderConfig
from tokengs_jax.splatting.reference import render_dense

# A 5x5 image seen by an identity camera; the optical axis hits the centre of pixel (2, 2).
SIZE = 5
W2C = np.eye(4, dtype=np.float32)
INTR = np.array([10.0, 10.0, 2.5, 2.5], np.float32)
BACKGROUND = np.array([0.1, 0.2, 0.3], np.float32)
RED, BLUE = [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]


def _scene(depths, opacities, colors, scale=0.1):
  """Isotropic Gaussians on the optical axis at `depths`."""
  n = len(depths)
  return Gaussians(
    means=jnp.array([[0.0, 0.0, z] for z in depths], jnp.float32),
    opacities=jnp.array(opacities, jnp.float32),
    scales=jnp.full((n, 3), scale, jnp.float32),
    quats=jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0], jnp.float32), (n, 1)),
    colors=jnp.array(colors, jnp.float32),
  )


def _render(g, **kwargs):
  rgb, alpha, depth = render_dense(
    g, W2C, INTR, height=SIZE, width=SIZE, background=BACKGROUND, **kwargs
  )
  return np.asarray(rgb), np.asarray(alpha[..., 0]), np.asarray(depth[..., 0])


def test_one_gaussian_at_a_pixel_centre_and_its_neighbours():
  rgb, alpha, depth = _render(_scene([2.0], [0.5], [RED]))
  # screen variance (fx s / z)^2 + eps2d = 0.25 + 0.3; alpha = o exp(-sigma) with
  # sigma = (dx^2 + dy^2) / (2 var)
  var = (10.0 * 0.1 / 2.0) ** 2 + RenderConfig().eps2d
  for (row, col), expected in {
    (2, 2): 0.5,
    (2, 3): 0.5 * math.exp(-0.5 / var),
    (1, 2): 0.5 * math.exp(-0.5 / var),
    (3, 1): 0.5 * math.exp(-1.0 / var),
  }.items():
    np.testing.assert_allclose(alpha[row, col], expected, rtol=1e-5)
    np.testing.assert_allclose(
      rgb[row, col], expected * np.array(RED) + (1 - expected) * BACKGROUND, rtol=1e-5
    )
    np.testing.assert_allclose(depth[row, col], 2.0, rtol=1e-5)
  # the corner is 2.5 sigma away in each axis: alpha below 1/255, background only
  assert alpha[0, 0] == 0.0 and depth[0, 0] == 0.0
  np.testing.assert_allclose(rgb[0, 0], BACKGROUND, rtol=1e-6)


def test_two_gaussians_composite_front_to_back_whatever_their_order():
  # the far (blue, 0.8) one is listed first: compositing follows depth, not index
  rgb, alpha, depth = _render(_scene([4.0, 2.0], [0.8, 0.5], [BLUE, RED]))
  front, back = 0.5, 0.8
  np.testing.assert_allclose(alpha[2, 2], 1 - (1 - front) * (1 - back), rtol=1e-5)
  expected_rgb = (
    front * np.array(RED)
    + (1 - front) * back * np.array(BLUE)
    + (1 - front) * (1 - back) * BACKGROUND
  )
  np.testing.assert_allclose(rgb[2, 2], expected_rgb, rtol=1e-5)
  np.testing.assert_allclose(depth[2, 2], (front * 2.0 + (1 - front) * back * 4.0) / 0.9, rtol=1e-5)


def test_alpha_is_capped_and_a_pixel_stops_before_saturating():
  # opacity 1 is capped at max_alpha 0.999 (T = 1e-3); the one behind would take T to 1e-6, below
  # transmittance_stop 1e-4, so the pixel stops before it and blue never shows
  rgb, alpha, depth = _render(_scene([2.0, 3.0], [1.0, 1.0], [RED, BLUE]))
  np.testing.assert_allclose(alpha[2, 2], 0.999, rtol=1e-6)
  np.testing.assert_allclose(
    rgb[2, 2], 0.999 * np.array(RED) + 0.001 * BACKGROUND, rtol=1e-5, atol=1e-7
  )
  np.testing.assert_allclose(depth[2, 2], 2.0, rtol=1e-5)


def test_a_gaussian_behind_the_camera_leaves_the_background():
  rgb, alpha, depth = _render(_scene([-2.0], [0.9], [RED]))
  np.testing.assert_array_equal(alpha, 0.0)
  np.testing.assert_array_equal(depth, 0.0)
  np.testing.assert_allclose(rgb, np.broadcast_to(BACKGROUND, (SIZE, SIZE, 3)), rtol=1e-6)
  no_background, _, _ = render_dense(_scene([-2.0], [0.9], [RED]), W2C, INTR, height=3, width=4)
  assert no_background.shape == (3, 4, 3)
  np.testing.assert_array_equal(no_background, 0.0)  # the default background is black
