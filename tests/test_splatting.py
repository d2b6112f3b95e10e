"""Renderer parity with gsplat 1.5.3 fixtures, tiled vs dense, gradients, batching, jit."""

import functools

import hypothesis
import hypothesis.strategies as st
import jax
import jax.extend.core as jax_core
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import reference_fixture

from tokengs_jax.gaussians import Gaussians
from tokengs_jax.splatting import RenderBudgetWarning, RenderConfig, binning, exact, render
from tokengs_jax.splatting.reference import render_dense

FIELDS = ("means", "quats", "scales", "opacities", "colors")


def _intrinsics(ks):
  ks = np.asarray(ks)
  return np.stack([ks[..., 0, 0], ks[..., 1, 1], ks[..., 0, 2], ks[..., 1, 2]], axis=-1)


def _fixture_gaussians(data):
  return Gaussians(
    means=data["means"],
    opacities=data["opacities"],
    scales=data["scales"],
    quats=data["quats"],
    colors=data["colors"],
  )


def _assert_grads_close(grads, data, rtol=1e-3):
  for name in FIELDS:
    ours, ref = np.asarray(getattr(grads, name)), data["grad_" + name]
    assert np.all(np.isfinite(ours)), name
    np.testing.assert_allclose(ours, ref, rtol=rtol, atol=rtol * np.abs(ref).max(), err_msg=name)


@pytest.fixture(scope="module")
def rgbed():
  return dict(np.load(reference_fixture("gsplat_rgbed_2cam.npz")))


@pytest.fixture(scope="module")
def render200():
  return dict(np.load(reference_fixture("gsplat_render_200.npz")))


def _render_rgbed(gaussians, data):
  return render(
    gaussians,
    data["viewmats"],
    _intrinsics(data["Ks"]),
    height=int(data["height"]),
    width=int(data["width"]),
    background=data["backgrounds"],
    near=float(data["near"]),
    far=float(data["far"]),
  )


def test_rgbed_fixture_images(rgbed):
  out = _render_rgbed(_fixture_gaussians(rgbed), rgbed)
  assert out.rgb.shape == (2, 48, 64, 3) and out.depth.shape == (2, 48, 64, 1)
  np.testing.assert_allclose(out.rgb, rgbed["render_colors"], atol=1e-4, rtol=0)
  np.testing.assert_allclose(out.alpha, rgbed["render_alphas"], atol=1e-4, rtol=0)
  np.testing.assert_allclose(out.depth, rgbed["render_depth"], atol=1e-4, rtol=0)
  assert not np.any(out.stats.overflow)


def test_rgbed_fixture_projection(rgbed):
  out = _render_rgbed(_fixture_gaussians(rgbed), rgbed)
  hit = rgbed["radii"][..., 0] > 0
  np.testing.assert_array_equal(np.asarray(out.radii)[..., 0] > 0, hit)
  firm = hit & ~rgbed["radii_fragile"]
  np.testing.assert_array_equal(np.asarray(out.radii)[firm], rgbed["radii"][firm])
  np.testing.assert_allclose(np.asarray(out.means2d)[hit], rgbed["means2d"][hit], atol=1e-4)
  np.testing.assert_allclose(np.asarray(out.depths)[hit], rgbed["depths"][hit], atol=1e-5)


def test_rgbed_fixture_gradients(rgbed):
  def loss(g):
    out = _render_rgbed(g, rgbed)
    return (
      jnp.sum(rgbed["w_rgb"] * out.rgb)
      + jnp.sum(rgbed["w_alpha"] * out.alpha)
      + jnp.sum(rgbed["w_depth"] * out.depth)
    )

  _assert_grads_close(jax.grad(loss)(_fixture_gaussians(rgbed)), rgbed)


