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
    tile_truncated: [T] bool, the budget cut some of this tile's pairs. Cuts go by depth, so a
      truncated tile still holds a front-to-back prefix of its Gaussians: it loses nothing when its
      pixels saturate before that prefix runs out.
    shared_lists: [] bool, tiles read overlapping ranges of `gaussian_ids` (`share_tiles`: every
      sub-tile reads its tile's list), so no tile may rewrite its list in place (the compositor's
      backward compaction, `rasterize.rasterize_tiles`).
  """

  gaussian_ids: jax.Array
  tile_starts: jax.Array
  tile_ends: jax.Array
  num_intersections: jax.Array
  tile_truncated: jax.Array
  shared_lists: jax.Array


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


def box_counts(means2d, radii, visible, *, tile_size, tiles_x, tiles_y):
  """Tiles covered by each visible Gaussian's radius box (gsplat's pair count).

  means2d: [N, 2], radii: [N, 2], visible: [N] -> (counts [N] int32, the four `tile_rectangles`).
  """
  x0, x1, y0, y1 = tile_rectangles(
    means2d, radii, tile_size=tile_size, tiles_x=tiles_x, tiles_y=tiles_y
  )
  return jnp.where(visible, (x1 - x0) * (y1 - y0), 0), (x0, x1, y0, y1)


def min_sigma_over_tile(means2d, conics, tile_x, tile_y, *, tile_size, height, width):
  """Lower bound of sigma = a dx²/2 + b dx dy + c dy²/2 over the pixel centres of a tile.

  The exact minimum of the convex quadratic over the rectangle spanned by the tile's pixel centres
  (clipped to the image): 0 if the mean is inside, else the least of the four edge minima.

  Args:
    means2d: [..., 2]; conics: [..., 3] (positive definite); tile_x, tile_y: [...] int32 (all
      broadcast together).
  Returns:
    [...] minimum sigma.
  """
  a, b, c = conics[..., 0], conics[..., 1], conics[..., 2]
  left = tile_x * tile_size + 0.5
  top = tile_y * tile_size + 0.5
  x0, x1 = left - means2d[..., 0], jnp.minimum(left + tile_size - 1, width - 0.5) - means2d[..., 0]
  y0, y1 = top - means2d[..., 1], jnp.minimum(top + tile_size - 1, height - 0.5) - means2d[..., 1]

  def sigma(dx, dy):
    return 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy

  # On a vertical edge dx = x the minimising dy is clip(-b x / c); on a horizontal one likewise.
  edges = [sigma(x, jnp.clip(-b * x / c, y0, y1)) for x in (x0, x1)]
  edges += [sigma(jnp.clip(-b * y / a, x0, x1), y) for y in (y0, y1)]
  inside = (x0 <= 0) & (x1 >= 0) & (y0 <= 0) & (y1 >= 0)
  return jnp.where(
    inside, 0.0, jnp.minimum(jnp.minimum(edges[0], edges[1]), jnp.minimum(edges[2], edges[3]))
  )


def reaches_tile(
  means2d, conics, opacities, tile_x, tile_y, *, tile_size, height, width, alpha_threshold
):
  """Whether a Gaussian's alpha may reach `alpha_threshold` at a pixel centre of a tile.

  Conservative: False only when min sigma over the tile exceeds ln(opacity / threshold), so the
  compositor would skip the Gaussian at every pixel of the tile.
  means2d: [..., 2]; conics: [..., 3]; opacities, tile_x, tile_y: [...] -> [...] bool.
  """
  sigma_floor = min_sigma_over_tile(
    means2d, conics, tile_x, tile_y, tile_size=tile_size, height=height, width=width
  )
  # Slack far above float rounding: a kept pair only costs work, a wrongly dropped one changes
  # pixels. Written as "not beyond" so that a NaN bound (a conic entry underflowing to 0) keeps it.
  reach = jnp.log(jnp.maximum(opacities, alpha_threshold) / alpha_threshold)
  return ~(sigma_floor > reach * (1.0 + 1e-3) + 1e-3)


def depth_order(keys):
  """`jnp.argsort(keys, stable=True)` ([N] -> [N] int32) for float32 keys without NaN.

  XLA:CPU sorts a lone int32 operand ~7x faster than a (key, index) pair with its comparator
  (65,536 keys: 1.7 ms vs 11.4 ms), so up to N = 2^16: the keys as order-preserving int32 bits
  (-0.0 as 0.0, as the float sort ties them), each key's rank among them (sort + binary search),
  then one sort of rank * N + index, which fits uint32 and is the exact stable order (5 ms).
  """
  num = keys.shape[0]
  if num > 2**16 or keys.dtype != jnp.float32:
    return jnp.argsort(keys, stable=True).astype(jnp.int32)
  bits = jax.lax.bitcast_convert_type(jnp.where(keys == 0, jnp.zeros_like(keys), keys), jnp.int32)
  ordered = bits ^ ((bits >> 31) & 0x7FFFFFFF)  # negative floats: reverse the magnitude bits
  rank = jnp.searchsorted(jnp.sort(ordered), ordered, side="left", method="scan_unrolled")
  packed = rank.astype(jnp.uint32) * jnp.uint32(num) + jnp.arange(num, dtype=jnp.uint32)
  return (jnp.sort(packed) % jnp.uint32(num)).astype(jnp.int32)


def bin_gaussians(
  means2d,
  radii,
  depths,
  visible,
  conics,
  opacities,
  *,
  tile_size,
  tiles_x,
  tiles_y,
  height,
  width,
  alpha_threshold,
  budget,
) -> TileBins:
  """Builds the per-tile, depth-ordered intersection lists with a fixed budget.

  Gaussians are ranked by (depth, index) first and their intersections emitted in rank order, so a
  budget overflow drops the farthest Gaussians' tiles, never a near one.

  The budget holds every tile of each radius box (gsplat's rule, what `num_intersections` counts),
  but a box tile where the Gaussian's alpha stays below `alpha_threshold` at every pixel centre
  (min sigma over the tile > ln(opacity / threshold)) is sorted behind all tiles: the compositor
  would skip it at every pixel anyway, so dropping it changes nothing but the work.

  Args:
    means2d: [N, 2]; radii: [N, 2]; depths: [N]; visible: [N] bool; conics: [N, 3]; opacities: [N].
    tile_size, tiles_x, tiles_y, height, width: tiling; alpha_threshold: the compositor's skip rule;
    budget: static number of intersection slots B.
    N must be at least 1 (`render` handles empty scenes before binning).
  """
  num = depths.shape[0]
  num_tiles = tiles_x * tiles_y
  means2d, radii, depths, conics, opacities = jax.lax.stop_gradient(
    (means2d, radii, depths, conics, opacities)
  )
  counts, (x0, x1, y0, y1) = box_counts(
    means2d, radii, visible, tile_size=tile_size, tiles_x=tiles_x, tiles_y=tiles_y
  )

  order = depth_order(jnp.where(visible, depths, jnp.inf))  # rank -> Gaussian
  counts_by_rank = counts[order]
  ends = jnp.cumsum(counts_by_rank)
  starts = ends - counts_by_rank
  total = ends[-1]

  slot_rank, slot_tile = _slot_tiles(
    order,
    counts_by_rank,
    starts,
    total,
    (x0, x1, y0),
    means2d,
    conics,
    opacities,
    budget=budget,
    tile_size=tile_size,
    tiles_x=tiles_x,
    num_tiles=num_tiles,
    height=height,
    width=width,
    alpha_threshold=alpha_threshold,
  )
  sorted_tile, sorted_rank = _sort_pairs(slot_tile, slot_rank, num, num_tiles)
  gaussian_ids = order[sorted_rank]
  # Gaussians cut (wholly or partly) by the budget mark every tile of their box truncated.
  cut = visible & (jnp.zeros(num, ends.dtype).at[order].set(ends) > budget)
  cut_boxes = _covering_counts(cut, (x0, x1, y0, y1), tiles_x=tiles_x, tiles_y=tiles_y)
  bounds = jnp.searchsorted(sorted_tile, jnp.arange(num_tiles + 1, dtype=jnp.int32), side="left")
  return TileBins(
    gaussian_ids=gaussian_ids.astype(jnp.int32),
    tile_starts=bounds[:-1].astype(jnp.int32),
    tile_ends=bounds[1:].astype(jnp.int32),
    num_intersections=total.astype(jnp.int32),
    tile_truncated=cut_boxes.reshape(-1) > 0,
    shared_lists=jnp.asarray(False),
  )


def _slot_tiles(
  order,
  counts_by_rank,
  starts,
  total,
  box_corner,
  means2d,
  conics,
  opacities,
  *,
  budget,
  tile_size,
  tiles_x,
  num_tiles,
  height,
  width,
  alpha_threshold,
):
  """Expands the depth-ranked radius boxes into the B budget slots, in rank order.

  Args:
    order: [N] rank -> Gaussian; counts_by_rank, starts: [N] box tiles and first slot of each
      rank; total: [] slots needed; box_corner: (x0, x1, y0) [N] int32 of `tile_rectangles`;
      means2d: [N, 2]; conics: [N, 3]; opacities: [N].

  Returns:
    `(slot_rank, slot_tile)`: [B] owner rank and tile of each slot; the tile is `num_tiles` (sorted
    behind every tile) for slots past `total` and tiles the Gaussian's alpha never reaches.
  """
  x0, x1, y0 = box_corner
  num = order.shape[0]
  # Owner rank of each slot: mark every non-empty run's first slot, then a running max fills it.
  slots = jnp.arange(budget, dtype=jnp.int32)
  ranks = jnp.arange(num, dtype=jnp.int32)
  marks = (
    jnp.zeros(budget, jnp.int32)
    .at[jnp.where(counts_by_rank > 0, starts, budget)]
    .max(ranks, mode="drop")
  )
  slot_rank = jax.lax.cummax(marks)
  slot_gauss = order[slot_rank]
  local = slots - starts[slot_rank]
  box_width = jnp.maximum(x1 - x0, 1)[slot_gauss]
  tile_x = x0[slot_gauss] + local % box_width
  tile_y = y0[slot_gauss] + local // box_width
  touches = reaches_tile(
    means2d[slot_gauss],
    conics[slot_gauss],
    opacities[slot_gauss],
    tile_x,
    tile_y,
    tile_size=tile_size,
    height=height,
    width=width,
    alpha_threshold=alpha_threshold,
  )
  slot_tile = jnp.where(
    (slots < total) & touches, tile_y * tiles_x + tile_x, num_tiles
  )  # rest last
  return slot_rank, slot_tile


def _sort_pairs(slot_tile, slot_rank, num, num_tiles):
  """Slots [B] sorted by (tile, rank): `(sorted_tile, sorted_rank)`, both [B] int32.

  The key packs (tile, rank) into one int32 when it fits (exact order, one single-key sort),
  else a two-key sort.
  """
  if (num_tiles + 1) * num <= _INT32_MAX:
    keys = jnp.sort(slot_tile * num + slot_rank)
    sorted_tile = keys // num
    sorted_rank = keys - sorted_tile * num
  else:
    sorted_tile, sorted_rank = jax.lax.sort((slot_tile, slot_rank), num_keys=2)
  return sorted_tile, sorted_rank


def _covering_counts(cut, boxes, *, tiles_x, tiles_y):
  """Per tile [tiles_y, tiles_x] int32, how many of the `cut` [N] bool boxes cover it.

  boxes: the four [N] int32 arrays of `tile_rectangles`. +-1 at each cut box's corners, then a
  2D prefix sum: O(N + T), no per-pair work.
  """
  x0, x1, y0, y1 = boxes
  corners = jnp.zeros((tiles_y + 1, tiles_x + 1), jnp.int32)
  for row, col, sign in ((y0, x0, 1), (y0, x1, -1), (y1, x0, -1), (y1, x1, 1)):
    corners = corners.at[row, col].add(jnp.where(cut, sign, 0))
  return jnp.cumsum(jnp.cumsum(corners, axis=0), axis=1)[:tiles_y, :tiles_x]


def split_tiles(
  bins: TileBins,
  means2d,
  conics,
  opacities,
  *,
  tile_size,
  subtile_size,
  tiles_x,
  tiles_y,
  height,
  width,
  alpha_threshold,
) -> TileBins:
  """Splits every tile's list into the lists of its f x f sub-tiles (f = tile / subtile size).

  A sub-tile keeps, in its tile's front-to-back order, the Gaussians that may reach one of its
  pixels (`reaches_tile`): the image is the same, the compositor evaluates fewer (pixel,
  Gaussian) pairs. No sort: an entry's place in a sub-list is a running count of the entries
  before it. Sub-tile q of tile t owns the slots from f² start_t + q len_t of a buffer f² times
  the tile buffer (a sub-list is never longer than its tile's), so the split cuts nothing.

  Args:
    bins: one camera's TileBins over tiles of `tile_size` (the buffer, length L, unpadded).
    means2d: [N, 2]; conics: [N, 3]; opacities: [N]; the rest: tiling and the skip rule.

  Returns:
    TileBins over the row-major grid of ceil(H / s) x ceil(W / s) sub-tiles (s = subtile_size),
    buffer f² L; `num_intersections` stays the tile-level count the budget is made of, and a
    sub-tile is truncated where its tile is.
  """
  f = tile_size // subtile_size
  parts, length = f * f, bins.gaussian_ids.shape[0]
  ids = bins.gaussian_ids
  entry = jnp.arange(length, dtype=jnp.int32)
  tile = _entry_tiles(bins.tile_ends, length)  # tiles_x * tiles_y: unlisted
  listed = tile < tiles_x * tiles_y
  tile = jnp.minimum(tile, tiles_x * tiles_y - 1)
  part = jnp.arange(parts, dtype=jnp.int32)
  sub_x = (tile % tiles_x)[:, None] * f + part % f  # [L, parts]
  sub_y = (tile // tiles_x)[:, None] * f + part // f
  means2d, conics, opacities = jax.lax.stop_gradient((means2d[ids], conics[ids], opacities[ids]))
  touch = (
    listed[:, None]
    & (sub_x * subtile_size < width)
    & (sub_y * subtile_size < height)
    & reaches_tile(
      means2d[:, None],
      conics[:, None],
      opacities[:, None],
      sub_x,
      sub_y,
      tile_size=subtile_size,
      height=height,
      width=width,
      alpha_threshold=alpha_threshold,
    )
  )
  # running[i, q]: entries before i that touch part q (a [L + 1, parts] exclusive count)
  running = jnp.cumsum(jnp.pad(touch, ((1, 0), (0, 0))), axis=0, dtype=jnp.int32)
  starts, ends = bins.tile_starts, bins.tile_ends
  sub_starts = parts * starts[:, None] + part * (ends - starts)[:, None]  # [T, parts]
  sub_ends = sub_starts + running[ends] - running[starts]
  slot = sub_starts[tile] + running[:-1] - running[starts][tile]
  # Skipped entries go to distinct slots past the buffer (dropped): the indices stay unique.
  slot = jnp.where(touch, slot, parts * length + entry[:, None] * parts + part)
  sub_ids = (
    jnp.zeros(parts * length, ids.dtype)
    .at[slot.reshape(-1)]
    .set(jnp.repeat(ids, parts), mode="drop", unique_indices=True)
  )
  parent, which = _subtile_parents(f, subtile_size, tiles_x=tiles_x, height=height, width=width)
  return TileBins(
    gaussian_ids=sub_ids,
    tile_starts=sub_starts[parent, which],
    tile_ends=sub_ends[parent, which],
    num_intersections=bins.num_intersections,
    tile_truncated=bins.tile_truncated[parent],
    shared_lists=bins.shared_lists,
  )


def _entry_tiles(tile_ends, length):
  """[length] int32: how many tile ends are <= each entry (`searchsorted(tile_ends, entry,
  "right")`), as a running count of the ends (a binary search per entry cost 3x more)."""
  end_marks = jnp.zeros(length + 1, jnp.int32).at[tile_ends].add(1)
  return jnp.cumsum(end_marks[:length], dtype=jnp.int32)


def share_tiles(bins: TileBins, *, tile_size, subtile_size, tiles_x, height, width) -> TileBins:
  """`split_tiles` without the filter: every sub-tile reads its whole tile's list, in place.

  No per-pair work; the compositor does what it would on whole tiles. For scenes of Gaussians
  large against a tile, which reach nearly every sub-tile they are listed in.
  """
  f = tile_size // subtile_size
  parent, _ = _subtile_parents(f, subtile_size, tiles_x=tiles_x, height=height, width=width)
  return TileBins(
    gaussian_ids=bins.gaussian_ids,
    tile_starts=bins.tile_starts[parent],
    tile_ends=bins.tile_ends[parent],
    num_intersections=bins.num_intersections,
    tile_truncated=bins.tile_truncated[parent],
    shared_lists=jnp.asarray(f > 1),
  )


def _subtile_parents(f, subtile_size, *, tiles_x, height, width):
  """(tile, part) [G] of each sub-tile of the row-major sub-tile grid, part = f row + column."""
  sub_x = -(-width // subtile_size)
  grid_y, grid_x = jnp.divmod(jnp.arange(-(-height // subtile_size) * sub_x), sub_x)
  return (grid_y // f) * tiles_x + grid_x // f, (grid_y % f) * f + grid_x % f
