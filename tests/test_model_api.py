"""The model's functional API (`tokengs_jax.model.api`): reconstruct from raw images and cameras
(official parity), decode at times, jit / vmap / grad, encode_views, the Gaussian count, and
image normalisation."""

import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scenes import (
  DYNAMIC_CONFIG,
  MICRO,
  dynamic_batch,
  dynamic_params,
  micro_params,
  official_fixture,
  random_inputs,
)

from tokengs_jax import model
from tokengs_jax.camera import plucker_rays
from tokengs_jax.gaussians import Gaussians
from tokengs_jax.model import (
  decode_at_times,
  encode,
  encode_views,
  normalize_images,
  param_shapes,
  reconstruct,
)
from tokengs_jax.model.configs import IMAGE_MEAN, IMAGE_STD


def test_official_reconstruct_from_raw_images_and_cameras():
  """reconstruct = our ImageNet normalisation + our Plücker rays + the network."""
  config, params, io = official_fixture()
  images01 = io["images_rgb"] * np.array(IMAGE_STD) + np.array(IMAGE_MEAN)
  run = jax.jit(functools.partial(reconstruct, config=config))
  gaussians = run(params, images01, io["c2w"], io["intrinsics"])
  assert isinstance(gaussians, Gaussians)
  np.testing.assert_allclose(gaussians.to_flat(), io["gaussians"], rtol=0, atol=1e-4)


def test_gaussian_count_is_independent_of_views_and_resolution():
  params = param_shapes(MICRO)
  counts = set()
  for views, height, width in ((1, 8, 8), (3, 12, 16), (6, 32, 4)):
    images, c2w, intrinsics = random_inputs(jax.random.key(views), 2, views, height, width)
    shapes = jax.eval_shape(
      functools.partial(reconstruct, config=MICRO), params, images, c2w, intrinsics
    )  # shapes only, nothing is computed
    counts.add(shapes.means.shape)
  assert counts == {(2, MICRO.num_gaussians, 3)}
  assert MICRO.num_gaussians == 4 * 2 * 2


def test_decode_at_times_equals_reconstruct_at_each_time():
  params = dynamic_params()
  batch = dynamic_batch([[0.0, 1.0], [0.2, 0.9]], [[0.5, 0.0, 1.0], [0.3, 0.6, 0.1]])
  context = (batch["context_images"], batch["context_c2w"], batch["context_intrinsics"])

  @jax.jit
  def decoded(params, images, c2w, intrinsics, times, target_times):
    encoded = model.encode_views(params, images, c2w, intrinsics, DYNAMIC_CONFIG, times=times)
    return decode_at_times(params, encoded, DYNAMIC_CONFIG, target_times)

  reconstruct = jax.jit(
    lambda *args, **kwargs: model.reconstruct(*args, config=DYNAMIC_CONFIG, **kwargs)
  )
  at_times = decoded(params, *context, batch["context_times"], batch["target_times"])
  assert at_times.batch_shape == (2, 3)
  static = DYNAMIC_CONFIG.num_static_gaussians
  for t in range(3):
    expected = reconstruct(
      params, *context, times=batch["context_times"], target_times=batch["target_times"][:, t]
    )
    at_t = jax.tree.map(lambda x, index=t: x[:, index], at_times)
    jax.tree.map(
      lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6), at_t, expected
    )
  # static Gaussians do not depend on the time, dynamic ones do
  means = np.asarray(at_times.means)
  np.testing.assert_allclose(means[:, 1, :static], means[:, 0, :static], rtol=1e-6, atol=1e-7)
  assert np.abs(means[:, 1, static:] - means[:, 0, static:]).max() > 1e-3