def test_render200_fixture_images_and_gradients(render200):
  data = render200
  cam = (data["viewmat"][None], _intrinsics(data["K"])[None])

  def run(g):
    return render(g, *cam, height=48, width=64, background=data["background"], near=0.01, far=1e10)

  out = run(_fixture_gaussians(data))
  np.testing.assert_allclose(out.rgb[0], data["render_colors"], atol=1e-4, rtol=0)
  np.testing.assert_allclose(out.alpha[0], data["render_alphas"], atol=1e-4, rtol=0)
  # This fixture's radii are plain 3.33 sigma ones (no opacity): only the culled set must agree.
  np.testing.assert_array_equal(np.asarray(out.radii[0, :, 0]) > 0, data["radii"][:, 0] > 0)

  def loss(g):
    out = run(g)
    return jnp.sum(data["loss_w_rgb"] * out.rgb[0]) + jnp.sum(data["loss_w_alpha"] * out.alpha[0])

  _assert_grads_close(jax.grad(loss)(_fixture_gaussians(data)), data)


# ---- random scenes: tiled vs dense -------------------------------------------------------------

HEIGHT, WIDTH, NUM = 40, 52, 48  # not tile multiples: exercises edge-tile padding
# Small chunks and few tiles per step so that a small scene takes many compacted loop steps.
SMALL_STEPS = RenderConfig(chunk_size=8, tiles_per_step=3)
W2C = np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3.0], [0, 0, 0, 1]], np.float32)
INTR = np.array([44.0, 47.0, 25.0, 21.0], np.float32)


def random_scene(seed, num=NUM, dtype=np.float32):
  rng = np.random.default_rng(seed)
  return Gaussians(
    means=rng.uniform([-1.2, -1.0, -1.0], [1.2, 1.0, 1.0], (num, 3)).astype(dtype),
    opacities=rng.uniform(0.05, 1.0, num).astype(dtype),
    scales=np.exp(rng.uniform(np.log(0.02), np.log(0.4), (num, 3))).astype(dtype),
    quats=rng.normal(size=(num, 4)).astype(dtype),
    colors=rng.uniform(0, 1, (num, 3)).astype(dtype),
  )


@functools.partial(jax.jit, static_argnames="config")
def _tiled_loss_and_grad(g, weights, config):
  def loss(g):
    out = render(
      g,
      W2C[None],
      INTR[None],
      height=HEIGHT,
      width=WIDTH,
      background=weights[0, 0, :3],
      config=config,
    )
    return jnp.sum(out.rgb[0] * weights[..., :3]) + jnp.sum(
      out.alpha[0] * weights[..., 3:4]
    ) + jnp.sum(out.depth[0] * weights[..., 4:]), out

  return jax.value_and_grad(loss, has_aux=True)(g)


@jax.jit
def _dense_loss_and_grad(g, weights):
  def loss(g):
    rgb, alpha, depth = render_dense(
      g, W2C, INTR, height=HEIGHT, width=WIDTH, background=weights[0, 0, :3]
    )
    return jnp.sum(rgb * weights[..., :3]) + jnp.sum(alpha * weights[..., 3:4]) + jnp.sum(
      depth * weights[..., 4:]
    ), (rgb, alpha, depth)

  return jax.value_and_grad(loss, has_aux=True)(g)


@hypothesis.settings(max_examples=6, deadline=None, derandomize=True)
@hypothesis.given(seed=st.integers(0, 2**31 - 1))
def test_tiled_matches_dense_reference(seed):
  g = random_scene(seed)
  weights = np.random.default_rng(seed + 1).uniform(0, 1, (HEIGHT, WIDTH, 5)).astype(np.float32)
  (_, out), grads = _tiled_loss_and_grad(g, weights, SMALL_STEPS)
  (_, (rgb, alpha, depth)), dense_grads = _dense_loss_and_grad(g, weights)
  np.testing.assert_allclose(out.rgb[0], rgb, atol=1e-4, rtol=0)
  np.testing.assert_allclose(out.alpha[0], alpha, atol=1e-4, rtol=0)
  np.testing.assert_allclose(out.depth[0], depth, atol=1e-4 * 5, rtol=0)  # depths reach ~4
  for name in FIELDS:
    ref = np.asarray(getattr(dense_grads, name))
    np.testing.assert_allclose(
      getattr(grads, name), ref, rtol=1e-3, atol=1e-3 * np.abs(ref).max(), err_msg=name
    )


