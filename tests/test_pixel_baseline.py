"""experiments/pixel_baseline.py: the pixel-aligned (GS-LRM-style) baseline of the studies.

One tiny config (the `smoke` preset's model: one encoder + one decoder block, width 32, 8x8
patches) and few distinct shapes, so that the file compiles in seconds.
"""

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments import pixel_baseline, re10k
from tokengs_jax.camera import invert_rigid, pixel_centers, project_points

HEIGHT, WIDTH, VIEWS = 32, 32, 2


def _look_at(eye, target) -> np.ndarray:
  """OpenCV camera-to-world [4, 4] at `eye` looking at `target` (+y down)."""
  eye, target = np.asarray(eye, np.float64), np.asarray(target, np.float64)
  forward = (target - eye) / np.linalg.norm(target - eye)
  right = np.cross(forward, [0.0, -1.0, 0.0])
  right /= np.linalg.norm(right)
  down = np.cross(forward, right)
  c2w = np.eye(4)
  c2w[:3, :3] = np.stack([right, down, forward], axis=-1)
  c2w[:3, 3] = eye
  return c2w.astype(np.float32)


def _cameras(views: int, height: int, width: int):
  """Two distinct, non-trivial cameras: c2w [1, V, 4, 4], intrinsics [1, V, 4] (pixels)."""
  eyes = [(0.0, 0.0, 0.0), (0.4, -0.1, 0.2), (-0.3, 0.2, 0.1)][:views]
  c2w = np.stack([_look_at(eye, (0.1 * i, 0.05, 2.0)) for i, eye in enumerate(eyes)])
  intrinsics = np.array(
    [
      [1.1 * width, 1.0 * height, 0.5 * width, 0.5 * height],
      [0.9 * width, 0.95 * height, 0.45 * width, 0.55 * height],
      [width, height, 0.5 * width, 0.5 * height],
    ][:views],
    np.float32,
  )
  return jnp.asarray(c2w[None]), jnp.asarray(intrinsics[None])


@pytest.fixture(scope="module")
def baseline():
  """(config, params) of the smoke-sized baseline; the head readout is enlarged so that depths,
  colours and scales vary from pixel to pixel (the default 0.002 makes them nearly constant)."""
  config = re10k.PRESETS["smoke"].model.replace(clip_head_readout_std=0.5)
  return config, pixel_baseline.init_params(jax.random.key(0), config)


@pytest.fixture(scope="module")
def scene():
  """Images [1, V, H, W, 3] in [0, 1], c2w [1, V, 4, 4], intrinsics [1, V, 4]."""
  images = jax.random.uniform(jax.random.key(1), (1, VIEWS, HEIGHT, WIDTH, 3))
  return (images, *_cameras(VIEWS, HEIGHT, WIDTH))


@pytest.fixture(scope="module")
def gaussians(baseline, scene):
  config, params = baseline
  return jax.device_get(pixel_baseline.jitted_reconstruct(params, *scene, config))


def test_params_have_one_block_per_encoder_and_decoder_layer(baseline):
  config, params = baseline
  blocks = sorted(name for name in params if name.startswith("block_"))
  assert blocks == [f"block_{i}" for i in range(config.enc_depth + config.dec_depth)]
  assert {"rgb_embed", "ray_embed", "norm", "unpatchify"} <= set(params)
  p = config.patch_size
  assert params["unpatchify"]["kernel"].shape == (config.enc_embed_dim, 14 * p * p)


def test_one_gaussian_per_input_pixel(baseline, gaussians):
  config, _ = baseline
  n = VIEWS * HEIGHT * WIDTH
  assert gaussians.batch_shape == (1,)
  assert gaussians.means.shape == (1, n, 3) and gaussians.scales.shape == (1, n, 3)
  assert gaussians.quats.shape == (1, n, 4) and gaussians.colors.shape == (1, n, 3)
  assert gaussians.opacities.shape == (1, n)
  for leaf in jax.tree.leaves(gaussians):
    assert np.isfinite(leaf).all()
  assert ((gaussians.opacities > 0) & (gaussians.opacities < 1)).all()
  assert ((gaussians.colors >= 0) & (gaussians.colors <= 1)).all()
  assert ((gaussians.scales > 0) & (gaussians.scales <= config.gaussian_scale_cap + 1e-6)).all()
  np.testing.assert_allclose(np.linalg.norm(gaussians.quats, axis=-1), 1.0, atol=1e-5)
  # the per-pixel attributes really vary (not one Gaussian broadcast to every pixel)
  assert np.std(gaussians.colors) > 1e-2


