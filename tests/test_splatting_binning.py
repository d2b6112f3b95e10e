"""Binning (`splatting.binning`): the ellipse-tile bound never exceeds a tile's true minimum;
sub-tile lists (`binning.split_tiles`) are the brute-force filter of their tiles' lists and render
what whole tiles render; the depth ranking (`binning.depth_order`) is the stable argsort."""

import dataclasses
import functools

import hypothesis
import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tokengs_jax.gaussians import Gaussians
from tokengs_jax.splatting import RenderConfig, binning, pipeline, render

HEIGHT, WIDTH, NUM = 40, 56, 64  # not tile multiples: sub-tiles of edge tiles lie outside
W2C = np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3.0], [0, 0, 0, 1]], np.float32)
INTR = np.array([44.0, 47.0, 27.0, 21.0], np.float32)


def _scene(seed, num=NUM):
  rng = np.random.default_rng(seed)
  return Gaussians(
    means=rng.uniform([-1.2, -1.0, -1.0], [1.2, 1.0, 1.0], (num, 3)).astype(np.float32),
    opacities=rng.uniform(0.05, 1.0, num).astype(np.float32),
    scales=np.exp(rng.uniform(np.log(0.01), np.log(0.3), (num, 3))).astype(np.float32),
    quats=rng.normal(size=(num, 4)).astype(np.float32),
    colors=rng.uniform(0, 1, (num, 3)).astype(np.float32),
  )


