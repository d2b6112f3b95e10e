"""Tiled front-to-back alpha compositing with per-tile early stop and a recomputing backward.

Tiles advance one chunk of `chunk_size` sorted Gaussians per loop step; a step takes the first S
tiles that still have work (a compacted list; S from a halving ladder of block sizes, the
smallest that holds them all) and evaluates [S, chunk, tile pixels] alphas (pixel-major: the pixels
on the minor, vectorised axis; `Tiling.pixel_major=False` is the [S, pixels, chunk] layout), turns
them into transmittances with a prefix sum of log(1 - alpha) (a small triangular matmul), and
composites with one batched matmul. The loop stops
as soon as no tile has both Gaussians left and a pixel that is not saturated, so empty tiles cost
nothing beyond the first step and saturated scenes stop after a few chunks.

The backward (custom_vjp) replays the steps front to back and needs only the forward's final
per-pixel sums, so its memory is one step's [tiles, pixels, chunk] block, never pixels x Gaussians.
It replays shorter lists: the forward of a gradient rewrites each tile's list in place to the
Gaussians that some not-yet-stopped pixel keeps (alpha >= threshold); the others change no
transmittance and get no gradient (on the 65k benchmark scene 9% fewer backward chunks). Chunks
then group differently, so the replayed transmittances match the forward's to float rounding.
For the cotangent of colour F = sum_k w_k f_k with w_k = alpha_k T_{k-1} and T_final = prod (1 -
alpha_k):  dL/dalpha_k = T_{k-1} <f_k, gF> - (sum_{m>k} w_m <f_m, gF> + gT T_final) / (1 - alpha_k),
where the suffix sum is the total minus the running prefix (known from the forward's output).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from tokengs_jax.splatting.config import PRECISION

# Columns of the per-Gaussian attribute matrix fed to the compositor.
MEAN_X, MEAN_Y, CONIC_A, CONIC_B, CONIC_C, OPACITY = range(6)
NUM_GEOMETRY = 6  # the columns after these are the composited features (rgb, depth)


class Tiling(NamedTuple):
  """Static description of the tile grid and of the compositing rule (hashable)."""

  height: int
  width: int
  tile_size: int
  tiles_x: int
  tiles_y: int
  num_images: int  # the tile list is num_images grids of tiles_y x tiles_x, one after the other
  chunk_size: int
  tiles_per_step: int
  max_alpha: float
  alpha_threshold: float
  transmittance_stop: float
  # The forward of a gradient compacts each tile's list to the Gaussians that reach an open pixel,
  # so the backward replays fewer chunks (False: it replays the forward's lists; tests compare).
  compact_backward: bool = True
  # Blocks laid out [S, K, P] (pixels on the minor, vectorised axis) rather than [S, P, K]
  # (`RenderConfig.pixel_major`: the same sums, rounded differently).
  pixel_major: bool = True


def _axes(tiling: Tiling) -> tuple[int, int]:
  """(Gaussian axis, pixel axis) of a block."""
  return (1, 2) if tiling.pixel_major else (2, 1)


def _per_pixel(x, tiling: Tiling):
  """[S, P] -> broadcastable against a block."""
  return x[:, None, :] if tiling.pixel_major else x[..., None]


def _prefix(x, strict_upper, tiling: Tiling):
  """Exclusive prefix sum of a block over its Gaussians (a triangular matmul)."""
  if tiling.pixel_major:  # a batched dot: "jk,sjp->skp" made XLA transpose x to [S, P, K]
    lower = jnp.broadcast_to(strict_upper.T, (x.shape[0],) + strict_upper.shape)
    return jnp.matmul(lower, x, precision=PRECISION)
  return jnp.matmul(x, strict_upper, precision=PRECISION)


def tile_pixel_centers(tiling: Tiling, dtype):
  """Pixel centres of every tile (plus one empty padding tile) and whether they are in the image.

  -> (centres [T + 1, P, 2] (u, v), inside [T + 1, P] bool), T = num_images * tiles_y * tiles_x,
  P = tile_size².
  """
  ts = tiling.tile_size
  grid = tiling.tiles_x * tiling.tiles_y
  tile = jnp.arange(tiling.num_images * grid + 1) % grid
  tile_y, tile_x = jnp.divmod(tile, tiling.tiles_x)
  pix_y, pix_x = jnp.divmod(jnp.arange(ts * ts), ts)
  col = tile_x[:, None] * ts + pix_x[None, :]
  row = tile_y[:, None] * ts + pix_y[None, :]
  inside = (col < tiling.width) & (row < tiling.height)
  centres = jnp.stack([col, row], axis=-1).astype(dtype) + 0.5
  return centres, inside


class _Chunk(NamedTuple):
  gaussian_ids: jax.Array  # [S, K]
  slot_valid: jax.Array  # [S, K]
  attrs: jax.Array  # [S, K, D]
  dx: jax.Array  # [S, P, K] ([S, K, P] pixel-major) mean - pixel centre
  dy: jax.Array
  vis: jax.Array  # exp(-sigma)
  raw_alpha: jax.Array  # opacity * vis (before the cap)
  alpha: jax.Array  # capped, 0 where skipped
  keep: jax.Array  # a valid slot not skipped by the sigma / threshold rules


def _load_chunk(
  chunk_index, attrs, gaussian_ids, tile_starts, tile_ends, centres, tiling
) -> _Chunk:
  """Evaluates chunk `chunk_index [S]` of S tiles (ranges [S], centres [S, P, 2]) at their pixels."""
  positions = (tile_starts + chunk_index * tiling.chunk_size)[:, None] + jnp.arange(
    tiling.chunk_size
  )
  slot_valid = positions < tile_ends[:, None]
  ids = gaussian_ids[jnp.minimum(positions, gaussian_ids.shape[0] - 1)]
  data = attrs[ids]
  if tiling.pixel_major:
    gauss, pixel = (lambda x: x[:, :, None]), (lambda x: x[:, None, :])
  else:
    gauss, pixel = (lambda x: x[:, None, :]), (lambda x: x[:, :, None])
  dx = gauss(data[..., MEAN_X]) - pixel(centres[..., 0])
  dy = gauss(data[..., MEAN_Y]) - pixel(centres[..., 1])
  sigma = (
    0.5 * (gauss(data[..., CONIC_A]) * dx * dx + gauss(data[..., CONIC_C]) * dy * dy)
    + gauss(data[..., CONIC_B]) * dx * dy
  )
  vis = jnp.exp(-jnp.maximum(sigma, 0.0))
  raw_alpha = gauss(data[..., OPACITY]) * vis
  alpha = jnp.minimum(tiling.max_alpha, raw_alpha)
  keep = gauss(slot_valid) & (sigma >= 0) & (alpha >= tiling.alpha_threshold)
  return _Chunk(ids, slot_valid, data, dx, dy, vis, raw_alpha, jnp.where(keep, alpha, 0.0), keep)


class _Transmittance(NamedTuple):
  before: jax.Array  # [S, P, K] ([S, K, P] pixel-major) T just before each Gaussian
  weight: jax.Array  # alpha * T_before where composited, else 0
  include: jax.Array  # composited
  transmittance: jax.Array  # [S, P] after the chunk
  done: jax.Array  # [S, P] pixel stopped


def _transmittance(chunk: _Chunk, transmittance, done, tiling) -> _Transmittance:
  k = tiling.chunk_size
  strict_upper = jnp.triu(
    jnp.ones((k, k), chunk.alpha.dtype), 1
  )  # [i, j] = i < j: exclusive prefix
  log_keep = jnp.log1p(-chunk.alpha)
  before = _per_pixel(transmittance, tiling) * jnp.exp(_prefix(log_keep, strict_upper, tiling))
  after = before * (1.0 - chunk.alpha)
  # T only decreases, so once a Gaussian would take T to <= stop every later one would too: this
  # mask is exactly gsplat's "stop before the Gaussian that saturates the pixel".
  saturating = chunk.keep & (after <= tiling.transmittance_stop)
  include = chunk.keep & ~saturating & ~_per_pixel(done, tiling)
  weight = jnp.where(include, chunk.alpha * before, 0.0)
  gauss_axis = _axes(tiling)[0]
  new_t = transmittance * jnp.exp(jnp.sum(jnp.where(include, log_keep, 0.0), axis=gauss_axis))
  return _Transmittance(before, weight, include, new_t, done | jnp.any(saturating, axis=gauss_axis))


# The compositor's loop step comes in block sizes tiles_per_step, /2, /4, ... (not below this):
# once few tiles still have work, a full block would composite mostly the empty padding tile
# (a 32x32 training render has 16 sub-tiles a camera and a few long lists: halving blocks made the
# default train step 1.4x faster; docs/benchmarks.md).
_MIN_TILES_PER_STEP = 8


def step_sizes(tiling: Tiling) -> tuple[int, ...]:
  """The block sizes (tiles per loop step) a compositing loop chooses from, largest first."""
  sizes = [tiling.tiles_per_step]
  while sizes[-1] // 2 >= _MIN_TILES_PER_STEP:
    sizes.append(sizes[-1] // 2)
  return tuple(sizes)


def _step_on_active_tiles(active, step, tiling):
  """`step(sel)` on the compacted list `sel` [S] of the first S active tiles (padded with the
  empty tile T), S the smallest of `step_sizes` that holds every active tile (else the largest):
  one `lax.switch` per loop step, so a tail of a few long lists costs small blocks.

  `step(sel)` -> (rows, extra): rows, a pytree of the selected tiles' new state [S, ...]; extra,
  a pytree whose shapes do not depend on S. Returns (index [S_max], rows padded to [S_max, ...],
  extra) with S_max = tiling.tiles_per_step; index is `sel`, then T + 1 (out of range: a scatter
  with mode="drop" skips the padding). The caller scatters the rows into its loop state outside
  the switch: a state array passed through the branches and updated there was copied whole at
  every step (XLA:CPU), O(tiles) per step and so O(tiles²) a render (issue 27: 0.2 of the 0.8 s
  forward at 1024²); the branches only read the state.
  """
  sizes = step_sizes(tiling)
  out_of_range = active.shape[0]

  def on(size):
    def run(_):
      sel = jnp.nonzero(active, size=size, fill_value=active.shape[0] - 1)[0]
      rows, extra = step(sel)
      pad = sizes[0] - size
      index = jnp.pad(sel, (0, pad), constant_values=out_of_range)
      rows = jax.tree.map(lambda x: jnp.pad(x, ((0, pad),) + ((0, 0),) * (x.ndim - 1)), rows)
      return index, rows, extra

    return run

  if len(sizes) == 1:
    return on(sizes[0])(None)
  # sizes descend, so the count of sizes >= the active count, minus one, indexes the smallest.
  fits = jnp.sum(jnp.asarray(sizes) >= jnp.sum(active))
  return jax.lax.switch(jnp.maximum(fits - 1, 0), [on(size) for size in sizes], None)


def _scatter_rows(state, index, rows):
  """state (a tuple of [T + 1, ...] arrays) with rows [S_max, ...] written at index [S_max]."""
  return tuple(x.at[index].set(r, mode="drop") for x, r in zip(state, rows, strict=True))


def _pad_ranges(tile_starts, tile_ends):
  zero = jnp.zeros((1,), tile_starts.dtype)
  return jnp.concatenate([tile_starts, zero]), jnp.concatenate([tile_ends, zero])


def _compaction_writes(kept, sel, chunk, done, starts, size, length, shared, tiling):
  """Where the chunk's slots that some open pixel keeps (alpha above the threshold where the
  pixel has not stopped) go: behind the ones kept before, in the same list. A tile's write
  position never passes its read position, so the list ahead of the loop stays intact.
  -> (the selected tiles' new kept counts [S], (positions, ids) [size * K], `length` (dropped)
  past the kept slots)."""
  needed = jnp.any(chunk.keep & ~_per_pixel(done, tiling), axis=_axes(tiling)[1])  # [S, K]
  rank = jnp.cumsum(needed, axis=-1) - needed
  position = jnp.where(needed & ~shared, (starts[sel] + kept[sel])[:, None] + rank, length)
  pad = (size - sel.shape[0]) * needed.shape[-1]
  writes = (
    jnp.pad(position.reshape(-1), (0, pad), constant_values=length),
    jnp.pad(chunk.gaussian_ids.reshape(-1), (0, pad)),
  )
  return kept[sel] + jnp.sum(needed, axis=-1, dtype=kept.dtype), writes


def _forward(attrs, gaussian_ids, tile_starts, tile_ends, tiling, compact=False, shared=False):
  """The compositing loop; with `compact` it also returns the compacted lists (ids [B], kept
  [T]) that the backward replays: the slots no open pixel keeps change neither a transmittance
  nor a gradient, so the backward skips them (fewer chunks where pixels saturate). Where
  `shared` ([] bool: overlapping lists) the ids are returned unchanged."""
  centres, inside = tile_pixel_centers(tiling, attrs.dtype)
  starts, ends = _pad_ranges(tile_starts, tile_ends)
  num_features = attrs.shape[-1] - NUM_GEOMETRY
  length = gaussian_ids.shape[0]

  # Per-tile "every pixel stopped" is carried (updated for the selected tiles only) rather than
  # re-reduced over all pixels of all tiles at every step.
  def active(chunk_index, tile_done):
    return (starts + chunk_index * tiling.chunk_size < ends) & ~tile_done

  def cond(state):
    chunk_index, _, _, tile_done, _, _ = state[0]
    return jnp.any(active(chunk_index, tile_done))

  def step(ids, state, sel):
    """The selected tiles' next chunk: (their new state rows [S, ...], compaction writes)."""
    chunk_index, transmittance, done, _, accum, kept = state
    chunk = _load_chunk(chunk_index[sel], attrs, ids, starts[sel], ends[sel], centres[sel], tiling)
    trans = _transmittance(chunk, transmittance[sel], done[sel], tiling)
    summed = accum[sel] + jnp.einsum(
      "skp,skf->spf" if tiling.pixel_major else "spk,skf->spf",
      trans.weight,
      chunk.attrs[..., NUM_GEOMETRY:],
      precision=PRECISION,
    )
    kept_rows, writes = kept[sel], ()
    if compact:
      size = tiling.tiles_per_step
      kept_rows, writes = _compaction_writes(
        kept, sel, chunk, done[sel], starts, size, length, shared, tiling
      )
    rows = (
      chunk_index[sel] + 1,
      trans.transmittance,
      trans.done,
      jnp.all(trans.done, axis=-1),
      summed,
      kept_rows,
    )
    return rows, writes

  def body(state):
    (chunk_index, _, _, tile_done, _, _), ids = state
    # The state and the list are written outside the switch: passed through its branches and
    # written there they were copied whole at every step.
    index, rows, writes = _step_on_active_tiles(
      active(chunk_index, tile_done), functools.partial(step, ids, state[0]), tiling
    )
    if compact:
      ids = ids.at[writes[0]].set(writes[1], mode="drop")
    return _scatter_rows(state[0], index, rows), ids

  init = (
    jnp.zeros(starts.shape, jnp.int32),
    jnp.ones(inside.shape, attrs.dtype),
    ~inside,
    jnp.all(~inside, axis=-1),
    jnp.zeros(inside.shape + (num_features,), attrs.dtype),
    jnp.zeros(starts.shape, jnp.int32),
  )
  state, ids = jax.lax.while_loop(cond, body, (init, gaussian_ids))
  chunks, transmittance, _, tile_done, accum, kept = state
  out = accum[:-1], transmittance[:-1], chunks[:-1], tile_done[:-1]
  return (out, (ids, kept[:-1])) if compact else out


