"""`render_exact` (`splatting.exact`): what overflowed is rendered again with a learnt budget,
never under a transformation nor past `BUDGET_LIMIT`."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from render_scenes import HEIGHT, INTR, W2C, WIDTH

from tokengs_jax.gaussians import Gaussians
from tokengs_jax.splatting import RenderBudgetWarning, RenderConfig, exact, render
from tokengs_jax.splatting.reference import render_dense


def _crowded_scene(num=64, seed=3):
  """Half-transparent Gaussians spread over the image: many tiles each, no pixel saturates."""
  rng = np.random.default_rng(seed)
  return Gaussians(
    means=rng.uniform([-1.0, -0.8, -0.5], [1.0, 0.8, 0.5], (num, 3)).astype(np.float32),
    opacities=np.full(num, 0.05, np.float32),
    scales=rng.uniform(0.2, 0.4, (num, 3)).astype(np.float32),
    quats=rng.normal(size=(num, 4)).astype(np.float32),
    colors=rng.uniform(0, 1, (num, 3)).astype(np.float32),
  )


def test_render_exact_rerenders_an_overflowing_scene(monkeypatch):
  g = _crowded_scene()
  tight = RenderConfig(max_intersections=64, chunk_size=8)
  with pytest.warns(RenderBudgetWarning, match="overflowed"):
    cut = render(g, W2C[None], INTR[None], height=HEIGHT, width=WIDTH, config=tight)
  assert bool(cut.stats.overflow[0]) and int(cut.stats.num_intersections[0]) > 64
  calls = []
  quiet = exact.jitted_render  # no warning: render_exact renders again instead
  monkeypatch.setattr(
    exact, "jitted_render", lambda *a, **k: calls.append(k["config"]) or quiet(*a, **k)
  )
  out = exact.render_exact(g, W2C[None], INTR[None], height=HEIGHT, width=WIDTH, config=tight)
  assert len(calls) == 2 and not bool(out.stats.overflow[0]) and not bool(out.stats.truncated[0])
  rgb, alpha, _ = render_dense(jax.tree.map(jnp.asarray, g), W2C, INTR, height=HEIGHT, width=WIDTH)
  np.testing.assert_allclose(out.rgb[0], rgb, atol=1e-5)
  np.testing.assert_allclose(out.alpha[0], alpha, atol=1e-5)
  assert float(jnp.max(jnp.abs(cut.rgb[0] - rgb))) > 1e-3  # the tight render was wrong
  # the learnt budget is where the next call of these shapes starts: one render
  again = exact.render_exact(g, W2C[None], INTR[None], height=HEIGHT, width=WIDTH, config=tight)
  assert len(calls) == 3 and calls[-1] == calls[1]
  np.testing.assert_array_equal(again.rgb, out.rgb)


def test_render_exact_refuses_transformations_and_impossible_budgets(monkeypatch):
  g = _crowded_scene()
  with pytest.raises(TypeError, match="outside|cannot run under"):
    jax.jit(lambda g: exact.render_exact(g, W2C[None], INTR[None], height=HEIGHT, width=WIDTH).rgb)(
      g
    )
  monkeypatch.setattr(exact, "BUDGET_LIMIT", 100)
  with pytest.raises(exact.RenderBudgetError, match="BUDGET_LIMIT"):
    exact.render_exact(
      g,
      W2C[None],
      INTR[None],
      height=HEIGHT,
      width=WIDTH,
      config=RenderConfig(max_intersections=64, chunk_size=8, tile_size=8),
    )
