"""`render_exact`: renders that are never truncated, by re-rendering outside jit.

`render` sorts (Gaussian, tile) pairs into a buffer of static size; a scene that needs more loses
its farthest Gaussians' tiles and says so in `stats.overflow`. Inside jit nothing can be resized,
so results that are reported or exported come from `render_exact`, which follows the
neighbour-list idiom of jax-md (`did_buffer_overflow`, reallocate outside jit): render, read the
flag on the host, and render again with a buffer that holds every pair the scene needs. The
buffer size is learnt per input shape, so later calls start at it (one render, no recompile).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import numpy as np

from tokengs_jax.gaussians import Gaussians
from tokengs_jax.splatting.config import RenderConfig, RenderResult
from tokengs_jax.splatting.checks import check_cameras
from tokengs_jax.splatting.pipeline import jitted_render

# Largest buffer (pairs per camera) `render_exact` and `tuning.tune` grow to: binning holds a
# few int32 / float32 arrays of this size per camera (~2.5 GiB at 2^26).
BUDGET_LIMIT = 2**26

# (input shapes, height, width, config) -> the largest buffer a scene of these shapes needed.
_learnt_budgets: dict[tuple, int] = {}


class RenderBudgetError(RuntimeError):
  """A scene needs more (Gaussian, tile) pairs than `BUDGET_LIMIT` allows."""


def larger_budget(
  config: RenderConfig, num_gaussians: int, height: int, width: int, needed: int | None = None
) -> RenderConfig:
  """`config` with a buffer for `needed` pairs per camera (None: 4x the current buffer).

  Rounded up to a power of two (few distinct sizes: few compilations), capped at N x tiles,
  which no scene can exceed (every Gaussian in every tile).
  Raises RenderBudgetError beyond `BUDGET_LIMIT`.
  """
  tiles = -(-height // config.tile_size) * -(-width // config.tile_size)
  current = config.intersection_budget(num_gaussians, tiles)
  ceiling = max(1, num_gaussians) * tiles
  if current >= ceiling:
    raise RenderBudgetError(
      f"the buffer ({current} pairs) already holds every Gaussian in every "
      "tile; an overflow beyond it is impossible"
    )
  target = 4 * current if needed is None else max(needed, current + 1)
  budget = min(1 << (int(target) - 1).bit_length(), ceiling)
  if budget > BUDGET_LIMIT:
    raise RenderBudgetError(
      f"an exact render needs {target} (Gaussian, tile) pairs per camera, above "
      f"splatting.exact.BUDGET_LIMIT = {BUDGET_LIMIT}; render fewer or smaller Gaussians, a "
      f"smaller image, or raise the limit if memory allows"
    )
  return dataclasses.replace(config, max_intersections=budget)


def render_exact(
  gaussians: Gaussians,
  world_to_camera,
  intrinsics,
  *,
  height: int,
  width: int,
  config: RenderConfig = RenderConfig(),
  **kwargs,
) -> RenderResult:
  """`render`, re-rendered with a larger buffer until no camera overflowed (call outside jit).

  Same arguments and result as `render` (`kwargs`: background, near, far). The result's
  `stats.overflow` is False everywhere: every pixel is what an unbounded buffer gives (a
  truncation behind saturated pixels, `stats.truncated` without overflow, loses nothing). Not
  differentiable (it reads the flag on the host); training renders inside jit with `render` and
  logs the overflow fraction instead.

  Raises:
    TypeError: called under a jax transformation (jit, grad, vmap).
    ValueError: a camera with a NaN / inf or fx, fy <= 0 (as `render`).
    RenderBudgetError: the scene needs more than `BUDGET_LIMIT` pairs per camera.
  """
  leaves = jax.tree.leaves((gaussians, world_to_camera, intrinsics, kwargs))
  if any(isinstance(leaf, jax.core.Tracer) for leaf in leaves):
    raise TypeError(
      "render_exact reads the overflow flag on the host and cannot run under "
      "jit/grad/vmap; inside a transformation use render and its stats.overflow"
    )
  num = gaussians.num_gaussians
  tiles = -(-height // config.tile_size) * -(-width // config.tile_size)
  key = (
    jax.tree.map(np.shape, gaussians),
    np.shape(world_to_camera),
    np.shape(intrinsics),
    height,
    width,
    config,
  )
  if key in _learnt_budgets and _learnt_budgets[key] > config.intersection_budget(num, tiles):
    config_now = dataclasses.replace(config, max_intersections=_learnt_budgets[key])
  else:
    config_now = config
  run = functools.partial(
    jitted_render, gaussians, world_to_camera, intrinsics, height=height, width=width, **kwargs
  )
  out = run(config=config_now)
  check_cameras(world_to_camera, intrinsics)  # after the trace has checked their shapes
  while np.any(np.asarray(out.stats.overflow)):
    # overflow implies a cut, so the count exceeds the buffer: the next render holds it all
    needed = int(np.max(np.asarray(out.stats.num_intersections, np.int64)))
    config_now = larger_budget(config_now, num, height, width, needed)
    _learnt_budgets[key] = config_now.max_intersections
    out = run(config=config_now)
  return out