def _tile_and_split_bins(g, subtile_size):
  config = RenderConfig(subtile_size=subtile_size, min_intersections=2048)
  camera = pipeline._project(g, W2C, INTR, 0.025, 125.0, height=HEIGHT, width=WIDTH, config=config)
  proj = camera.proj
  tiling = dict(
    tiles_x=-(-WIDTH // 16),
    tiles_y=-(-HEIGHT // 16),
    height=HEIGHT,
    width=WIDTH,
    alpha_threshold=config.alpha_threshold,
  )
  bins = binning.bin_gaussians(
    proj.means2d,
    proj.radii,
    proj.depths,
    proj.cull_code == 0,
    proj.conics,
    g.opacities,
    tile_size=16,
    budget=2048,
    **tiling,
  )
  split = binning.split_tiles(
    bins, proj.means2d, proj.conics, g.opacities, tile_size=16, subtile_size=subtile_size, **tiling
  )
  return proj, bins, split, tiling


@pytest.mark.parametrize("subtile_size", [8, 4])
def test_split_lists_are_each_tile_list_filtered_in_order(subtile_size):
  g = _scene(0)
  proj, bins, split, tiling = _tile_and_split_bins(g, subtile_size)
  f = 16 // subtile_size
  sub_x = -(-WIDTH // subtile_size)
  assert split.gaussian_ids.shape == (f * f * bins.gaussian_ids.shape[0],)
  ids, starts, ends = map(np.asarray, (bins.gaussian_ids, bins.tile_starts, bins.tile_ends))
  sub_ids, sub_starts, sub_ends = map(
    np.asarray, (split.gaussian_ids, split.tile_starts, split.tile_ends)
  )
  assert sub_starts.shape == (-(-HEIGHT // subtile_size) * sub_x,)
  # every (sub-tile, Gaussian of its parent tile's list) pair, tested in one call
  listed, grid_x, grid_y, owner = [], [], [], []
  for index in range(sub_starts.shape[0]):
    y, x = divmod(index, sub_x)
    parent = (y // f) * tiling["tiles_x"] + x // f
    pairs = ids[starts[parent] : ends[parent]]
    listed.append(pairs)
    grid_x += [x] * pairs.size
    grid_y += [y] * pairs.size
    owner += [index] * pairs.size
    assert bool(split.tile_truncated[index]) == bool(bins.tile_truncated[parent])
  listed, owner = np.concatenate(listed), np.asarray(owner)
  reaches = np.asarray(
    binning.reaches_tile(
      proj.means2d[listed],
      proj.conics[listed],
      g.opacities[listed],
      jnp.asarray(grid_x),
      jnp.asarray(grid_y),
      tile_size=subtile_size,
      height=HEIGHT,
      width=WIDTH,
      alpha_threshold=tiling["alpha_threshold"],
    )
  )
  for index in range(sub_starts.shape[0]):
    expected = listed[(owner == index) & reaches]  # the parent's list order, filtered
    np.testing.assert_array_equal(sub_ids[sub_starts[index] : sub_ends[index]], expected)
  kept = int(reaches.sum())
  # the scene is small enough that some pairs do not reach a sub-tile: the split does cut work
  assert 0 < kept < f * f * (ends[-1] - starts[0])
  assert int(split.num_intersections) == int(bins.num_intersections)


@hypothesis.settings(max_examples=20, deadline=None, derandomize=True)
@hypothesis.given(seed=st.integers(0, 2**31 - 1))
def test_min_sigma_over_tile_is_the_minimum_over_its_pixels(seed):
  # The ellipse-tile test drops a (Gaussian, tile) pair only if this bound says no pixel centre of
  # the tile reaches the alpha threshold: it must never exceed the true minimum over the pixels.
  rng = np.random.default_rng(seed)
  height, width, tile = 40, 52, 16
  means = rng.uniform(-30, 80, (64, 2))
  basis = rng.normal(size=(64, 2, 2)) * np.exp(rng.uniform(-1, 3, (64, 1, 1)))
  cov = basis @ np.swapaxes(basis, 1, 2) + 0.3 * np.eye(2)
  inv = np.linalg.inv(cov)
  conics = np.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1)
  tile_x, tile_y = rng.integers(0, 4, 64), rng.integers(0, 3, 64)
  bound = np.asarray(
    binning.min_sigma_over_tile(
      jnp.asarray(means, jnp.float32),
      jnp.asarray(conics, jnp.float32),
      jnp.asarray(tile_x),
      jnp.asarray(tile_y),
      tile_size=tile,
      height=height,
      width=width,
    )
  )
  for i in range(64):
    cols = np.arange(tile_x[i] * tile, min(tile_x[i] * tile + tile, width)) + 0.5
    rows = np.arange(tile_y[i] * tile, min(tile_y[i] * tile + tile, height)) + 0.5
    dx = means[i, 0] - cols[None, :]
    dy = means[i, 1] - rows[:, None]
    sigma = 0.5 * (conics[i, 0] * dx * dx + conics[i, 2] * dy * dy) + conics[i, 1] * dx * dy
    # float32 rounding only, 10x below the 1e-3 slack binning adds before dropping a pair.
    assert bound[i] <= sigma.min() * (1 + 1e-4) + 1e-4, i
    inside = cols[0] <= means[i, 0] <= cols[-1] and rows[0] <= means[i, 1] <= rows[-1]
    assert (bound[i] == 0) == inside, i  # zero only where the mean lies inside the pixel rectangle


@functools.partial(jax.jit, static_argnames="config")
def _loss_and_grad(g, weights, config):
  def loss(g):
    out = render(g, W2C[None], INTR[None], height=HEIGHT, width=WIDTH, config=config)
    image = jnp.concatenate([out.rgb[0], out.alpha[0], out.depth[0]], axis=-1)
    return jnp.sum(image * weights), out

  return jax.value_and_grad(loss, has_aux=True)(g)


# every sub-tile shares (0; slow, the default run keeps the splitting case) / splits its list
@pytest.mark.parametrize("split_below", [pytest.param(0, marks=pytest.mark.slow), 10**6])
@pytest.mark.parametrize("budget", [None, 96])
def test_sub_tiles_render_what_whole_tiles_render(budget, split_below, monkeypatch):
  """Images, gradients and the overflow flag equal those of the unsplit tiles (float noise)."""
  monkeypatch.setattr(pipeline, "_SPLIT_MAX_PAIRS_PER_GAUSSIAN", split_below)
  monkeypatch.setattr(pipeline, "_SPLIT_MAX_PAIRS_PER_TILE", split_below)
  jax.clear_caches()  # the constants are read at trace time
  g = _scene(1)
  weights = np.random.default_rng(2).uniform(0, 1, (HEIGHT, WIDTH, 5)).astype(np.float32)
  base = RenderConfig(chunk_size=8, tiles_per_step=5, max_intersections=budget)
  (_, whole), whole_grads = _loss_and_grad(g, weights, dataclasses.replace(base, subtile_size=16))
  for subtile_size in (8, 4):
    config = dataclasses.replace(base, subtile_size=subtile_size)
    (_, out), grads = _loss_and_grad(g, weights, config)
    _assert_same_render(
      out, grads, whole, whole_grads, image_atol=2e-5, grad_tolerance=(1e-4, 1e-5)
    )
  if budget is not None:  # the tight budget does cut this scene, and the flag says so
    assert bool(whole.stats.truncated[0]) and bool(whole.stats.overflow[0])


def test_lists_split_where_gaussians_are_small_or_lists_short():
  """The split rule on the benchmark scenes' counts (65k Gaussians, all drawn): the fine scene at
  256² and 1024² splits (2.8 pairs per Gaussian; 11.1 but 178 a tile), the saturating TokenGS-like
  one at 256² and 1024² shares (11.3 and 2,893 a tile; 125 and 1,996 a tile)."""
  n = 2**16
  for pairs, tiles, split in ((181052, 256, True), (728031, 4096, True), (740000, 256, False),
                              (8175000, 4096, False)):  # fmt: skip
    assert bool(pipeline._split_pays(jnp.int32(pairs), jnp.int32(n), tiles)) == split, pairs


def _assert_same_render(out, grads, ref, ref_grads, *, image_atol, grad_tolerance):
  """`out` and its Gaussian gradients equal `ref`'s: images to `image_atol`, each gradient to
  `grad_tolerance` = (rtol, atol as a fraction of its largest reference entry), stats exactly.
  Depth, in scene units (about 3 here), also to 1e-5 relative: float32's summation-order noise."""
  for name, rtol in (("rgb", 0), ("alpha", 0), ("depth", 1e-5)):
    np.testing.assert_allclose(getattr(out, name), getattr(ref, name), atol=image_atol, rtol=rtol)
  rtol, atol_fraction = grad_tolerance
  for name in ("means", "scales", "quats", "opacities", "colors"):
    want = np.asarray(getattr(ref_grads, name))
    np.testing.assert_allclose(
      getattr(grads, name), want, rtol=rtol, atol=atol_fraction * np.abs(want).max(), err_msg=name
    )
  for name in ("truncated", "overflow", "num_intersections", "budget"):
    np.testing.assert_array_equal(getattr(out.stats, name), getattr(ref.stats, name))


@pytest.mark.parametrize("num", [1, 5, 1000, 2**16, 2**16 + 3])
def test_depth_order_is_the_stable_argsort(num):
  # ties, both zeros (tied, as the float sort ties them), negatives, the culled (+inf) and
  # subnormals (XLA:CPU compares them as 0); 2**16 is the largest N of the packed path, 2**16 + 3
  # takes the argsort.
  rng = np.random.default_rng(num)
  keys = rng.uniform(0.02, 9.0, num).astype(np.float32)
  keys[::7] = np.inf
  keys[1::13] = keys[0]
  keys[2::17] = -0.0
  keys[3::19] = 0.0
  keys[4::23] = -rng.uniform(0, 3, keys[4::23].shape)
  keys[5::29] = np.float32(1e-42)
  order = jax.jit(binning.depth_order)(jnp.asarray(keys))
  assert order.dtype == jnp.int32
  np.testing.assert_array_equal(order, jnp.argsort(jnp.asarray(keys), stable=True))
  normal = np.where(np.abs(keys) < 1e-37, 0.0, keys)
  np.testing.assert_array_equal(order, np.argsort(normal, kind="stable"))


def _walled_scene(seed, num=200, walls=4):
  """`walls` wide, opaque, camera-facing discs in front of `num - walls` random Gaussians: every
  pixel saturates on the discs, so a budget cut of the Gaussians behind changes nothing."""
  g = _scene(seed, num)
  rng = np.random.default_rng(seed)
  means, scales, opacities, quats = (np.array(x) for x in (g.means, g.scales, g.opacities, g.quats))
  means[:walls] = np.c_[rng.uniform(-0.1, 0.1, (walls, 2)), np.full(walls, -1.5)]
  means[walls:, 2] = np.abs(means[walls:, 2])
  scales[:walls], opacities[:walls], quats[:walls] = (3.0, 3.0, 0.01), 0.999, (1, 0, 0, 0)
  return dataclasses.replace(g, means=means, scales=scales, opacities=opacities, quats=quats)


@pytest.mark.parametrize("saturating", [True, False])
def test_rebin_on_overflow_renders_what_the_ladder_renders(saturating):
  """`rebin_on_overflow`: the first binning at B/4 is kept where its cut lies behind saturated
  pixels and re-done at the size that holds every pair where it could change a pixel; images,
  gradients and stats are those of the count-chosen ladder size (float noise)."""
  g = _walled_scene(3) if saturating else _scene(1, num=200)
  weights = np.random.default_rng(2).uniform(0, 1, (HEIGHT, WIDTH, 5)).astype(np.float32)
  base = RenderConfig(chunk_size=8, tiles_per_step=5, max_intersections=1024, min_intersections=8)
  ladder = base.budget_ladder(200, -(-HEIGHT // 16) * -(-WIDTH // 16))
  (_, first), _ = _loss_and_grad(g, weights, dataclasses.replace(base, max_intersections=ladder[0]))
  needed = int(first.stats.num_intersections[0])
  assert ladder[0] < needed <= ladder[-1]  # the count-based ladder sorts above B/4
  assert bool(first.stats.truncated[0]) and bool(first.stats.overflow[0]) != saturating
  (_, ref), ref_grads = _loss_and_grad(g, weights, base)
  (_, out), grads = _loss_and_grad(g, weights, dataclasses.replace(base, rebin_on_overflow=True))
  _assert_same_render(out, grads, ref, ref_grads, image_atol=1e-6, grad_tolerance=(1e-5, 1e-6))
  if not saturating:  # the overflowing first binning was not used
    assert float(jnp.max(jnp.abs(first.rgb - ref.rgb))) > 1e-3
