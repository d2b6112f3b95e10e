"""Renderer settings and result containers."""

from __future__ import annotations

import dataclasses
import math

import jax


@dataclasses.dataclass(frozen=True)
class RenderConfig:
  """Static renderer knobs (hashable: usable as a static jit argument).

  The defaults reproduce gsplat 1.5.3 `rasterization(packed=False, render_mode="RGB+ED")` as the
  official TokenGS renderer calls it.

  Attributes:
    tile_size: tile edge in pixels.
    eps2d: added to both diagonal entries of every 2D covariance (low-pass filter).
    radius_sigmas: upper bound of the radius in standard deviations (gsplat's 3.33).
    max_alpha: per-Gaussian alpha cap.
    alpha_threshold: a Gaussian is skipped at a pixel whose alpha is below this.
    transmittance_stop: a pixel stops before the Gaussian that would bring T to <= this.
    chunk_size: Gaussians composited per tile per loop step; memory of a step is
      tiles_per_step x tile_size^2 x chunk_size.
    tiles_per_step: tiles composited per loop step, taken from a compacted list of the tiles that
      still have work (finished and empty tiles cost nothing); capped at the number of tiles.
    intersections_per_gaussian: default (Gaussian, tile) budget is this times N (at least
      `min_intersections`); exceeding it drops the farthest Gaussians' tiles and sets
      `stats.truncated`, and `stats.overflow` where that can change a pixel (see RenderStats).
      Binning cost grows with the budget (one sort of B keys). Dense scenes need little: a tile's
      list only has to reach its pixels' saturation (BUILD_NOTES.md has the measurements).
    min_intersections: floor of the default budget (small scenes, few Gaussians, large tiles).
    max_intersections: explicit budget; overrides the two above when set.
  """

  tile_size: int = 16
  eps2d: float = 0.3
  radius_sigmas: float = 3.33
  max_alpha: float = 0.999
  alpha_threshold: float = 1.0 / 255.0
  transmittance_stop: float = 1e-4
  chunk_size: int = 32
  tiles_per_step: int = 32
  intersections_per_gaussian: float = 8.0
  min_intersections: int = 4096
  max_intersections: int | None = None

  def intersection_budget(self, num_gaussians: int) -> int:
    """Static size of the (Gaussian, tile) intersection buffer for N Gaussians (a chunk multiple)."""
    if self.max_intersections is not None:
      budget = self.max_intersections
    else:
      budget = max(self.min_intersections, math.ceil(self.intersections_per_gaussian * num_gaussians))
    return max(self.chunk_size, -(-budget // self.chunk_size) * self.chunk_size)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RenderStats:
  """Per-camera counters (each [..., V] int32, `overflow` bool).

  A Gaussian is counted under the first rule that culls it, in gsplat's order: depth (centre z
  outside [near, far]), degenerate (2D covariance determinant <= 0 or zero radius), opacity
  (< alpha_threshold), frustum (its radius box misses the image). `num_visible` are the rest.
  `num_intersections` is the number of (Gaussian, tile) pairs the scene's radius boxes need;
  `budget` the static buffer size; `truncated` is True when the first exceeded the second (the
  farthest Gaussians lost tiles). `overflow` is True when that could change the image: some
  truncated tile ran out of its (depth-ordered) list before all of its pixels saturated. A
  truncated render without overflow is exact: every cut pair lies behind saturated pixels.
  `tile_chunks` is the number of (tile, chunk) blocks composited (early stop diagnostic).
  """

  num_culled_depth: jax.Array
  num_culled_degenerate: jax.Array
  num_culled_opacity: jax.Array
  num_culled_frustum: jax.Array
  num_visible: jax.Array
  num_intersections: jax.Array
  budget: jax.Array
  truncated: jax.Array
  overflow: jax.Array
  tile_chunks: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RenderResult:
  """What `render` returns.

  Attributes:
    rgb: [..., V, H, W, 3] background-composited colour.
    alpha: [..., V, H, W, 1] accumulated opacity 1 - T.
    depth: [..., V, H, W, 1] expected depth (gsplat "ED": accumulated z / max(alpha, 1e-10)).
    means2d: [..., V, N, 2] projected centres in pixels, differentiable for every Gaussian in front
      of the camera plane (finite, but meaningless, for culled ones).
    radii: [..., V, N, 2] int32 pixel radii, 0 where culled.
    depths: [..., V, N] camera-space z of the centres.
    stats: RenderStats.
  """

  rgb: jax.Array
  alpha: jax.Array
  depth: jax.Array
  means2d: jax.Array
  radii: jax.Array
  depths: jax.Array
  stats: RenderStats
