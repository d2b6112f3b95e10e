"""Training losses: hand-computed values, the visibility deviation, schedules, finite gradients."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage

from tokengs_jax import losses

# One camera at the origin looking down +z; 40x20 image with fx = fy = 20, principal point at the
# centre, so a point (x, y, 1) lands at normalised coordinates (u_n, v_n) = (x, 2 y).
HEIGHT, WIDTH = 20, 40
INTRINSICS = jnp.array([[20.0, 20.0, 20.0, 10.0]])
IDENTITY = jnp.eye(4)[None]


def _translated(tx):
  """World-to-camera of a camera at (tx, 0, 0) looking down +z.  -> [4, 4]."""
  return jnp.eye(4).at[0, 3].set(-tx)


# One compiled program per shape instead of op-by-op dispatch (keeps the tests fast).
_visibility = jax.jit(
  losses.visibility_loss, static_argnums=(3, 4), static_argnames=("threshold", "near")
)


def _vis(means, w2c=IDENTITY, intrinsics=INTRINSICS, **kwargs):
  return _visibility(jnp.asarray(means, jnp.float32), w2c, intrinsics, HEIGHT, WIDTH, **kwargs)


def test_rgb_loss_hand_values():
  pred = jnp.zeros((2, 4, 4, 3))
  target = jnp.full((2, 4, 4, 3), 0.5)
  assert float(losses.rgb_loss(pred, target, "l2")) == pytest.approx(0.25)
  assert float(losses.rgb_loss(pred, target, "l1")) == pytest.approx(0.5)


def test_ssim_loss_matches_a_zero_padded_numpy_reference():
  # Independent reference of the fused-ssim conventions: scipy Gaussian filter, zero ("constant")
  # border, population covariance, mean of the map, then (1 - SSIM) / 2.
  rng = np.random.default_rng(0)
  target = rng.uniform(0, 1, (2, 18, 21, 3))
  pred = np.clip(target + rng.normal(0, 0.2, target.shape), 0, 1)
  blur = lambda z: ndimage.gaussian_filter(
    z, sigma=(0, 1.5, 1.5, 0), truncate=3.5, mode="constant", cval=0.0
  )
  mx, my = blur(pred), blur(target)
  vx = blur(pred * pred) - mx * mx
  vy = blur(target * target) - my * my
  cxy = blur(pred * target) - mx * my
  c1, c2 = 0.01**2, 0.03**2
  ssim = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
  expected = (1 - ssim.mean()) / 2
  ours = losses.ssim_loss(jnp.asarray(pred, jnp.float32), jnp.asarray(target, jnp.float32))
  assert float(ours) == pytest.approx(expected, abs=1e-5)
  assert float(losses.ssim_loss(target, target)) == pytest.approx(0.0, abs=1e-6)


def test_visibility_loss_hand_values():
  means = [
    [1.5, 0.0, 1.0],  # u_n = 1.5 -> 0.5
    [0.0, 0.0, 1.0],  # centre -> 0
    [0.3, 0.75, 1.0],  # v_n = 1.5 -> 0.5
    [1.4, 0.6, 1.0],  # 0.4 + 0.2 = 0.6 (u and v add)
    [3.0, 0.0, 1.0],
  ]  # u_n = 3 -> 2, clamped to 1
  np.testing.assert_allclose(_vis(means), (0.5 + 0 + 0.5 + 0.6 + 1.0) / 5, rtol=1e-6)
  # The clamp is the threshold.
  np.testing.assert_allclose(_vis(means, threshold=0.5), (0.5 + 0 + 0.5 + 0.5 + 0.5) / 5, rtol=1e-6)


def test_visibility_loss_takes_the_closest_view_and_batches():
  # Second camera shifted by +1.5 in x sees the point (1.5, 0, 1) at its centre.
  w2c = jnp.stack([jnp.eye(4), _translated(1.5)])[None].repeat(2, axis=0)  # [B=2, V=2, 4, 4]
  intrinsics = jnp.broadcast_to(INTRINSICS, (2, 2, 4))
  means = jnp.array([[[1.5, 0.0, 1.0]], [[-2.0, 0.0, 1.0]]])  # [B=2, N=1, 3]
  out = _vis(means, w2c, intrinsics)
  assert out.shape == (2,)
  # Scene 1: u_n = -2 in view 0 (distance 1), -3.5 in view 1 (clamped): min 1.
  np.testing.assert_allclose(out, [0.0, 1.0], atol=1e-6)


def test_visibility_penalises_centres_behind_or_on_the_camera():
  # Officially (projection without depth) (0, 0, -1) lands on the image centre: loss 0.
  # Here depth <= near means hidden: the clamp value, 1.
  for z in (-1.0, 0.0, 0.01):
    np.testing.assert_allclose(_vis([[0.0, 0.0, z]]), 1.0)
  np.testing.assert_allclose(_vis([[0.0, 0.0, 0.01]], near=0.001), 0.0)


def test_visibility_gradient_pulls_outside_points_inward():
  means = jnp.array([[1.5, 0.2, 1.0], [-0.2, -0.8, 1.0]])  # right of the image; above it
  grad = jax.jit(jax.grad(_vis))(means)
  assert grad[0, 0] > 0 and grad[1, 1] < 0  # descent moves x left, y down: towards the centre
  stepped = means - 0.1 * grad
  assert float(_vis(stepped)) < float(_vis(means))


def test_visibility_gradient_comes_from_the_view_the_point_is_in_front_of():
  # Behind camera 0 (looking down -z) but in front of camera 1, outside its image on the right.
  flipped = jnp.diag(jnp.array([-1.0, 1.0, -1.0, 1.0]))  # looks down -z
  w2c = jnp.stack([flipped, jnp.eye(4)])
  intrinsics = jnp.broadcast_to(INTRINSICS, (2, 4))
  means = jnp.array([[1.5, 0.0, 1.0]])
  value, grad = jax.jit(jax.value_and_grad(_vis))(means, w2c, intrinsics)
  assert float(value) == pytest.approx(0.5)
  assert grad[0, 0] > 0


def test_visibility_gradients_finite_on_the_camera_plane():
  means = jnp.array([[0.0, 0.0, 0.0], [1e-20, 2.0, 0.0], [5.0, 5.0, 1e-9], [0.3, 0.1, -4.0]])
  grad = jax.jit(jax.grad(_vis))(means)
  assert np.isfinite(np.asarray(grad)).all()


def test_render_loss_combines_terms_with_weights():
  config = losses.LossConfig(lambda_ssim=0.2, lambda_vis=1.0)
  pred = jnp.zeros((1, 2, 12, 12, 3))
  target = jnp.full((1, 2, 12, 12, 3), 0.5)
  means = jnp.array([[[1.5, 0.0, 1.0], [0.0, 0.0, 1.0]]])
  w2c = jnp.broadcast_to(jnp.eye(4), (1, 2, 4, 4))
  intrinsics = jnp.broadcast_to(INTRINSICS, (1, 2, 4))
  # Renders are 12x12 but the cameras were set for 40x20; rescale so u_n = x, v_n = 2 y again.
  intrinsics = intrinsics * jnp.array([12 / WIDTH, 12 / HEIGHT, 12 / WIDTH, 12 / HEIGHT])
  loss, terms = jax.jit(losses.render_loss, static_argnums=2)(
    pred, target, config, means=means, world_to_camera=w2c, intrinsics=intrinsics
  )
  assert float(terms["rgb"]) == pytest.approx(0.25)
  assert float(terms["visibility"]) == pytest.approx(0.25)  # (0.5 + 0) / 2
  assert float(terms["ssim"]) == pytest.approx(float(losses.ssim_loss(pred, target)))
  assert float(loss) == pytest.approx(0.25 + 0.2 * float(terms["ssim"]) + 0.25, rel=1e-6)
  assert float(terms["loss"]) == float(loss)
  assert float(terms["psnr"]) == pytest.approx(10 * np.log10(1 / 0.25), rel=1e-5)


def test_render_loss_lpips_term_and_argument_checks():
  pred = jnp.zeros((1, 1, 16, 16, 3))
  with pytest.raises(ValueError, match="means"):
    losses.render_loss(pred, pred, losses.LossConfig())
  config = losses.LossConfig(lambda_vis=0.0, lambda_ssim=0.0, lambda_lpips=0.5)
  with pytest.raises(ValueError, match="lpips_params"):
    losses.render_loss(pred, pred, config)
  from tokengs_jax import lpips as lpips_lib

  params = lpips_lib.load_vgg_params()
  loss, terms = jax.jit(losses.render_loss, static_argnums=2)(
    pred, pred, config, lpips_params=params
  )
  assert float(terms["lpips"]) == pytest.approx(0.0, abs=1e-7)
  assert float(loss) == float(terms["lpips"]) * 0.5 + float(terms["rgb"])


@pytest.mark.parametrize("rgb", ["l2", "l1"])
def test_render_loss_gradients_finite_for_flat_identical_images(rgb):
  # Zero variance everywhere, zero difference (|x| kink for L1), a point behind the camera.
  config = losses.LossConfig(rgb_loss=rgb)
  target = jnp.full((1, 1, 12, 12, 3), 0.5)
  means = jnp.array([[[0.0, 0.0, -1.0], [0.2, 0.1, 1.0], [0.0, 0.0, 0.0]]])
  w2c = jnp.eye(4)[None, None]
  intrinsics = jnp.array([[[10.0, 10.0, 6.0, 6.0]]])

  def total(pred, m):
    return losses.render_loss(
      pred, target, config, means=m, world_to_camera=w2c, intrinsics=intrinsics
    )[0]

  loss, (grad_pred, grad_means) = jax.jit(jax.value_and_grad(total, argnums=(0, 1)))(target, means)
  assert np.isfinite(float(loss))
  assert np.isfinite(np.asarray(grad_pred)).all() and np.isfinite(np.asarray(grad_means)).all()


def test_dynamic_aux_weight_hold_then_decay():
  config = losses.LossConfig(lambda_dyn_aux=0.3, dyn_aux_hold_steps=5000, dyn_aux_decay_steps=10000)
  steps = jnp.array([0, 5000, 10000, 15000, 40000])
  weights = jax.jit(jax.vmap(lambda s: losses.dynamic_aux_weight(s, config)))(steps)
  np.testing.assert_allclose(weights, [0.3, 0.3, 0.15, 0.0, 0.0], atol=1e-7)
  constant = losses.LossConfig(lambda_dyn_aux=0.3)
  assert float(losses.dynamic_aux_weight(10**6, constant)) == pytest.approx(0.3)
  assert float(losses.dynamic_aux_weight(0, losses.LossConfig())) == 0.0
  floor = losses.LossConfig(lambda_dyn_aux=0.3, dyn_aux_decay_steps=10, dyn_aux_min=0.1)
  assert float(losses.dynamic_aux_weight(100, floor)) == pytest.approx(0.1)


def test_add_dynamic_aux():
  config = losses.LossConfig(lambda_dyn_aux=0.3, dyn_aux_hold_steps=10, dyn_aux_decay_steps=10)
  loss, terms = losses.add_dynamic_aux(
    jnp.array(1.0), {"loss": jnp.array(1.0)}, jnp.array(2.0), 15, config
  )
  assert float(loss) == pytest.approx(1.0 + 0.15 * 2.0)
  assert float(terms["loss"]) == float(loss)
  assert float(terms["dyn_aux"]) == 2.0 and float(terms["dyn_aux_weight"]) == pytest.approx(0.15)


def test_loss_config_validates():
  with pytest.raises(ValueError):
    losses.LossConfig(rgb_loss="l3")
  with pytest.raises(ValueError):
    losses.LossConfig(visibility_threshold=0.0)
  assert hash(losses.LossConfig()) == hash(losses.LossConfig())  # usable as a static jit argument


def test_depth_loss_is_opacity_weighted_relative_error_over_known_pixels():
  truth = jnp.array([[2.0, 4.0], [1.0, 0.0]])  # the last pixel is unknown
  depth = jnp.array([[2.0, 5.0], [3.0, 7.0]])[..., None]
  alpha = jnp.array([[1.0, 1.0], [0.5, 1.0]])[..., None]
  # exact, 1/4 off, 2x off at half opacity; the unknown pixel is ignored
  np.testing.assert_allclose(losses.depth_loss(depth, alpha, truth), (0 + 0.25 + 0.5 * 2) / 3)
  assert float(losses.depth_loss(depth, alpha, jnp.zeros((2, 2)))) == 0.0  # nothing known
  # An empty render (alpha 0, expected depth a huge 0/0 stand-in) has a finite gradient.
  grad = jax.grad(lambda d: losses.depth_loss(d, jnp.zeros_like(d), truth))(depth * 1e10)
  assert np.isfinite(np.asarray(grad)).all()


def _gaussians_in_front(means_key, colours_key, shape, *, spread, opacity, scale):
  """Round Gaussians [*shape] of one opacity and size, centred within `spread` of (0, 0, 2):
  in front of an identity camera looking down +z."""
  from tokengs_jax.gaussians import Gaussians

  means = jax.random.uniform(means_key, (*shape, 3), minval=-spread, maxval=spread)
  return Gaussians(
    means=means.at[..., 2].add(2.0),
    opacities=jnp.full(shape, opacity),
    scales=jnp.full((*shape, 3), scale),
    quats=jnp.tile(jnp.array([1.0, 0, 0, 0]), (*shape, 1)),
    colors=jax.random.uniform(colours_key, (*shape, 3)),
  )


def test_supervision_adds_the_depth_term_only_with_depths_and_a_weight():
  from tokengs_jax import splatting
  from tokengs_jax.gaussians import Gaussians
  from tokengs_jax.train.supervision import supervision_loss

  key = jax.random.split(jax.random.key(0), 2)
  gaussians = _gaussians_in_front(*key, (1, 64), spread=0.5, opacity=0.9, scale=0.2)
  means = gaussians.means
  images = jnp.full((1, 1, 16, 16, 3), 0.5)
  w2c = jnp.eye(4)[None, None]
  intrinsics = jnp.array([[[16.0, 16.0, 8.0, 8.0]]])
  depths = jnp.full((1, 1, 16, 16), 4.0)  # twice as far as the Gaussians
  args = (gaussians, images, w2c, intrinsics)
  render = splatting.RenderConfig()
  plain, plain_terms = supervision_loss(*args, losses.LossConfig(), render)
  weighted = losses.LossConfig(lambda_depth=0.5)
  assert "depth" not in supervision_loss(*args, weighted, render)[1]  # no depths: no term
  loss, terms = supervision_loss(*args, weighted, render, depths=depths)
  assert 0.2 < float(terms["depth"]) < 0.6  # about half the covered pixels' depth is off
  np.testing.assert_allclose(loss, plain + 0.5 * terms["depth"], rtol=1e-5)
  assert "depth" not in supervision_loss(*args, losses.LossConfig(), render, depths=depths)[1]

  def depth_of(means):
    g = Gaussians(means, gaussians.opacities, gaussians.scales, gaussians.quats, gaussians.colors)
    return supervision_loss(g, images, w2c, intrinsics, weighted, render, depths=depths)[1]["depth"]

  # The term pulls the Gaussians back towards the true depth (+z).
  assert float(jax.grad(depth_of)(means)[..., 2].sum()) < 0


def _scene_of_two_examples():
  """Gaussians [2, N] that cover part of two views, and two examples' input views
  [2, 3, 16, 16, 3] of different mean colours (neither of them grey)."""
  key = jax.random.split(jax.random.key(1), 3)
  gaussians = _gaussians_in_front(key[0], key[1], (2, 24), spread=0.6, opacity=0.8, scale=0.08)
  tint = jnp.array([[0.2, 0.9, 0.5], [0.8, 0.1, 0.3]])[:, None, None, None]
  context = tint * jax.random.uniform(key[2], (2, 3, 16, 16, 3), minval=0.5, maxval=1.5)
  return gaussians, context


def test_input_mean_background_is_composited_behind_the_render():
  from tokengs_jax import splatting
  from tokengs_jax.train.supervision import ObjectiveConfig, render_views

  gaussians, context = _scene_of_two_examples()
  w2c = jnp.tile(jnp.eye(4), (2, 2, 1, 1)).at[:, 1, 0, 3].set(0.3)
  intrinsics = jnp.tile(jnp.array([16.0, 16.0, 8.0, 8.0]), (2, 2, 1))
  args = (gaussians, w2c, intrinsics, 16, 16, splatting.RenderConfig())
  composited = render_views(*args, ObjectiveConfig(background="input_mean"), context)
  black = render_views(*args, ObjectiveConfig(background=(0.0, 0.0, 0.0)))
  uncovered = 1.0 - black.alpha
  assert 0.2 < float(jnp.mean(uncovered)) < 0.8  # the background shows, but not everywhere
  mean = jnp.mean(context, axis=(1, 2, 3))[:, None, None, None]  # each example's own
  np.testing.assert_allclose(composited.rgb, black.rgb + uncovered * mean, atol=1e-6)
  with pytest.raises(ValueError, match="context images"):
    render_views(*args, ObjectiveConfig(background="input_mean"))
  with pytest.raises(ValueError, match="background"):
    ObjectiveConfig(background="grey")


def _two_supervision_views():
  """(images [2, 2, 16, 16, 3], world_to_camera, intrinsics): two examples, two views 0.3 apart."""
  images = jax.random.uniform(jax.random.key(2), (2, 2, 16, 16, 3))
  w2c = jnp.tile(jnp.eye(4), (2, 2, 1, 1)).at[:, 1, 0, 3].set(0.3)
  intrinsics = jnp.tile(jnp.array([16.0, 16.0, 8.0, 8.0]), (2, 2, 1))
  return images, w2c, intrinsics


def test_objectives_with_input_mean_use_each_examples_own_input_colour():
  """Two examples with different inputs, scored together (in view chunks), lose exactly what
  each loses alone over the fixed RGB of its own inputs' mean colour: static and time-conditioned
  objectives, the dynamic auxiliary render included."""
  from tokengs_jax import splatting
  from tokengs_jax.train.objective import time_conditioned_loss
  from tokengs_jax.train.supervision import ObjectiveConfig, supervision_loss

  gaussians, context = _scene_of_two_examples()
  images, w2c, intrinsics = _two_supervision_views()
  times = jnp.array([[0.2, 0.7], [0.4, 0.9]])
  loss_config = losses.LossConfig(lambda_dyn_aux=0.3)
  render = splatting.RenderConfig()

  def static(g, views, objective, ctx=None):
    return supervision_loss(g, *views, loss_config, render, objective, context_images=ctx)[0]

  def timed(g, views, t, objective, ctx=None):
    def at(t, _world_to_camera):  # the same Gaussians at every time and camera: [B, T]
      return jax.tree.map(lambda x: jnp.repeat(x[:, None], t.shape[1], axis=1), g)

    return time_conditioned_loss(
      at, t, *views, loss_config, render, objective, num_static_gaussians=12, context_images=ctx
    )[0]

  together = ObjectiveConfig(view_chunk_size=1, background="input_mean")
  alone = [
    ObjectiveConfig(background=tuple(float(c) for c in jnp.mean(context[b], axis=(0, 1, 2))))
    for b in range(2)
  ]
  views = (images, w2c, intrinsics)
  one = lambda x, b: jax.tree.map(lambda y: y[b : b + 1], x)
  each = np.mean([static(one(gaussians, b), one(views, b), alone[b]) for b in range(2)])
  np.testing.assert_allclose(static(gaussians, views, together, context), each, rtol=1e-5)
  # the swapped inputs' colours give another loss: each example reads its own
  assert abs(float(static(gaussians, views, together, context[::-1])) - each) > 1e-4
  each = np.mean(
    [timed(one(gaussians, b), one(views, b), times[b : b + 1], alone[b]) for b in range(2)]
  )
  np.testing.assert_allclose(timed(gaussians, views, times, together, context), each, rtol=1e-5)


def test_objectives_render_one_set_per_view_as_each_view_alone():
  """Gaussians [B, V] (colours for each camera, `model.decode(viewer_c2w=)`): the static and
  the time-conditioned objectives (one decode for every view) score view v with set v alone,
  in view chunks or not; the same set repeated scores as the shared set."""
  from tokengs_jax import splatting
  from tokengs_jax.train.objective import time_conditioned_loss
  from tokengs_jax.train.supervision import ObjectiveConfig, supervision_loss

  gaussians, _ = _scene_of_two_examples()
  images, w2c, intrinsics = _two_supervision_views()
  render = splatting.RenderConfig()
  recoloured = dataclasses.replace(gaussians, colors=1.0 - gaussians.colors)
  per_view = jax.tree.map(lambda a, b: jnp.stack([a, b], axis=1), gaussians, recoloured)
  repeated = jax.tree.map(lambda a: jnp.stack([a, a], axis=1), gaussians)

  def static(g, objective, loss_config, view=slice(None)):
    views = (images[:, view], w2c[:, view], intrinsics[:, view])
    return float(supervision_loss(g, *views, loss_config, render, objective)[0])

  def timed(g, objective, loss_config):
    first = ObjectiveConfig(view_chunk_size=objective.view_chunk_size, decode_times="first")
    at = lambda times, world_to_camera: g  # one decode: a set per view's camera, or [B, 1]
    times = jnp.zeros((2, 2))
    return float(
      time_conditioned_loss(at, times, images, w2c, intrinsics, loss_config, render, first)[0]
    )

  with_vis, without = losses.LossConfig(), losses.LossConfig(lambda_vis=0.0)
  one = jax.tree.map(lambda a: a[:, None], gaussians)
  objective = ObjectiveConfig(view_chunk_size=1)  # the chunked path: it slices the sets
  shared = static(gaussians, objective, with_vis)
  np.testing.assert_allclose(static(repeated, objective, with_vis), shared, rtol=1e-6)
  alone = [static(g, objective, without, slice(v, v + 1)) for v, g in enumerate(_sets_of(per_view))]
  np.testing.assert_allclose(static(per_view, objective, without), np.mean(alone), rtol=1e-5)
  assert abs(static(per_view, objective, without) - static(gaussians, objective, without)) > 1e-4
  np.testing.assert_allclose(
    timed(repeated, objective, with_vis), timed(one, objective, with_vis), rtol=1e-5
  )
  np.testing.assert_allclose(
    timed(per_view, objective, without), static(per_view, objective, without), rtol=1e-5
  )


def _sets_of(gaussians):
  """Gaussians [B, V] -> the V sets [B]."""
  return [jax.tree.map(lambda a: a[:, v], gaussians) for v in range(gaussians.batch_shape[1])]
