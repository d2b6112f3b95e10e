"""The compositor (`splatting.rasterize`): its halving ladder of block sizes; the backward replays
the lists the forward compacted and gives the gradients of the full lists; both block layouts
(pixel-major, the default, and Gaussian-major) composite the same sums."""

import dataclasses
import functools
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from render_scenes import HEIGHT, INTR, W2C, WIDTH, random_scene

from tokengs_jax.splatting import RenderConfig, pipeline, rasterize


def test_compositor_block_sizes_halve_down_to_eight():
  def sizes(tiles_per_step):
    tiling = rasterize.Tiling(32, 32, 8, 4, 4, 1, 32, tiles_per_step, 0.999, 1 / 255, 1e-4)
    return rasterize.step_sizes(tiling)

  assert sizes(128) == (128, 64, 32, 16, 8)
  assert sizes(35) == (35, 17, 8)
  assert sizes(3) == (3,)  # no ladder below 16: `test_chunking_...` compares the two paths


def _binned_scene(config):
  """A scene of opaque Gaussians whose pixels saturate part-way through their tiles' lists:
  (attrs [N, 10], TileBins of the sub-tiles, Tiling)."""
  g = random_scene(11, num=500)
  g = dataclasses.replace(g, opacities=np.maximum(g.opacities, 0.9))
  camera = jax.tree.map(
    lambda x: x[None],
    pipeline._project(g, W2C, INTR, 0.025, 125.0, height=HEIGHT, width=WIDTH, config=config),
  )
  tiles = -(-HEIGHT // config.tile_size) * -(-WIDTH // config.tile_size)
  ladder = config.budget_ladder(g.means.shape[0], tiles)
  bins = pipeline._bin(camera, height=HEIGHT, width=WIDTH, config=config, ladder=ladder)
  s = config.subtile_size
  tiling = rasterize.Tiling(
    HEIGHT, WIDTH, s, -(-WIDTH // s), -(-HEIGHT // s), 1, config.chunk_size,
    config.tiles_per_step, config.max_alpha, config.alpha_threshold, config.transmittance_stop,
  )  # fmt: skip
  return camera.attrs[0], jax.tree.map(lambda x: x[0], bins), tiling


@pytest.mark.parametrize("pixel_major", [True, False])
def test_compacted_backward_gives_the_full_lists_gradients(pixel_major):
  config = RenderConfig(chunk_size=8, tiles_per_step=5)  # many chunks, steps of several sizes
  attrs, bins, tiling = _binned_scene(config)
  tiling = tiling._replace(pixel_major=pixel_major)
  assert not bool(bins.shared_lists)  # split sub-tile lists: each tile owns its range
  lists = (bins.gaussian_ids, bins.tile_starts, bins.tile_ends)
  weights = np.random.default_rng(0).uniform(0, 1, (3, 4)).astype(np.float32)

  def grad(compact):
    def loss(attrs):
      accum, final_t, _, _ = rasterize.rasterize_tiles(
        attrs, *lists, tiling._replace(compact_backward=compact), bins.shared_lists
      )
      return jnp.sum(accum * weights[0]) + jnp.sum(final_t * weights[1, 0])

    return jax.jit(jax.grad(loss))(attrs)

  full, compacted = grad(False), grad(True)
  np.testing.assert_allclose(compacted, full, rtol=1e-5, atol=1e-6 * np.abs(full).max())
  # the compaction happened: the backward replays fewer chunks than the forward composited
  out, (ids, kept) = rasterize._forward(attrs, *lists, tiling, compact=True)
  assert int(jnp.sum(-(-kept // tiling.chunk_size))) < int(jnp.sum(out[2]))
  assert int(jnp.sum(kept)) < int(jnp.sum(jnp.minimum(
    bins.tile_ends - bins.tile_starts, out[2] * tiling.chunk_size
  )))  # fmt: skip
  # each compacted list is an in-order subsequence of its tile's list
  for t in range(bins.tile_starts.shape[0]):
    start, end = int(bins.tile_starts[t]), int(bins.tile_ends[t])
    listed = list(np.asarray(bins.gaussian_ids[start:end]))
    for gaussian in np.asarray(ids[start : start + int(kept[t])]):
      listed = listed[listed.index(gaussian) + 1 :]  # ValueError if out of order or absent


def test_block_layouts_composite_the_same_sums():
  """`RenderConfig.pixel_major` lays blocks out [tiles, chunk, pixels] instead of [tiles, pixels,
  chunk]: the same sums in another rounding, so images, gradients and stats agree to float noise."""
  g = random_scene(5, num=300)
  weights = np.random.default_rng(6).uniform(0, 1, (HEIGHT, WIDTH, 5)).astype(np.float32)

  @functools.partial(jax.jit, static_argnames="pixel_major")
  def loss_and_grad(g, pixel_major):
    config = RenderConfig(chunk_size=8, tiles_per_step=5, pixel_major=pixel_major)

    def loss(g):
      out = pipeline.render(g, W2C[None], INTR[None], height=HEIGHT, width=WIDTH, config=config)
      image = jnp.concatenate([out.rgb[0], out.alpha[0], out.depth[0]], axis=-1)
      return jnp.sum(image * weights), out

    return jax.value_and_grad(loss, has_aux=True)(g)

  (_, ref), ref_grads = loss_and_grad(g, False)
  (_, out), grads = loss_and_grad(g, True)
  for name in ("rgb", "alpha", "depth"):
    np.testing.assert_allclose(getattr(out, name), getattr(ref, name), atol=2e-6, rtol=0)
  for name in ("means", "scales", "quats", "opacities", "colors"):
    want = np.asarray(getattr(ref_grads, name))
    np.testing.assert_allclose(
      getattr(grads, name), want, rtol=1e-5, atol=1e-5 * np.abs(want).max(), err_msg=name
    )
  jax.tree.map(np.testing.assert_array_equal, out.stats, ref.stats)


def _loop_copies(hlo: str) -> list[tuple[int, ...]]:
  """Shapes of the `copy` instructions outside the entry computation (loop bodies, branches)."""
  shapes, in_entry = [], False
  for line in hlo.splitlines():
    if line and not line[0].isspace() and line.rstrip().endswith("{"):
      in_entry = line.startswith("ENTRY")
    match = re.search(r"= \w+\[([\d,]*)\]\S* copy\(", line)
    if match and not in_entry:
      shapes.append(tuple(int(d) for d in match.group(1).split(",") if d))
  return shapes


def test_loop_steps_do_not_copy_the_whole_state():
  """The per-tile state, the id list and the gradients are written outside the step's
  `lax.switch`: written inside, XLA:CPU copied each of them whole at every step (O(tiles) a step,
  O(tiles²) a render; issue 27). Checked on the compiled forward and forward+backward."""
  tiling = rasterize.Tiling(40, 56, 8, 7, 5, 1, 8, 16, 0.999, 1 / 255, 1e-4)  # 35 tiles, 2 sizes
  num, length = 37, 389
  whole = {tiling.tiles_x * tiling.tiles_y + 1, num, length}  # leading sizes of the state

  def composite(attrs, ids, starts, ends):
    return rasterize.rasterize_tiles(attrs, ids, starts, ends, tiling, False)

  def loss(*args):
    return jnp.sum(composite(*args)[0]) + jnp.sum(composite(*args)[1])

  args = (jnp.zeros((num, 10)), jnp.zeros((length,), jnp.int32)) + (jnp.zeros(35, jnp.int32),) * 2
  for fn in (composite, jax.grad(loss)):
    copies = _loop_copies(jax.jit(fn).lower(*args).compile().as_text())
    assert not [shape for shape in copies if shape and shape[0] in whole], copies