def test_chunking_and_tile_scheduling_do_not_change_the_result():
  g = random_scene(7)
  weights = np.random.default_rng(8).uniform(0, 1, (HEIGHT, WIDTH, 5)).astype(np.float32)
  (loss_small, out_small), grads_small = _tiled_loss_and_grad(g, weights, SMALL_STEPS)
  (loss_default, out_default), grads_default = _tiled_loss_and_grad(g, weights, RenderConfig())
  np.testing.assert_allclose(out_small.rgb, out_default.rgb, atol=2e-6)
  np.testing.assert_allclose(
    grads_small.means, grads_default.means, rtol=1e-4, atol=1e-5 * np.abs(grads_default.means).max()
  )
  assert int(out_small.stats.tile_chunks[0]) > int(out_default.stats.tile_chunks[0])
  # 8-pixel tiles (a RenderConfig option, not the default): same image and gradients
  (_, out_tile8), grads_tile8 = _tiled_loss_and_grad(
    g, weights, RenderConfig(tile_size=8, tiles_per_step=64)
  )
  np.testing.assert_allclose(out_tile8.rgb, out_default.rgb, atol=2e-6)
  np.testing.assert_allclose(
    grads_tile8.means, grads_default.means, rtol=1e-4, atol=1e-5 * np.abs(grads_default.means).max()
  )


def test_float64_finite_difference_gradients():
  with jax.enable_x64(True):
    g = random_scene(3, num=12, dtype=np.float64)
    weights = np.random.default_rng(4).uniform(0, 1, (HEIGHT, WIDTH, 5))

    def loss(g):
      out = render(
        g,
        W2C[None].astype(np.float64),
        INTR[None].astype(np.float64),
        height=HEIGHT,
        width=WIDTH,
        config=SMALL_STEPS,
      )
      assert out.rgb.dtype == jnp.float64
      return jnp.sum(out.rgb[0] * weights[..., :3]) + jnp.sum(out.depth[0] * weights[..., 4:])

    grads = jax.grad(loss)(g)
    rng = np.random.default_rng(5)
    for _ in range(3):
      direction = jax.tree.map(lambda x: rng.normal(size=x.shape), g)
      eps = 1e-6
      plus = jax.tree.map(lambda x, d: x + eps * d, g, direction)
      minus = jax.tree.map(lambda x, d: x - eps * d, g, direction)
      numeric = (loss(plus) - loss(minus)) / (2 * eps)
      analytic = sum(
        jnp.vdot(a, d) for a, d in zip(jax.tree.leaves(grads), jax.tree.leaves(direction))
      )
      np.testing.assert_allclose(analytic, numeric, rtol=1e-5)


def test_batch_and_multi_camera_shapes_match_single_renders():
  scenes = jax.tree.map(
    lambda a, b: np.stack([a, b]), random_scene(1, num=16), random_scene(2, num=16)
  )
  shift = np.eye(4, dtype=np.float32)
  shift[0, 3] = 0.3
  w2c = np.broadcast_to(np.stack([W2C, shift @ W2C, W2C]), (2, 3, 4, 4))
  intr = np.broadcast_to(INTR, (2, 3, 4))
  backgrounds = np.random.default_rng(0).uniform(0, 1, (2, 3, 3)).astype(np.float32)
  out = render(scenes, w2c, intr, height=HEIGHT, width=WIDTH, background=backgrounds)
  assert out.rgb.shape == (2, 3, HEIGHT, WIDTH, 3) and out.alpha.shape == (2, 3, HEIGHT, WIDTH, 1)
  assert out.means2d.shape == (2, 3, 16, 2) and out.radii.shape == (2, 3, 16, 2)
  assert out.stats.overflow.shape == (2, 3)
  for b in range(2):
    for v in range(3):
      single = render(
        jax.tree.map(lambda x: x[b], scenes),
        w2c[b, v][None],
        intr[b, v][None],
        height=HEIGHT,
        width=WIDTH,
        background=backgrounds[b, v],
      )
      np.testing.assert_allclose(out.rgb[b, v], single.rgb[0], atol=1e-6)
      np.testing.assert_allclose(out.depth[b, v], single.depth[0], atol=1e-5)
  # One scene seen by a [V] camera stack with a shared [3] background broadcasts too.
  shared = render(
    random_scene(1, num=16),
    w2c[0],
    intr[0],
    height=HEIGHT,
    width=WIDTH,
    background=backgrounds[0, 0],
  )
  assert shared.rgb.shape == (3, HEIGHT, WIDTH, 3)
  single = render(
    random_scene(1, num=16),
    w2c[0, 1][None],
    intr[0, 1][None],
    height=HEIGHT,
    width=WIDTH,
    background=backgrounds[0, 0],
  )
  np.testing.assert_allclose(shared.rgb[1], single.rgb[0], atol=1e-6)


