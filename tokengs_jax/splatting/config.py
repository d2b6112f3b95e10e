"""Renderer settings and result containers."""

from __future__ import annotations

import dataclasses
import math
import numbers

import jax

# Every matmul / einsum of the renderer asks for full float32: on GPU / TPU the default precision
# may run float32 dots as TF32 / bf16 passes, which is visible at gsplat-parity tolerances.
PRECISION = jax.lax.Precision.HIGHEST


@dataclasses.dataclass(frozen=True)
class RenderConfig:
  """Static renderer knobs (hashable: usable as a static jit argument).

  The defaults reproduce gsplat 1.5.3 `rasterization(packed=False, render_mode="RGB+ED")` as the
  official TokenGS renderer calls it.

  Attributes:
    tile_size: tile edge in pixels: the unit of binning, of the (Gaussian, tile) budget and of
      `stats.num_intersections` (gsplat's tile).
    subtile_size: edge in pixels of the blocks the compositor works on; must divide `tile_size`.
      Each tile's list is split, without a sort, into the lists of its sub-tiles (the Gaussians
      that may reach one of their pixels, see `binning.split_tiles`): the image is the same, and
      small Gaussians cost fewer pixel evaluations. `tile_size` turns the split off.
    eps2d: added to both diagonal entries of every 2D covariance (low-pass filter).
    radius_sigmas: upper bound of the radius in standard deviations (gsplat's 3.33).
    max_alpha: per-Gaussian alpha cap.
    alpha_threshold: a Gaussian is skipped at a pixel whose alpha is below this.
    transmittance_stop: a pixel stops before the Gaussian that would bring T to <= this.
    chunk_size: Gaussians composited per (sub-)tile per loop step; memory of a step is
      tiles_per_step x subtile_size^2 x chunk_size.
    tiles_per_step: (sub-)tiles composited per loop step, taken from a compacted list of the tiles that
      still have work (finished and empty tiles cost nothing); capped at the number of tiles. A
      step with fewer active tiles runs a smaller block from the ladder tiles_per_step / 2, / 4,
      ... (down to 8), so the tail of a few long lists does not pay for the padding.
    intersections_per_gaussian: the (Gaussian, tile) budget is this times N (at least
      `min_intersections`); a scene needing more has its farthest Gaussians' tiles cut, which sets
      `stats.truncated`, and `stats.overflow` where that can change a pixel (see RenderStats).
      Binning only pays for what a scene uses: the buffer is sorted at the smallest of B/4, B/2, B
      that holds the scene's pairs (docs/benchmarks.md has the measurements).
    min_intersections: floor of the default budget (small scenes, few Gaussians, large tiles).
    max_intersections: explicit budget; overrides the two above when set (`render_exact` sets it).
    rebin_on_overflow: bin at the smallest ladder size (B/4) even when the pairs exceed it and
      bin again at the size that holds them all only if that cut could change a pixel
      (`stats.overflow`; `lax.cond`). Saturating scenes then sort a quarter of the buffer
      losslessly (a cut behind saturated pixels changes nothing); scenes that overflow it bin and
      composite twice. Same image; opt-in (docs/benchmarks.md, "Binning at B/4, re-binning on
      overflow").
    pixel_major: the compositor's blocks are laid out [tiles, chunk, pixels] (pixels on the
      minor, vectorised axis; per-Gaussian reductions over a major axis) rather than [tiles,
      pixels, chunk]. Same sums, rounded differently (~1e-7); the backward is faster on XLA:CPU
      (docs/benchmarks.md, "Pixel-major blocks").
  """

  tile_size: int = 16
  subtile_size: int = 8
  eps2d: float = 0.3
  radius_sigmas: float = 3.33
  max_alpha: float = 0.999
  alpha_threshold: float = 1.0 / 255.0
  transmittance_stop: float = 1e-4
  chunk_size: int = 32
  tiles_per_step: int = 128
  intersections_per_gaussian: float = 16.0
  min_intersections: int = 4096
  max_intersections: int | None = None
  rebin_on_overflow: bool = False
  pixel_major: bool = True

  def __post_init__(self):
    for name in ("tile_size", "subtile_size", "chunk_size", "tiles_per_step"):
      value = getattr(self, name)
      if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value <= 0:
        raise ValueError(f"RenderConfig.{name} must be a positive int, got {value!r}")
    if self.tile_size % self.subtile_size:
      raise ValueError(
        f"RenderConfig.subtile_size ({self.subtile_size}) must divide tile_size ({self.tile_size})"
      )
    if not self.intersections_per_gaussian > 0:
      raise ValueError(
        "RenderConfig.intersections_per_gaussian must be > 0, got "
        f"{self.intersections_per_gaussian!r}"
      )
    if self.max_intersections is not None and self.max_intersections <= 0:
      raise ValueError(
        f"RenderConfig.max_intersections must be None or > 0, got {self.max_intersections!r}"
      )
    if not 0 < self.max_alpha <= 1 or not 0 <= self.alpha_threshold < 1:
      raise ValueError(
        "RenderConfig needs 0 < max_alpha <= 1 and 0 <= alpha_threshold < 1, got "
        f"{self.max_alpha!r}, {self.alpha_threshold!r}"
      )

  def intersection_budget(self, num_gaussians: int, num_tiles: int | None = None) -> int:
    """Static size of the (Gaussian, tile) buffer for N Gaussians (a chunk multiple).

    With `num_tiles` (tiles per image) it is capped at N x tiles, which no scene can exceed.
    """
    if self.max_intersections is not None:
      budget = self.max_intersections
    else:
      budget = max(
        self.min_intersections, math.ceil(self.intersections_per_gaussian * num_gaussians)
      )
    if num_tiles is not None:
      budget = min(budget, max(1, num_gaussians) * num_tiles)
    return self._chunks(budget)

  def budget_ladder(self, num_gaussians: int, num_tiles: int | None = None) -> tuple[int, ...]:
    """Ascending buffer sizes binning may sort at, the largest the budget: B/4, B/2, B.

    Steps below `min_intersections` collapse into one, so small scenes compile a single size.
    """
    budget = self.intersection_budget(num_gaussians, num_tiles)
    floor = min(budget, self._chunks(self.min_intersections))
    return tuple(sorted({max(floor, self._chunks(budget // 2**k)) for k in range(3)}))

  def _chunks(self, size: int) -> int:
    return max(self.chunk_size, -(-size // self.chunk_size) * self.chunk_size)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RenderStats:
  """Per-camera counters (each [..., V] int32, `overflow` bool).

  A Gaussian is counted under the first rule that culls it: non-finite (a NaN or inf in any of
  its fields: it is rendered as absent and gets a zero gradient, see `render`), then gsplat's
  order: depth (centre z outside [near, far]), degenerate (2D covariance determinant <= 0 or zero radius), opacity
  (< alpha_threshold), frustum (its radius box misses the image). `num_visible` are the rest.
  `num_intersections` is the number of (Gaussian, tile) pairs the scene's radius boxes need;
  `budget` the static buffer size; `truncated` is True when the first exceeded the second (the
  farthest Gaussians lost tiles). `overflow` is True when that could change the image: some
  truncated tile ran out of its (depth-ordered) list before all of its pixels saturated. A
  truncated render without overflow is exact: every cut pair lies behind saturated pixels.
  `tile_chunks` is the number of (tile, chunk) blocks composited (early stop diagnostic).
  """

  num_culled_nonfinite: jax.Array
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