def test_means_lie_on_their_pixel_rays_at_positive_depth(gaussians, scene):
  """Gaussian v * H * W + i * W + j projects to pixel (i, j)'s centre in input view v, in front of
  the camera, at a distance from its centre inside [DEPTH_NEAR, DEPTH_FAR]."""
  _, c2w, intrinsics = scene
  means = np.asarray(gaussians.means[0]).reshape(VIEWS, HEIGHT * WIDTH, 3)
  centres = pixel_centers(HEIGHT, WIDTH).reshape(-1, 2)
  distances = []
  for v in range(VIEWS):
    uv, z = project_points(
      jnp.asarray(means[v]), invert_rigid(c2w[0, v : v + 1]), intrinsics[0, v : v + 1]
    )
    np.testing.assert_allclose(uv[0], centres, atol=2e-3)
    assert (z[0] > 0).all()
    distances.append(np.linalg.norm(means[v] - np.asarray(c2w[0, v, :3, 3]), axis=-1))
  distances = np.stack(distances)
  assert distances.min() >= pixel_baseline.DEPTH_NEAR - 1e-5
  assert distances.max() <= pixel_baseline.DEPTH_FAR + 1e-5
  assert np.ptp(distances) > 0.1  # the depth is predicted per pixel, not a constant
  # a Gaussian does not sit on another view's ray: view 1's Gaussians miss view 0's pixel centres
  uv, _ = project_points(jnp.asarray(means[1]), invert_rigid(c2w[0, :1]), intrinsics[0, :1])
  assert np.abs(np.asarray(uv[0]) - np.asarray(centres)).max() > 1.0