def test_grad_under_jit_and_vmap_agree_with_eager_grad():
  g = random_scene(11, num=16)

  def loss(g, w2c):
    return jnp.sum(render(g, w2c[None], INTR[None], height=HEIGHT, width=WIDTH).rgb)

  eager = jax.grad(loss)(g, W2C)
  jitted = jax.jit(jax.grad(loss))(g, W2C)
  for a, b in zip(jax.tree.leaves(eager), jax.tree.leaves(jitted)):
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5 * np.abs(a).max())
  per_camera = jax.vmap(jax.grad(loss), in_axes=(None, 0))(g, np.stack([W2C, W2C]))
  np.testing.assert_allclose(
    per_camera.means[1], eager.means, rtol=1e-5, atol=1e-5 * np.abs(eager.means).max()
  )


def test_means2d_carry_gradient_for_visibility_losses():
  g = random_scene(12, num=16)
  grad = jax.grad(
    lambda m: jnp.sum(
      render(
        Gaussians(m, g.opacities, g.scales, g.quats, g.colors),
        W2C[None],
        INTR[None],
        height=HEIGHT,
        width=WIDTH,
      ).means2d[0, :, 0]
    )
  )(g.means)
  # d u / d x = fx / z for a camera looking down +z.
  z = g.means[:, 2] + 3.0
  np.testing.assert_allclose(grad[:, 0], INTR[0] / z, rtol=1e-5)


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


# ---- exactness: render_exact re-renders what overflowed ------------------------------------------


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


def test_budget_ladder_sorts_small_scenes_in_a_small_buffer():
  config = RenderConfig()
  assert config.budget_ladder(65536, 256) == (262144, 524288, 1048576)
  assert config.budget_ladder(100, 256) == (4096,)  # small scenes: one size
  assert config.intersection_budget(100, 4) == 416  # never above N x tiles (chunk multiple)
  # whichever ladder step a scene is binned at, the image is the same
  g = random_scene(5)
  tiles = 3 * 4
  ladder = RenderConfig(min_intersections=32, chunk_size=8)
  single = RenderConfig(min_intersections=NUM * tiles, chunk_size=8)
  assert len(ladder.budget_ladder(NUM, tiles)) == 3 and len(single.budget_ladder(NUM, tiles)) == 1
  a = render(g, W2C[None], INTR[None], height=HEIGHT, width=WIDTH, config=ladder)
  b = render(g, W2C[None], INTR[None], height=HEIGHT, width=WIDTH, config=single)
  assert int(a.stats.num_intersections[0]) <= ladder.budget_ladder(NUM, tiles)[1]  # a lower step
  assert not bool(a.stats.truncated[0])
  np.testing.assert_array_equal(a.rgb, b.rgb)
  np.testing.assert_array_equal(a.depth, b.depth)


# ---- precision: every dot of the renderer (and losses / metrics) at full float32 ----------------


