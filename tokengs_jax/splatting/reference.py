"""Dense all-pairs reference renderer, for tests only (every pixel against every Gaussian).

It shares the projection with `render` but none of the binning or chunked compositing: one
lax.scan walks all visible Gaussians in (depth, index) order and applies gsplat's per-pixel rule
literally (skip, cap, stop, T <- T (1 - alpha)). Memory and time are pixels x Gaussians; keep
scenes small.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from tokengs_jax import camera
from tokengs_jax.gaussians import Gaussians
from tokengs_jax.splatting import projection
from tokengs_jax.splatting.config import RenderConfig


def render_dense(
  gaussians: Gaussians,
  world_to_camera,
  intrinsics,
  *,
  height: int,
  width: int,
  background=None,
  near: float = 0.025,
  far: float = 125.0,
  config: RenderConfig = RenderConfig(),
):
  """One scene [N], one camera (w2c [4, 4], intrinsics [4]) -> (rgb [H, W, 3], alpha, depth [H, W, 1])."""
  dtype = gaussians.means.dtype
  proj = projection.project_gaussians(
    gaussians.means,
    gaussians.quats,
    gaussians.scales,
    gaussians.opacities,
    world_to_camera,
    intrinsics,
    height=height,
    width=width,
    near=near,
    far=far,
    eps2d=config.eps2d,
    radius_sigmas=config.radius_sigmas,
    alpha_threshold=config.alpha_threshold,
  )
  visible = proj.cull_code == projection.VISIBLE
  order = jnp.argsort(jnp.where(visible, proj.depths, jnp.inf), stable=True)
  pixels = camera.pixel_centers(height, width, dtype).reshape(-1, 2)
  features = jnp.concatenate([gaussians.colors, proj.depths[:, None]], axis=-1)

  def step(carry, index):
    transmittance, done, accum = carry
    dx = proj.means2d[index, 0] - pixels[:, 0]
    dy = proj.means2d[index, 1] - pixels[:, 1]
    a, b, c = proj.conics[index, 0], proj.conics[index, 1], proj.conics[index, 2]
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    alpha = jnp.minimum(
      config.max_alpha, gaussians.opacities[index] * jnp.exp(-jnp.maximum(sigma, 0.0))
    )
    evaluated = visible[index] & ~done & (sigma >= 0) & (alpha >= config.alpha_threshold)
    next_t = transmittance * (1.0 - alpha)
    stop = evaluated & (next_t <= config.transmittance_stop)
    composite = evaluated & ~stop
    accum = accum + jnp.where(composite, alpha * transmittance, 0.0)[:, None] * features[index]
    return (jnp.where(composite, next_t, transmittance), done | stop, accum), None

  init = (
    jnp.ones(height * width, dtype),
    jnp.zeros(height * width, bool),
    jnp.zeros((height * width, 4), dtype),
  )
  (transmittance, _, accum), _ = jax.lax.scan(step, init, order)
  background = jnp.zeros(3, dtype) if background is None else jnp.asarray(background, dtype)
  alpha = (1.0 - transmittance)[:, None]
  rgb = accum[:, :3] + transmittance[:, None] * background
  depth = accum[:, 3:] / jnp.maximum(alpha, 1e-10)
  shape = (height, width)
  return rgb.reshape(shape + (3,)), alpha.reshape(shape + (1,)), depth.reshape(shape + (1,))