def test_each_output_token_writes_exactly_its_own_patch(baseline, scene):
  """Unpatchify order: perturbing the final-norm output of one token (view v, patch row I,
  column J) changes the raw channels of exactly that p x p block of pixels."""
  config, params = baseline
  images, c2w, intrinsics = scene
  p, view, row, col = config.patch_size, 1, 2, 1
  per_view = (HEIGHT // p) * (WIDTH // p)
  token = view * per_view + row * (WIDTH // p) + col

  @jax.jit
  def raw(delta):
    def interceptor(next_fun, args, kwargs, context):
      out = next_fun(*args, **kwargs)
      if context.module.path == ("norm",) and context.method_name == "__call__":
        out = out.at[:, token].add(delta)
      return out

    with nn.intercept_methods(interceptor):
      return pixel_baseline.PixelAlignedGS(config).apply(
        {"params": params}, images, jnp.zeros((1, VIEWS, HEIGHT, WIDTH, 6))
      )

  changed = np.abs(np.asarray(raw(1.0) - raw(0.0))).max(axis=-1)[0] > 1e-6  # [V, H, W]
  expected = np.zeros_like(changed)
  expected[view, row * p : (row + 1) * p, col * p : (col + 1) * p] = True
  np.testing.assert_array_equal(changed, expected)


def _training_batch(key) -> dict:
  """Two 16x16 input views and one target view from a third camera (small renders: the gradient
  program is the file's largest compile)."""
  height = width = 16
  context_c2w, context_k = _cameras(2, height, width)
  target_c2w, target_k = _cameras(3, height, width)
  return {
    "context_images": jax.random.uniform(key, (1, 2, height, width, 3)),
    "context_c2w": context_c2w,
    "context_intrinsics": context_k,
    "target_images": jax.random.uniform(jax.random.fold_in(key, 1), (1, 1, height, width, 3)),
    "target_c2w": target_c2w[:, 2:],
    "target_intrinsics": target_k[:, 2:],
  }


@pytest.mark.parametrize("colour_weights", ["mean", "viewer"])
def test_training_loss_has_finite_nonzero_gradients(baseline, colour_weights):
  """`loss_fn` (render + photometric + visibility terms) differentiates through every layer,
  also with colours read for each target camera."""
  config, params = baseline
  config = config.replace(input_colour_weights=colour_weights)
  key = jax.random.key(2)
  batch = _training_batch(key)
  compute = pixel_baseline.loss_fn(config)
  (loss, terms), grads = jax.jit(jax.value_and_grad(compute, has_aux=True))(params, batch, key, 0)
  assert np.isfinite(float(loss)) and float(loss) > 0
  assert np.isfinite(float(terms["psnr"]))
  for path, leaf in jax.tree_util.tree_leaves_with_path(grads):
    assert np.isfinite(leaf).all(), jax.tree_util.keystr(path)
  for name in ("rgb_embed", "ray_embed", "block_0", "block_1", "unpatchify"):
    norm = sum(float(jnp.sum(g**2)) for g in jax.tree.leaves(grads[name]))
    assert norm > 0, name


def test_training_loss_is_the_tokengs_objective_on_the_baseline_gaussians(baseline):
  """`loss_fn` scores the baseline's Gaussians, coloured for the target camera, with TokenGS's
  `supervision_loss` (the same terms, LPIPS left off)."""
  from tokengs_jax import losses, splatting
  from tokengs_jax.objective import ObjectiveConfig, supervision_loss

  config, params = baseline
  config = config.replace(input_colour_weights="viewer")
  batch = _training_batch(jax.random.key(3))
  loss, terms = jax.jit(pixel_baseline.loss_fn(config))(params, batch, None, 0)
  gaussians = pixel_baseline.method(params, config).gaussians(batch)  # for the target cameras
  expected, expected_terms = supervision_loss(
    gaussians,
    batch["target_images"],
    invert_rigid(batch["target_c2w"]),
    batch["target_intrinsics"],
    losses.LossConfig(),
    splatting.RenderConfig(),
    ObjectiveConfig(),
    context_images=batch["context_images"],
  )
  np.testing.assert_allclose(float(loss), float(expected), rtol=1e-5)
  for name, value in expected_terms.items():
    np.testing.assert_allclose(terms[name], value, rtol=1e-5, atol=1e-7, err_msg=name)


def test_colours_come_from_the_input_views_like_tokengs(baseline, scene, gaussians):
  """The smoke model reads colours from the inputs (`gaussian_colours="inputs"`); with the
  official head colours the same weights give other colours."""
  from tokengs_jax.model.colours import InputViews, input_colours

  config, params = baseline
  assert config.gaussian_colours == "inputs"
  images, c2w, intrinsics = scene
  expected, seen = input_colours(
    jnp.asarray(gaussians.means), InputViews(images, invert_rigid(c2w), intrinsics)
  )
  assert bool(jnp.all(seen))  # every Gaussian lies on a ray of its own view
  np.testing.assert_allclose(gaussians.colors, expected, atol=1e-5)
  head = pixel_baseline.jitted_reconstruct(params, *scene, config.replace(gaussian_colours="head"))
  np.testing.assert_allclose(head.means, gaussians.means, atol=1e-6)
  assert np.abs(np.asarray(head.colors) - expected).max() > 0.1


def test_viewer_colours_give_one_set_per_camera_like_tokengs(baseline, scene, gaussians):
  """With `input_colour_weights="viewer"` the Gaussians come as one set per viewing camera (here
  the two input cameras), each coloured by `viewer_colours` for it, at the mean-colour model's
  positions; the two cameras see different colours."""
  from tokengs_jax.model.colours import InputViews, viewer_colours

  config, params = baseline
  viewer = config.replace(input_colour_weights="viewer")
  images, c2w, intrinsics = scene
  per_camera = pixel_baseline.jitted_reconstruct(params, *scene, viewer, c2w)
  assert per_camera.means.shape == (1, 2) + gaussians.means.shape[1:]
  for t in range(2):
    np.testing.assert_allclose(per_camera.means[:, t], gaussians.means, atol=1e-6)
  means = jnp.asarray(gaussians.means)
  views = InputViews(images, invert_rigid(c2w), intrinsics)
  expected, _ = viewer_colours(means, views, means, c2w[..., :3, 3], viewer.viewer_colour_sharpness)
  np.testing.assert_allclose(per_camera.colors, expected, atol=1e-5)
  assert np.abs(np.asarray(per_camera.colors[:, 0] - per_camera.colors[:, 1])).max() > 0.05