def _dot_precisions(jaxpr):
  """Precision of every dot_general / conv in a closed jaxpr, sub-jaxprs included."""
  found = []
  for eqn in jaxpr.eqns:
    if eqn.primitive.name in ("dot_general", "conv_general_dilated"):
      found.append(eqn.params["precision"])
    for value in eqn.params.values():
      for sub in value if isinstance(value, (tuple, list)) else (value,):
        if isinstance(sub, jax_core.ClosedJaxpr):
          found += _dot_precisions(sub.jaxpr)
        elif isinstance(sub, jax_core.Jaxpr):
          found += _dot_precisions(sub)
  return found


def test_renderer_losses_and_metrics_pin_full_float32_matmuls():
  from tokengs_jax import losses, metrics

  highest = (jax.lax.Precision.HIGHEST, jax.lax.Precision.HIGHEST)
  g = random_scene(0)
  images = jnp.zeros((1, HEIGHT, WIDTH, 3))

  def loss(g):
    out = render(g, W2C[None], INTR[None], height=HEIGHT, width=WIDTH)
    config = losses.LossConfig(lambda_ssim=0.2, lambda_vis=0.0)
    value, _ = losses.render_loss(out.rgb, images, config)
    vis = losses.visibility_loss(g.means, W2C[None], INTR[None], HEIGHT, WIDTH)
    return value + vis + metrics.ssim(out.rgb, images).sum()

  precisions = _dot_precisions(jax.make_jaxpr(jax.grad(loss))(g).jaxpr)
  assert len(precisions) >= 10  # projection, compositor forward and backward, SSIM, visibility
  assert all(p == highest for p in precisions), precisions


# ---- input validation (trace time, ValueError naming the argument) -------------------------------


@pytest.mark.parametrize(
  "change, match",
  [
    (dict(intrinsics=INTR[None, :3]), "intrinsics must be"),
    (dict(intrinsics=np.eye(3, dtype=np.float32), world_to_camera=np.stack([W2C] * 3)), "3x3 K"),
    (dict(world_to_camera=W2C), "view axis"),
    (dict(intrinsics=np.stack([INTR] * 2)), "number of views"),
    (dict(colors=np.zeros((NUM, 4), np.float32)), r"Gaussians.colors must be \[..., N, 3\]"),
    (dict(opacities=np.zeros((NUM, 1), np.float32)), "Gaussians.opacities"),
    (dict(scales=np.zeros((NUM - 1, 3), np.float32)), "N = "),
    (dict(height=0), "height must be a positive int"),
    (dict(width=-3), "width must be a positive int"),
    (dict(height=40.0), "height must be a positive int"),
    (dict(background=np.zeros(4, np.float32)), "background"),
  ],
)
def test_render_refuses_bad_inputs_by_name(change, match):
  g = random_scene(0)
  fields = {name: change.pop(name) for name in FIELDS if name in change}
  args = dict(
    gaussians=Gaussians(**{**vars(g), **fields}),
    world_to_camera=W2C[None],
    intrinsics=INTR[None],
    height=HEIGHT,
    width=WIDTH,
  )
  args.update(change)
  with pytest.raises(ValueError, match=match):
    render(**args)


@pytest.mark.parametrize("knob", ["tile_size", "chunk_size", "tiles_per_step"])
def test_render_config_refuses_non_positive_sizes(knob):
  with pytest.raises(ValueError, match=knob):
    RenderConfig(**{knob: 0})


def test_compositor_block_sizes_halve_down_to_eight():
  from tokengs_jax.splatting import rasterize

  def sizes(tiles_per_step):
    tiling = rasterize.Tiling(32, 32, 8, 4, 4, 1, 32, tiles_per_step, 0.999, 1 / 255, 1e-4)
    return rasterize.step_sizes(tiling)

  assert sizes(128) == (128, 64, 32, 16, 8)
  assert sizes(35) == (35, 17, 8)
  assert sizes(3) == (3,)  # no ladder below 16: `test_chunking_...` compares the two paths
