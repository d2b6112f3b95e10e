"""Numerical stress suite: degenerate Gaussians and cameras. Every case asserts finite outputs and
gradients plus its documented behaviour (what is culled, what is reported)."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tokengs_jax.gaussians import Gaussians
from tokengs_jax.splatting import RenderConfig, render
from tokengs_jax.splatting.reference import render_dense

H, W, NUM = 24, 36, 8
W2C = np.eye(4, dtype=np.float32)  # camera at the origin looking down +z
INTR = np.array([30.0, 32.0, 18.0, 12.0], np.float32)
BACKGROUND = np.array([0.2, 0.4, 0.6], np.float32)
NEAR, FAR = 0.025, 125.0


def scene(means=None, opacities=None, scales=None, quats=None, colors=None, num=NUM):
  """num Gaussians: the given leading ones, then transparent padding (culled by opacity)."""
  base = Gaussians(
    means=np.tile([[0.0, 0.0, 3.0]], (num, 1)),
    opacities=np.zeros(num),
    scales=np.full((num, 3), 0.2),
    quats=np.tile([[1.0, 0, 0, 0]], (num, 1)),
    colors=np.tile([[0.9, 0.5, 0.1]], (num, 1)),
  )
  given = dict(means=means, opacities=opacities, scales=scales, quats=quats, colors=colors)
  fields = {}
  for name in given:
    value = np.array(getattr(base, name), np.float32)
    if given[name] is not None:
      new = np.asarray(given[name], np.float32)
      value[: len(new)] = new
    fields[name] = value
  return Gaussians(**fields)


def _loss(out):
  return jnp.sum(out.rgb) + jnp.sum(out.alpha) + jnp.sum(out.depth) + jnp.sum(out.means2d * 1e-3)


@functools.partial(jax.jit, static_argnames="config")
def run(g, config=RenderConfig()):
  """Renders and differentiates a [NUM] scene; returns (result, grads)."""

  def loss(g):
    out = render(
      g,
      W2C[None],
      INTR[None],
      height=H,
      width=W,
      background=BACKGROUND,
      near=NEAR,
      far=FAR,
      config=config,
    )
    return _loss(out), out

  (_, out), grads = jax.value_and_grad(loss, has_aux=True)(g)
  return jax.tree.map(lambda x: x[0], out), grads


def assert_finite(out, grads):
  for leaf in jax.tree.leaves((out, grads)):
    assert np.all(np.isfinite(np.asarray(leaf, np.float64))), leaf


def assert_background(out):
  np.testing.assert_allclose(out.rgb, np.broadcast_to(BACKGROUND, (H, W, 3)), atol=1e-7)
  np.testing.assert_allclose(out.alpha, 0.0, atol=1e-7)
  np.testing.assert_allclose(out.depth, 0.0, atol=1e-7)


def assert_matches_dense(g, out):
  rgb, alpha, depth = render_dense(
    jax.tree.map(jnp.asarray, g),
    W2C,
    INTR,
    height=H,
    width=W,
    background=BACKGROUND,
    near=NEAR,
    far=FAR,
  )
  np.testing.assert_allclose(out.rgb, rgb, atol=1e-4)
  np.testing.assert_allclose(out.alpha, alpha, atol=1e-4)
  np.testing.assert_allclose(out.depth, depth, atol=1e-4 * max(1.0, float(np.max(depth))))


def test_behind_camera_is_culled_by_depth():
  out, grads = run(scene(means=[[0, 0, -3.0]], opacities=[0.9]))
  assert_finite(out, grads)
  assert int(out.stats.num_culled_depth) == 1 and int(out.radii[0, 0]) == 0
  assert_background(out)
  np.testing.assert_allclose(
    grads.means[0], [1e-3 * INTR[0] / -3.0, 1e-3 * INTR[1] / -3.0, grads.means[0, 2]], rtol=1e-4
  )  # means2d still differentiable


def test_centre_on_the_camera_plane_is_culled_and_finite():
  out, grads = run(scene(means=[[0.1, 0.0, 0.0]], opacities=[0.9]))
  assert_finite(out, grads)
  assert int(out.stats.num_culled_depth) == 1
  assert_background(out)


def test_near_plane_is_inclusive():
  out, grads = run(
    scene(means=[[0, 0, NEAR], [0, 0, NEAR * 0.99]], opacities=[0.9, 0.9], scales=[[1e-3] * 3] * 2)
  )
  assert_finite(out, grads)
  assert int(out.radii[0, 0]) > 0 and int(out.radii[1, 0]) == 0
  assert int(out.stats.num_culled_depth) == 1


def test_beyond_far_plane_is_culled():
  out, grads = run(scene(means=[[0, 0, FAR * 1.01]], opacities=[0.9], scales=[[50.0] * 3]))
  assert_finite(out, grads)
  assert int(out.stats.num_culled_depth) == 1
  assert_background(out)


def test_centre_outside_image_border_still_contributes():
  # Centre 0.5 px left of the image, radius several px: the left column must see it.
  u = -0.5
  x = (u - INTR[2]) / INTR[0] * 3.0
  g = scene(means=[[x, 0, 3.0]], opacities=[0.9], scales=[[0.1] * 3])
  out, grads = run(g)
  assert_finite(out, grads)
  assert int(out.stats.num_visible) == 1 and float(out.alpha[12, 0, 0]) > 0.3
  assert_matches_dense(g, out)


def test_far_outside_the_frustum_is_culled():
  out, grads = run(scene(means=[[40.0, 0, 3.0], [0, -1e6, 3.0]], opacities=[0.9, 0.9]))
  assert_finite(out, grads)
  assert int(out.stats.num_culled_frustum) == 2
  assert_background(out)


def test_huge_coordinates_are_finite():
  out, grads = run(scene(means=[[1e30, 1e30, 1e30], [0, 0, 1e20]], opacities=[0.9, 0.9]))
  assert_finite(out, grads)
  assert int(out.stats.num_visible) == 0
  assert_background(out)


@pytest.mark.parametrize("scale", [1e-8, 1e-4, 1.0, 1e2, 1e4])
def test_scales_across_twelve_decades(scale):
  g = scene(means=[[0.05, 0.02, 3.0]], opacities=[0.8], scales=[[scale] * 3])
  out, grads = run(g)
  assert_finite(out, grads)
  assert int(out.stats.num_visible) == 1
  assert_matches_dense(g, out)
  if scale >= 1e2:  # covers the image: every pixel at the 0.8 opacity cap of its exp(-sigma)
    np.testing.assert_allclose(out.alpha, 0.8, atol=1e-3)


def test_tiny_gaussian_is_an_eps2d_blob():
  # A point Gaussian centred on a pixel centre renders its opacity there (cov2d = eps2d I).
  u, v = 10.5, 7.5
  g = scene(
    means=[[(u - INTR[2]) / INTR[0] * 3, (v - INTR[3]) / INTR[1] * 3, 3.0]],
    opacities=[0.7],
    scales=[[1e-8] * 3],
  )
  out, grads = run(g)
  assert_finite(out, grads)
  np.testing.assert_allclose(out.alpha[7, 10, 0], 0.7, rtol=1e-4)
  np.testing.assert_allclose(out.alpha[7, 11, 0], 0.7 * np.exp(-0.5 / 0.3), rtol=1e-3)


def test_extreme_anisotropy():
  # Needles (axis ratios 2e7) at oblique angles. Much longer needles seen edge-on make the 2D
  # determinant a float32 cancellation (a c - b^2 of 1e12-sized terms), as in gsplat: finite, but
  # two compilations of the same maths may then disagree by ~1e-2.
  g = scene(
    means=[[0, 0, 3.0], [0.2, 0.1, 2.5]],
    opacities=[0.9, 0.6],
    scales=[[1e-7, 0.05, 2.0], [2.0, 1e-7, 1e-7]],
    quats=[[0.9, 0.3, 0.2, 0.1], [0.5, 0.5, -0.5, 0.5]],
  )
  out, grads = run(g)
  assert_finite(out, grads)
  assert_matches_dense(g, out)


def test_unnormalised_quaternions_render_as_normalised():
  q = np.array([[0.7, 0.2, -0.4, 0.3]], np.float32)
  kw = dict(means=[[0.1, 0, 3.0]], opacities=[0.9], scales=[[0.5, 0.05, 0.1]])
  out_unit, _ = run(scene(quats=q / np.linalg.norm(q), **kw))
  out_big, grads = run(scene(quats=q * 1e3, **kw))
  assert_finite(out_big, grads)
  np.testing.assert_allclose(out_big.rgb, out_unit.rgb, atol=1e-5)


def test_zero_quaternion_is_the_identity_rotation():
  kw = dict(means=[[0.1, 0, 3.0]], opacities=[0.9], scales=[[0.5, 0.05, 0.1]])
  out_zero, grads = run(scene(quats=[[0.0, 0, 0, 0]], **kw))
  out_identity, _ = run(scene(quats=[[1.0, 0, 0, 0]], **kw))
  assert_finite(out_zero, grads)
  np.testing.assert_allclose(out_zero.rgb, out_identity.rgb, atol=1e-6)


def test_opacity_zero_and_below_threshold_are_culled():
  out, grads = run(scene(means=[[0, 0, 3.0]] * 3, opacities=[0.0, 1 / 255 * 0.999, 1 / 255 * 1.01]))
  assert_finite(out, grads)
  # The padding (opacity 0) counts too: NUM - 1 culled, the one just above threshold survives.
  assert int(out.stats.num_culled_opacity) == NUM - 1 and int(out.stats.num_visible) == 1


def test_opacity_one_is_capped():
  g = scene(means=[[0, 0, 3.0], [0, 0, 3.5]], opacities=[1.0, 1.0], scales=[[5.0] * 3] * 2)
  out, grads = run(g)
  assert_finite(out, grads)
  # At the centre the first layer's alpha is capped at 0.999 and the second would take T to
  # 1e-6 <= 1e-4: the pixel stops before it.
  np.testing.assert_allclose(out.alpha[12, 18], 0.999, atol=2e-6)
  np.testing.assert_allclose(out.depth[12, 18], 3.0, atol=1e-5)
  assert float(out.alpha.max()) < 1.0 - 1e-4  # T never goes to or below the stop value
  assert_matches_dense(g, out)


def test_zero_gaussians_render_the_background():
  empty = Gaussians(
    means=np.zeros((0, 3), np.float32),
    opacities=np.zeros((0,), np.float32),
    scales=np.zeros((0, 3), np.float32),
    quats=np.zeros((0, 4), np.float32),
    colors=np.zeros((0, 3), np.float32),
  )
  out = render(empty, W2C[None], INTR[None], height=H, width=W, background=BACKGROUND)
  assert out.means2d.shape == (1, 0, 2)
  assert_background(jax.tree.map(lambda x: x[0], out))
  grads = jax.grad(lambda g: jnp.sum(render(g, W2C[None], INTR[None], height=H, width=W).rgb))(
    empty
  )
  assert grads.means.shape == (0, 3)


def _crowd(num, centre_px, scale, seed=0):
  """num random Gaussians at depths 2..4 whose centres project near pixel centre_px (u, v)."""
  rng = np.random.default_rng(seed)
  z = rng.uniform(2.0, 4.0, num)
  u = centre_px[0] + rng.uniform(-0.5, 0.5, num)
  v = centre_px[1] + rng.uniform(-0.5, 0.5, num)
  means = np.stack([(u - INTR[2]) / INTR[0] * z, (v - INTR[3]) / INTR[1] * z, z], -1)
  return Gaussians(
    means=means.astype(np.float32),
    opacities=rng.uniform(0.3, 0.9, num).astype(np.float32),
    scales=np.full((num, 3), scale, np.float32),
    quats=rng.normal(size=(num, 4)).astype(np.float32),
    colors=rng.uniform(0, 1, (num, 3)).astype(np.float32),
  )


def _render_and_grad(g, config):
  out = render(g, W2C[None], INTR[None], height=H, width=W, background=BACKGROUND, config=config)
  grads = jax.grad(
    lambda g: _loss(render(g, W2C[None], INTR[None], height=H, width=W, config=config))
  )(g)
  out = jax.tree.map(lambda x: x[0], out)
  assert_finite(out, grads)
  assert_matches_dense(g, out)
  return out


CROWD_CONFIG = RenderConfig(chunk_size=8)


def test_all_gaussians_in_one_tile():
  g = _crowd(200, (8.0, 8.0), 1e-3)  # point-like at the centre of tile 0: one tile each
  out = _render_and_grad(g, CROWD_CONFIG)
  assert int(out.stats.num_intersections) == 200


def test_saturated_tiles_stop_early():
  g = _crowd(200, (18.0, 12.0), 3.0)  # each covers the whole image: 6 tiles each
  out = _render_and_grad(g, CROWD_CONFIG)
  assert int(out.stats.num_intersections) == 200 * 6
  # Without early stop this would be at least 1200 / 8 = 150 (sub-tile, chunk) blocks.
  assert int(out.stats.tile_chunks) <= 30


def test_equal_depths_composite_in_index_order():
  at_pixel = [0.5 / INTR[0] * 3.0, 0.5 / INTR[1] * 3.0, 3.0]  # centre of pixel (12, 18)
  g = scene(
    means=[at_pixel] * 3,
    opacities=[0.6, 0.6, 0.6],
    colors=[[1, 0, 0], [0, 1, 0], [0, 0, 1]],
    scales=[[1.0] * 3] * 3,
  )
  out, grads = run(g)
  assert_finite(out, grads)
  np.testing.assert_allclose(out.rgb[12, 18] - 0.4**3 * BACKGROUND, [0.6, 0.24, 0.096], atol=1e-4)


def test_budget_overflow_is_reported_and_drops_the_farthest():
  means = [[0, 0, 2.0], [0.1, 0.1, 3.0], [-0.2, 0.1, 4.0], [0.3, -0.2, 5.0]]
  g = scene(means=means, opacities=[0.5] * 4, scales=[[0.3] * 3] * 4)
  small = RenderConfig(max_intersections=8, chunk_size=8)
  out, grads = run(g, config=small)
  assert_finite(out, grads)
  full, _ = run(g)
  assert bool(out.stats.overflow) and not bool(full.stats.overflow)
  assert bool(out.stats.truncated) and not bool(full.stats.truncated)
  assert int(out.stats.budget) == 8 and int(out.stats.num_intersections) > 8
  # The nearest Gaussian (all 6 of its tiles within the budget) is intact where nothing else is.
  near_only, _ = run(scene(means=means[:1], opacities=[0.5], scales=[[0.3] * 3]))
  np.testing.assert_allclose(out.rgb[12, 18], near_only.rgb[12, 18], atol=0.2)
  assert float(out.alpha.sum()) < float(full.alpha.sum())


def test_budget_cut_behind_saturated_pixels_is_lossless():
  # Five opaque layers saturate every pixel (T <= 0.1^5 at the corners); the budget then cuts the
  # far Gaussians' tiles, which is reported as truncation but not as overflow, and changes nothing.
  near = [[0, 0, 2.0 + 0.01 * i] for i in range(5)]
  far = [[0.3 * i - 0.6, 0.1, 5.0 + i] for i in range(5)]
  g = scene(
    means=near + far,
    opacities=[1.0] * 5 + [0.8] * 5,
    scales=[[3.0] * 3] * 5 + [[0.5] * 3] * 5,
    num=10,
  )
  cut, grads = run(g, config=RenderConfig(max_intersections=32, chunk_size=8))
  full, full_grads = run(g)
  assert_finite(cut, grads)
  assert bool(cut.stats.truncated) and not bool(cut.stats.overflow)
  assert not bool(full.stats.truncated) and int(cut.stats.num_intersections) > 32
  np.testing.assert_array_equal(cut.rgb, full.rgb)
  np.testing.assert_allclose(
    grads.means, full_grads.means, atol=1e-6 * np.abs(full_grads.means).max()
  )


def test_bfloat16_inputs_compute_in_float32():
  g = scene(means=[[0.1, 0, 3.0], [-0.2, 0.1, 2.0]], opacities=[0.9, 0.5], scales=[[0.3] * 3] * 2)
  g16 = jax.tree.map(lambda x: jnp.asarray(x, jnp.bfloat16), g)
  out = render(g16, W2C[None], INTR[None], height=H, width=W, background=BACKGROUND)
  assert out.rgb.dtype == jnp.float32
  ref = render(
    jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), g16),
    W2C[None],
    INTR[None],
    height=H,
    width=W,
    background=BACKGROUND,
  )
  np.testing.assert_array_equal(out.rgb, ref.rgb)
  grads = jax.grad(lambda g: jnp.sum(render(g, W2C[None], INTR[None], height=H, width=W).rgb))(g16)
  assert grads.means.dtype == jnp.bfloat16
  assert np.all(np.isfinite(np.asarray(grads.means, np.float32)))


# ---- non-finite values stay local ----------------------------------------------------------------


def _four_gaussians():
  return dict(
    means=[[0, 0, 2.0], [0.1, 0.1, 3.0], [-0.2, 0.1, 4.0], [0.3, -0.2, 5.0]],
    opacities=[0.5, 0.6, 0.7, 0.8],
    scales=[[0.3] * 3] * 4,
    colors=[[0.9, 0.1, 0.1], [0.1, 0.9, 0.1], [0.1, 0.1, 0.9], [0.5, 0.5, 0.5]],
  )


@pytest.mark.parametrize(
  "field, value",
  [
    ("colors", np.nan),
    ("means", np.nan),
    ("scales", np.inf),
    ("quats", np.nan),
    ("opacities", np.nan),
  ],
)
def test_a_non_finite_gaussian_is_absent_and_its_gradient_zero(field, value):
  # Gaussian 0 is the nearest and covers the middle tiles: were its NaN to leak, whole tiles
  # (forward) or every Gaussian's gradient (backward) would turn NaN.
  fields = _four_gaussians()
  fields["quats"] = [[1.0, 0, 0, 0]] * 4
  bad = {name: np.array(v, np.float32) for name, v in fields.items()}
  bad[field][0] = value
  absent = {name: np.array(v, np.float32) for name, v in fields.items()}
  absent["opacities"][0] = 0.0  # the reference: Gaussian 0 culled by opacity
  out, grads = run(scene(**bad))
  ref, ref_grads = run(scene(**absent))
  assert int(out.stats.num_culled_nonfinite) == 1
  for leaf in jax.tree.leaves((out.rgb, out.alpha, out.depth, grads)):
    assert np.all(np.isfinite(leaf))
  np.testing.assert_allclose(out.rgb, ref.rgb, atol=1e-6)
  np.testing.assert_allclose(out.depth, ref.depth, atol=1e-5)
  for name in ("means", "opacities", "scales", "quats", "colors"):
    np.testing.assert_allclose(
      getattr(grads, name)[1:], getattr(ref_grads, name)[1:], rtol=1e-5, atol=1e-6
    )
    np.testing.assert_array_equal(getattr(grads, name)[0], 0.0)
