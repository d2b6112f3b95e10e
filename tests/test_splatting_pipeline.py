"""`render` end to end: parity with gsplat 1.5.3 fixtures, tiled vs dense, gradients, batching,
jit, input validation, full-float32 matmuls."""

import functools

import hypothesis
import hypothesis.strategies as st
import jax
import jax.extend.core as jax_core
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import reference_fixture
from render_scenes import HEIGHT, INTR, NUM, W2C, WIDTH, random_scene

from tokengs_jax.gaussians import Gaussians
from tokengs_jax.splatting import RenderConfig, render
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

# Small chunks and few tiles per step so that a small scene takes many compacted loop steps.
SMALL_STEPS = RenderConfig(chunk_size=8, tiles_per_step=3)


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