def test_jit_vmap_grad_through_reconstruct():
  params = micro_params()
  images, c2w, intrinsics = random_inputs(jax.random.key(1), 3, 2, 8, 8)

  def loss(p, imgs, cams, intr):
    g = reconstruct(p, imgs, cams, intr, config=MICRO)
    return jnp.sum(g.means**2) + jnp.sum(g.colors) + jnp.sum(g.opacities), g

  grad = jax.grad(loss, argnums=(0, 1), has_aux=True)
  (grads, image_grad), batched = jax.jit(grad)(params, images, c2w, intrinsics)
  # the same per scene, through vmap: the batched loss is the sum of the per-scene ones
  per_scene = jax.jit(jax.vmap(lambda i, c, k: grad(params, i[None], c[None], k[None])))
  (scene_grads, scene_image_grad), scene_gaussians = per_scene(images, c2w, intrinsics)
  np.testing.assert_allclose(scene_gaussians.means[:, 0], batched.means, atol=1e-5)
  np.testing.assert_allclose(scene_image_grad[:, 0], image_grad, atol=1e-5)
  jax.tree.map(
    lambda a, b: np.testing.assert_allclose(a.sum(0), b, rtol=1e-4, atol=1e-5), scene_grads, grads
  )
  assert all(np.all(np.isfinite(g)) for g in jax.tree.leaves(grads))
  assert np.abs(np.asarray(grads["gs_tokens"])).max() > 0
  assert np.abs(np.asarray(grads["patch_embed"]["proj"]["kernel"])).max() > 0
  assert np.abs(np.asarray(image_grad)).max() > 0


def test_encode_views_is_normalise_plucker_encode():
  params = micro_params()
  images, c2w, intrinsics = random_inputs(jax.random.key(4), 2, 2, 8, 8)
  run = jax.jit(functools.partial(encode_views, config=MICRO))
  encoded = run(params, images, c2w, intrinsics)
  expected = jax.jit(encode, static_argnums=3)(
    params, normalize_images(images), plucker_rays(c2w, intrinsics, 8, 8), MICRO
  )
  # one program vs two: equal up to XLA's fusion-dependent rounding
  chex.assert_trees_all_close(encoded, expected, rtol=0, atol=1e-5)


def test_normalize_images_scales_uint8_and_refuses_what_it_cannot_convert():
  """uint8 is scaled by 1/255 (it once cast the ImageNet mean/std to uint8: NaN Gaussians);
  grayscale, integer types and 0..255 floats are refused with a message naming `images`."""
  rng = np.random.default_rng(0)
  pixels = rng.integers(0, 256, (2, 4, 5, 3), dtype=np.uint8)
  from_uint8 = np.asarray(normalize_images(pixels))
  assert from_uint8.dtype == np.float32 and np.isfinite(from_uint8).all()
  np.testing.assert_allclose(
    from_uint8, np.asarray(normalize_images(pixels / np.float32(255))), atol=1e-6
  )
  np.testing.assert_allclose(np.asarray(jax.jit(normalize_images)(pixels)), from_uint8, atol=1e-6)
  with pytest.raises(ValueError, match=r"images: expected RGB \[\.\.\., 3\].*grayscale"):
    normalize_images(pixels[..., :1])
  with pytest.raises(TypeError, match="images: expected float in .0, 1. or uint8.*int32"):
    normalize_images(pixels.astype(np.int32))
  with pytest.raises(ValueError, match=r"images: expected float values in \[0, 1\].*divide by 255"):
    normalize_images(pixels.astype(np.float32))
  with_nan = (pixels / np.float32(255)).copy()
  with_nan[1, 2, 3, 0] = np.nan  # NaN compares false: it once passed the range check
  with pytest.raises(ValueError, match=r"images: expected float values in \[0, 1\], got \[nan"):
    normalize_images(with_nan)


def test_normalize_images_checks_a_constant_captured_by_an_outer_jit():
  """A concrete array closed over by a jitted function is range-checked on the host (numpy),
  not with jnp ops that the outer trace would stage."""
  images = jnp.full((1, 2, 2, 3), 0.5)
  np.testing.assert_allclose(
    jax.jit(lambda: normalize_images(images))(), normalize_images(images), atol=1e-6
  )