@functools.partial(jax.custom_vjp, nondiff_argnums=(4,))
def rasterize_tiles(attrs, gaussian_ids, tile_starts, tile_ends, tiling: Tiling, shared=True):
  """Composites every tile front to back, stopping each tile when its pixels are saturated.

  Args:
    attrs: [N, 6 + F] per Gaussian: mean x, mean y, conic a, b, c, opacity, then F features.
    gaussian_ids: [B] tile-sorted intersection list; tile_starts, tile_ends: [T] its tile ranges.
    tiling: static grid and compositing constants.
    shared: [] bool, some tiles' ranges overlap (`TileBins.shared_lists`); False lets the
      forward of a gradient compact each list in place for the backward.

  Returns:
    (accumulated features [T, P, F], final transmittance [T, P], chunks composited per tile [T],
    saturated [T]: every pixel of the tile stopped, so Gaussians behind its list change nothing).
  """
  del shared
  return _forward(attrs, gaussian_ids, tile_starts, tile_ends, tiling)


def _rasterize_fwd(attrs, gaussian_ids, tile_starts, tile_ends, tiling, shared):
  if not tiling.compact_backward:
    out = _forward(attrs, gaussian_ids, tile_starts, tile_ends, tiling)
    return out, (attrs, gaussian_ids, tile_starts, tile_ends, out[2]) + out[:2]
  shared = jnp.asarray(shared, bool)
  out, (ids, kept) = _forward(
    attrs, gaussian_ids, tile_starts, tile_ends, tiling, compact=True, shared=shared
  )
  # shared lists were left as they were: the backward replays the forward's chunks
  ends = jnp.where(shared, tile_ends, tile_starts + kept)
  num_chunks = jnp.where(shared, out[2], -(-kept // tiling.chunk_size))
  return out, (attrs, ids, tile_starts, ends, num_chunks) + out[:2]


def _geometry_grads(chunk: _Chunk, v_raw, pixel_axis):
  """[S, K, 6] gradients of the geometry columns (mean, conic, opacity) from dL/d raw alpha.

  The conic is constant over a Gaussian's pixels: the pixel moments are summed first.
  """
  v_sigma = -v_raw * chunk.raw_alpha
  dx, dy = chunk.dx, chunk.dy
  v_dx, v_dy = v_sigma * dx, v_sigma * dy
  m_x, m_y = jnp.sum(v_dx, axis=pixel_axis), jnp.sum(v_dy, axis=pixel_axis)
  conic_a, conic_b, conic_c = (chunk.attrs[..., i] for i in (CONIC_A, CONIC_B, CONIC_C))
  return jnp.stack(
    [
      conic_a * m_x + conic_b * m_y,
      conic_b * m_x + conic_c * m_y,
      0.5 * jnp.sum(v_dx * dx, axis=pixel_axis),
      jnp.sum(v_dx * dy, axis=pixel_axis),
      0.5 * jnp.sum(v_dy * dy, axis=pixel_axis),
      jnp.sum(v_raw * chunk.vis, axis=pixel_axis),
    ],
    axis=-1,
  )


def _rasterize_bwd(tiling, residuals, cotangents):
  attrs, gaussian_ids, tile_starts, tile_ends, num_chunks, accum, final_t = residuals
  g_accum, g_final_t, _, _ = cotangents
  centres, inside = tile_pixel_centers(tiling, attrs.dtype)
  starts, ends = _pad_ranges(tile_starts, tile_ends)
  pad = lambda x: jnp.concatenate([x, jnp.zeros_like(x[:1])])
  g_accum, num_chunks = pad(g_accum), pad(num_chunks)
  # A render that was composited but not used (`RenderConfig.rebin_on_overflow`) gets zero
  # cotangents: nothing to replay.
  used = jnp.any(g_accum != 0) | jnp.any(g_final_t != 0)
  num_chunks = jnp.where(used, num_chunks, 0)
  g_total = jnp.sum(pad(accum) * g_accum, axis=-1)  # [T + 1, P]
  # T_final's own cotangent enters every alpha's gradient as -gT T_final / (1 - alpha).
  g_through_final = pad(g_final_t * final_t)
  strict_upper = jnp.triu(jnp.ones((tiling.chunk_size,) * 2, attrs.dtype), 1)

  def cond(state):
    return jnp.any(state[0] < num_chunks)

  def step(state, sel):
    """The selected tiles' next chunk: (their new state rows [S, ...], gradient rows)."""
    chunk_index, transmittance, done, g_prefix, _ = state
    chunk = _load_chunk(
      chunk_index[sel], attrs, gaussian_ids, starts[sel], ends[sel], centres[sel], tiling
    )
    trans = _transmittance(chunk, transmittance[sel], done[sel], tiling)
    g_out = g_accum[sel]
    pm = tiling.pixel_major
    gauss_axis, pixel_axis = _axes(tiling)
    g_feat = jnp.einsum(
      "skf,spf->skp" if pm else "skf,spf->spk",
      chunk.attrs[..., NUM_GEOMETRY:],
      g_out,
      precision=PRECISION,
    )
    contrib = trans.weight * g_feat
    g_before = g_prefix[sel]
    # suffix_k = sum over later composited Gaussians (this chunk and the rest) of w <f, gF>
    earlier_in_chunk = _prefix(contrib, strict_upper, tiling)
    g_suffix = _per_pixel(g_total[sel] - g_before, tiling) - earlier_in_chunk - contrib
    v_alpha = jnp.where(
      trans.include,
      trans.before * g_feat
      - (g_suffix + _per_pixel(g_through_final[sel], tiling)) / (1.0 - chunk.alpha),
      0.0,
    )
    v_raw = jnp.where(chunk.raw_alpha <= tiling.max_alpha, v_alpha, 0.0)  # the cap has no slope
    v_geometry = _geometry_grads(chunk, v_raw, pixel_axis)
    v_features = jnp.einsum(
      "skp,spf->skf" if pm else "spk,spf->skf", trans.weight, g_out, precision=PRECISION
    )
    rows = jnp.concatenate([v_geometry, v_features], axis=-1)
    rows = jnp.where(chunk.slot_valid[..., None], rows, 0.0)
    # padded to the largest block with out-of-range ids (dropped): a shape the switch can return
    pad = (tiling.tiles_per_step - sel.shape[0]) * tiling.chunk_size
    ids = jnp.pad(chunk.gaussian_ids.reshape(-1), (0, pad), constant_values=attrs.shape[0])
    rows = jnp.pad(rows.reshape(-1, rows.shape[-1]), ((0, pad), (0, 0)))
    new = (chunk_index[sel] + 1, trans.transmittance, trans.done)
    return new + (g_before + jnp.sum(contrib, axis=gauss_axis),), (ids, rows)

  def body(state):
    # The state is written outside the switch (see `_step_on_active_tiles`), grads included.
    index, new, (ids, rows) = _step_on_active_tiles(
      state[0] < num_chunks, functools.partial(step, state), tiling
    )
    grads = state[-1].at[ids].add(rows, mode="drop")
    return _scatter_rows(state[:-1], index, new) + (grads,)

  init = (
    jnp.zeros(starts.shape, jnp.int32),
    jnp.ones(inside.shape, attrs.dtype),
    ~inside,
    jnp.zeros(inside.shape, attrs.dtype),
    jnp.zeros_like(attrs),
  )
  grads = jax.lax.while_loop(cond, body, init)[-1]
  return grads, None, None, None, None


rasterize_tiles.defvjp(_rasterize_fwd, _rasterize_bwd)
