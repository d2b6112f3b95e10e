"""Training losses: hand-computed values, the visibility deviation, schedules, finite gradients."""

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


def test_moving_pixels_compare_each_target_with_the_input_of_the_nearest_camera():
  rng = np.random.default_rng(0)
  context = rng.random((1, 2, 6, 6, 3)).astype(np.float32)
  context_c2w = np.tile(np.eye(4, dtype=np.float32), (1, 2, 1, 1))
  context_c2w[0, 1, :3, 3] = [2.0, 0.0, 0.0]
  # target 0 near camera 1, target 1 near camera 0; each changed in one block
  target_c2w = context_c2w[:, ::-1].copy()
  target_c2w[..., 1, 3] = 0.1
  target = context[:, ::-1].copy()
  target[0, 0, :2, :3, 1] += 0.5
  target[0, 1, 4:, 4:, 0] -= 0.05  # under the threshold
  target[0, 1, 3, 0, 2] += 0.2
  moving = losses.moving_pixels(target, target_c2w, context, context_c2w, threshold=0.1)
  expected = np.zeros((1, 2, 6, 6), np.float32)
  expected[0, 0, :2, :3] = 1
  expected[0, 1, 3, 0] = 1
  np.testing.assert_array_equal(moving, expected)


def test_motion_loss_is_the_error_of_the_moving_pixels_over_all_pixels():
  pred = jnp.zeros((1, 2, 2, 3))
  target = jnp.full((1, 2, 2, 3), 0.5)
  moving = jnp.array([[[1.0, 0.0], [0.0, 0.0]]])
  assert float(losses.motion_loss(pred, target, moving, "l2")) == pytest.approx(0.25 / 4)
  assert float(losses.motion_loss(pred, target, moving, "l1")) == pytest.approx(0.5 / 4)
  everywhere = jnp.ones((1, 2, 2))
  assert float(losses.motion_loss(pred, target, everywhere)) == pytest.approx(
    float(losses.rgb_loss(pred, target))
  )


def test_mask_loss_is_the_squared_alpha_error_averaged_over_views_and_pixels():
  """Official `lambda_mask`: mean (alpha - mask)^2 over every view and pixel, by hand."""
  alpha = np.array([[[[0.0], [1.0]], [[0.5], [1.0]]], [[[0.2], [0.2]], [[0.2], [0.2]]]])
  masks = np.array([[[0.0, 0.0], [1.0, 1.0]], [[0.2, 0.2], [0.2, 1.0]]])  # [V=2, 2, 2]
  # view 0: 0, 1, 0.25, 0; view 1: 0, 0, 0, 0.64 -> 1.89 / 8
  np.testing.assert_allclose(jax.jit(losses.mask_loss)(alpha, masks), 1.89 / 8, rtol=1e-6)
  grad = jax.grad(losses.mask_loss)(jnp.asarray(alpha), jnp.asarray(masks))
  assert float(grad[0, 1, 0, 0]) < 0 < float(grad[0, 0, 1, 0])  # towards the mask
  assert losses.LossConfig().lambda_mask == 0.0  # off by default, as official
  with pytest.raises(ValueError, match="lambda_mask"):
    losses.LossConfig(lambda_mask=-0.5)


def test_composite_on_white_keeps_the_foreground_and_whitens_the_background():
  """Official `gt * mask + 1 * (1 - mask)`: a soft mask blends towards white."""
  images = np.full((1, 1, 3, 3), 0.2, np.float32)[..., None].repeat(3, -1)  # [1, 1, 3, 3, 3]
  masks = np.array([[[[1.0, 0.0, 0.5]] * 3]], np.float32)  # [1, 1, 3, 3]
  got = np.asarray(losses.composite_on_white(images, masks))
  np.testing.assert_allclose(got[..., 0, :], 0.2)
  np.testing.assert_allclose(got[..., 1, :], 1.0)
  np.testing.assert_allclose(got[..., 2, :], 0.6)
