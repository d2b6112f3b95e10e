"""Exact compaction (`splatting.compaction`): what no camera draws is moved out, nothing changes."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tokengs_jax.gaussians import Gaussians
from tokengs_jax.splatting import RenderConfig, compaction, render, render_exact

HEIGHT, WIDTH = 40, 56
INTR = np.array([[44.0, 47.0, 27.0, 21.0], [50.0, 50.0, 28.0, 20.0]], np.float32)


def _w2c(x_shift):
  return np.array([[1, 0, 0, x_shift], [0, 1, 0, 0], [0, 0, 1, 3.0], [0, 0, 0, 1]], np.float32)


W2C = np.stack([_w2c(0.0), _w2c(0.4)])


def _scene(seed, num=600):
  """Gaussians around the cameras' view, many off-screen, behind them or transparent, with a few
  non-finite ones: about half are drawn."""
  rng = np.random.default_rng(seed)
  means = rng.uniform([-3, -2.5, -4], [3, 2.5, 4], (num, 3)).astype(np.float32)
  opacities = rng.uniform(0.05, 0.95, num).astype(np.float32)
  opacities[rng.uniform(size=num) < 0.15] = rng.uniform(0, 1 / 255, 1)[0]
  means[5] = np.nan
  return Gaussians(
    means=jnp.asarray(means),
    opacities=jnp.asarray(opacities),
    scales=jnp.asarray(rng.uniform(0.02, 0.25, (num, 3)), jnp.float32),
    quats=jnp.asarray(rng.normal(size=(num, 4)), jnp.float32),
    colors=jnp.asarray(rng.uniform(0, 1, (num, 3)), jnp.float32),
  )


def _drawn(g, w2c=W2C, intr=INTR):
  """[N] bool: the renderer draws it in some camera (its radii are 0 exactly where culled)."""
  out = render(g, w2c, intr, height=HEIGHT, width=WIDTH)
  return np.any(np.asarray(out.radii) > 0, axis=(0, 2))


@functools.partial(jax.jit, static_argnames="config")
def _loss_and_grad(g, weights, config=RenderConfig()):
  def loss(g):
    out = render(g, W2C, INTR, height=HEIGHT, width=WIDTH, config=config)
    image = jnp.concatenate([out.rgb, out.alpha, out.depth], axis=-1)
    return jnp.sum(image * weights), image

  return jax.value_and_grad(loss, has_aux=True)(g)


def test_drawable_keeps_every_gaussian_the_renderer_draws_and_drops_the_rest():
  g = _scene(0)
  drawn = _drawn(g)
  keep = np.asarray(compaction.drawable(g, W2C, INTR, height=HEIGHT, width=WIDTH))
  assert not np.any(drawn & ~keep)
  assert not keep[5]  # non-finite
  assert not np.any(keep & (np.asarray(g.opacities) < 1 / 255))
  assert 0.3 < keep.mean() < 0.7 and keep.sum() - drawn.sum() <= 0.05 * len(keep)  # few spare


def test_compacted_render_and_gradients_equal_the_full_ones_exactly():
  g = _scene(1)
  keep = np.asarray(compaction.drawable(g, W2C, INTR, height=HEIGHT, width=WIDTH))
  small = compaction.compact_for_cameras(g, W2C, INTR, height=HEIGHT, width=WIDTH)
  assert small.num_gaussians == compaction.bucket_size(keep.sum(), g.num_gaussians) == 512
  weights = np.random.default_rng(2).uniform(0, 1, (2, HEIGHT, WIDTH, 5)).astype(np.float32)
  (_, full), full_grads = _loss_and_grad(g, weights)
  (_, compacted), compacted_grads = _loss_and_grad(small, weights)
  np.testing.assert_array_equal(compacted, full)
  # the kept Gaussians' gradients, in order; every dropped one's is 0 in the full render
  for name in ("means", "opacities", "scales", "quats", "colors"):
    got, want = np.asarray(getattr(compacted_grads, name)), np.asarray(getattr(full_grads, name))
    np.testing.assert_array_equal(got[: keep.sum()], want[keep], err_msg=name)
    assert not np.any(got[keep.sum() :]) and not np.any(want[~keep]), name


def test_gradients_flow_through_compact_to_the_kept_gaussians():
  g = _scene(3)
  keep = compaction.drawable(g, W2C, INTR, height=HEIGHT, width=WIDTH)
  weights = np.random.default_rng(4).uniform(0, 1, (2, HEIGHT, WIDTH, 5)).astype(np.float32)

  def loss(g, compacted):
    if compacted:
      g, _ = compaction.compact(g, keep, 512)
    out = render(g, W2C, INTR, height=HEIGHT, width=WIDTH)
    return jnp.sum(jnp.concatenate([out.rgb, out.alpha, out.depth], axis=-1) * weights)

  full = jax.grad(loss)(g, False)
  through = jax.grad(loss)(g, True)
  for name in ("means", "opacities", "scales", "quats", "colors"):
    np.testing.assert_array_equal(getattr(through, name), getattr(full, name), err_msg=name)


def test_compact_keeps_order_pads_with_culled_stand_ins_and_reports_a_bucket_too_small():
  g = _scene(5, num=40)
  keep = np.zeros((2, 40), bool)
  keep[0, [3, 7, 9]] = True
  keep[1, [0, 39]] = True
  batched = jax.tree.map(lambda x: jnp.stack([x, x[::-1]]), g)
  out, fits = compaction.compact(batched, keep, 4)
  assert bool(fits)
  np.testing.assert_array_equal(out.means[0, :3], g.means[jnp.array([3, 7, 9])])
  np.testing.assert_array_equal(out.colors[1, :2], g.colors[jnp.array([39, 0])])
  assert not np.any(out.opacities[0, 3:]) and not np.any(out.opacities[1, 2:])
  stand_ins = jax.tree.map(lambda x: x[1, 2:], out)
  assert not np.any(_drawn(stand_ins))
  _, fits = compaction.compact(batched, keep, 2)
  assert not bool(fits)  # three kept in the first set: the caller must not use the cut set


def test_sets_and_broadcasting_keep_what_any_of_their_cameras_draws():
  g = _scene(6)
  one = np.asarray(compaction.drawable(g, W2C[:1], INTR[:1], height=HEIGHT, width=WIDTH))
  two = np.asarray(compaction.drawable(g, W2C[1:], INTR[1:], height=HEIGHT, width=WIDTH))
  both = np.asarray(compaction.drawable(g, W2C, INTR, height=HEIGHT, width=WIDTH))
  np.testing.assert_array_equal(both, one | two)
  # one set broadcast over two scenes, one camera each: kept where either draws it
  over = compaction.drawable(g, W2C[:, None], INTR[:, None], height=HEIGHT, width=WIDTH)
  np.testing.assert_array_equal(over, both)
  sets = jax.tree.map(lambda x: jnp.stack([x, x]), g)  # [2, N]: set v seen by camera v
  per_set = compaction.drawable(sets, W2C[:, None], INTR[:, None], height=HEIGHT, width=WIDTH)
  np.testing.assert_array_equal(per_set, np.stack([one, two]))


@pytest.mark.parametrize(
  ("count", "num", "size"), [(0, 4096, 256), (300, 4096, 512), (513, 1024, 1024), (900, 1000, 1000)]
)
def test_bucket_sizes_are_powers_of_two_or_the_full_set(count, num, size):
  assert compaction.bucket_size(count, num) == size


def test_render_exact_of_the_compacted_set_is_the_full_render():
  g = _scene(7, num=2000)
  small = compaction.compact_for_cameras(g, W2C, INTR, height=HEIGHT, width=WIDTH)
  assert small.num_gaussians < g.num_gaussians
  full = render_exact(g, W2C, INTR, height=HEIGHT, width=WIDTH)
  compacted = render_exact(small, W2C, INTR, height=HEIGHT, width=WIDTH)
  for name in ("rgb", "alpha", "depth"):
    np.testing.assert_array_equal(getattr(compacted, name), getattr(full, name), err_msg=name)
  np.testing.assert_array_equal(compacted.stats.num_visible, full.stats.num_visible)
