"""Static-shape (Gaussian, tile) intersection lists sorted by (tile, depth, index)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

_INT32_MAX = 2**31 - 1


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TileBins:
  """Intersections of one camera, grouped by tile, front to back inside each tile.

  Attributes:
    gaussian_ids: [B] Gaussian index of each sorted intersection (entries past a tile's end are
      padding that the compositor never reads as valid).
    tile_starts: [T] first entry of each tile in `gaussian_ids`.
    tile_ends: [T] one past the last entry of each tile.
    num_intersections: [] int32 number of pairs the scene needs (may exceed B).
  """

  gaussian_ids: jax.Array
  tile_starts: jax.Array
  tile_ends: jax.Array
  num_intersections: jax.Array


def tile_rectangles(means2d, radii, *, tile_size, tiles_x, tiles_y):
  """Tile range [x0, x1) x [y0, y1) covered by each radius box, as gsplat's intersect_tile.

  means2d: [N, 2], radii: [N, 2] (0 = culled) -> four int32 [N] arrays.
  """
  lo = (means2d - radii) / tile_size
  hi = (means2d + radii) / tile_size
  limits = jnp.array([tiles_x, tiles_y], dtype=means2d.dtype)
  # Clip in float first: the values of huge or far-away Gaussians do not fit an int32.
  lo = jnp.clip(jnp.floor(lo), 0, limits).astype(jnp.int32)
  hi = jnp.clip(jnp.ceil(hi), 0, limits).astype(jnp.int32)
  return lo[:, 0], hi[:, 0], lo[:, 1], hi[:, 1]


def bin_gaussians(means2d, radii, depths, visible, *, tile_size, tiles_x, tiles_y, budget) -> TileBins:
  """Builds the per-tile, depth-ordered intersection lists with a fixed budget.

  Gaussians are ranked by (depth, index) first and their intersections emitted in rank order, so a
  budget overflow drops the farthest Gaussians' tiles, never a near one. The sort key packs
  (tile, rank) into one int32 when it fits (exact order, one single-key sort), else a two-key sort.

  Args:
    means2d: [N, 2]; radii: [N, 2]; depths: [N]; visible: [N] bool.
    tile_size, tiles_x, tiles_y: tiling; budget: static number of intersection slots B.
    N must be at least 1 (`render` handles empty scenes before binning).
  """
  num = depths.shape[0]
  num_tiles = tiles_x * tiles_y
  means2d, radii, depths = jax.lax.stop_gradient((means2d, radii, depths))
  x0, x1, y0, y1 = tile_rectangles(means2d, radii, tile_size=tile_size, tiles_x=tiles_x, tiles_y=tiles_y)
  counts = jnp.where(visible, (x1 - x0) * (y1 - y0), 0)

  order = jnp.argsort(jnp.where(visible, depths, jnp.inf), stable=True)  # rank -> Gaussian
  counts_by_rank = counts[order]
  ends = jnp.cumsum(counts_by_rank)
  starts = ends - counts_by_rank
  total = ends[-1]

  # Owner rank of each slot: mark every non-empty run's first slot, then a running max fills it.
  slots = jnp.arange(budget, dtype=jnp.int32)
  ranks = jnp.arange(num, dtype=jnp.int32)
  marks = jnp.zeros(budget, jnp.int32).at[jnp.where(counts_by_rank > 0, starts, budget)].max(
      ranks, mode="drop")
  slot_rank = jax.lax.cummax(marks)
  slot_gauss = order[slot_rank]
  local = slots - starts[slot_rank]
  width = jnp.maximum(x1 - x0, 1)[slot_gauss]
  tile_x = x0[slot_gauss] + local % width
  tile_y = y0[slot_gauss] + local // width
  slot_tile = jnp.where(slots < total, tile_y * tiles_x + tile_x, num_tiles)  # padding sorts last

  if (num_tiles + 1) * num <= _INT32_MAX:
    keys = jnp.sort(slot_tile * num + slot_rank)
    sorted_tile = keys // num
    sorted_rank = keys - sorted_tile * num
  else:
    sorted_tile, sorted_rank = jax.lax.sort((slot_tile, slot_rank), num_keys=2)
  gaussian_ids = order[sorted_rank]
  bounds = jnp.searchsorted(sorted_tile, jnp.arange(num_tiles + 1, dtype=jnp.int32), side="left")
  return TileBins(
      gaussian_ids=gaussian_ids.astype(jnp.int32),
      tile_starts=bounds[:-1].astype(jnp.int32),
      tile_ends=bounds[1:].astype(jnp.int32),
      num_intersections=total.astype(jnp.int32),
  )
