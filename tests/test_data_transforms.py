"""Camera transforms (`tokengs_jax.data.transforms`): a 3D point lands on the same image content
after every transform, and the host-side rigid inverse equals the JAX one."""

import jax.numpy as jnp
import numpy as np
import pytest

from tokengs_jax import camera
from tokengs_jax.camera import project_points
from tokengs_jax.data import transforms

H, W = 40, 64


def _camera_looking_at_origin(rng):
  eye = rng.normal(size=3) * 0.5 + np.array([0.0, 0.0, -4.0])
  forward = -eye / np.linalg.norm(eye)
  right = np.cross([0.0, 1.0, 0.0], forward)
  right /= np.linalg.norm(right)
  down = np.cross(forward, right)
  c2w = np.eye(4)
  c2w[:3, :3] = np.stack([right, down, forward], axis=1)
  c2w[:3, 3] = eye
  return c2w


def _project(point, c2w, intrinsics):
  uv, depth = project_points(
    np.asarray(point, np.float32)[None],
    transforms.rigid_inverse(c2w).astype(np.float32)[None],
    np.asarray(intrinsics, np.float32)[None],
  )
  assert float(depth[0, 0]) > 0
  return np.asarray(uv[0, 0], np.float64)


def _blob_image(uv, height, width, sigma=2.0):
  """A Gaussian blob centred on continuous pixel coordinate uv (pixel centres at +0.5)."""
  v, u = np.mgrid[0:height, 0:width] + 0.5
  blob = np.exp(-((u - uv[0]) ** 2 + (v - uv[1]) ** 2) / (2 * sigma**2))
  return np.repeat((blob * 255).round().astype(np.uint8)[..., None], 3, axis=-1)


def _centroid(image):
  weight = image[..., 0].astype(np.float64)
  v, u = np.mgrid[0 : image.shape[0], 0 : image.shape[1]] + 0.5
  return np.array([(u * weight).sum(), (v * weight).sum()]) / weight.sum()


@pytest.fixture
def scene():
  rng = np.random.default_rng(3)
  c2w = np.stack([_camera_looking_at_origin(rng) for _ in range(3)])
  intrinsics = np.array([[50.0, 52.0, 30.5, 21.0]] * 3)
  point = np.array([0.1, -0.05, 0.2])
  images = np.stack([_blob_image(_project(point, c, k), H, W) for c, k in zip(c2w, intrinsics)])
  return c2w, intrinsics, point, images


@pytest.mark.parametrize("shape", [(24, 24), (32, 40), (40, 64), (80, 96)])
def test_resize_crop_keeps_projection_on_the_content(scene, shape):
  c2w, intrinsics, point, images = scene
  out_images, out_intrinsics = transforms.resize_and_center_crop(images, intrinsics, shape)
  assert out_images.shape == (3, *shape, 3) and out_images.dtype == np.uint8
  for view in range(3):
    uv = _project(point, c2w[view], out_intrinsics[view])
    np.testing.assert_allclose(_centroid(out_images[view]), uv, atol=0.3)


def test_flip_mirrors_world_and_image_together(scene):
  c2w, intrinsics, point, images = scene
  flipped, c2w_f, intr_f = transforms.flip_horizontal(images, c2w, intrinsics)
  mirrored = point * np.array([-1.0, 1.0, 1.0])
  for view in range(3):
    uv = _project(point, c2w[view], intrinsics[view])
    uv_f = _project(mirrored, c2w_f[view], intr_f[view])
    np.testing.assert_allclose(uv_f, [W - uv[0], uv[1]], atol=1e-4)
    np.testing.assert_allclose(_centroid(flipped[view]), uv_f, atol=0.05)
    np.testing.assert_allclose(
      np.linalg.det(c2w_f[view, :3, :3]), 1.0, atol=1e-5
    )  # still a rotation


@pytest.mark.parametrize("method", ["first_cam", "mean_cam"])
@pytest.mark.parametrize("scale_method", ["constant", "distance", "bound"])
def test_normalisation_and_scale_keep_projections(scene, method, scale_method):
  c2w, intrinsics, point, _ = scene
  normalised = transforms.normalize_cameras(c2w, 2, method)
  if method == "first_cam":
    np.testing.assert_allclose(normalised[0], np.eye(4), atol=1e-6)
  else:  # the mean context camera is at the origin, looking down +z on average
    np.testing.assert_allclose(normalised[:2, :3, 3].mean(0), 0.0, atol=1e-5)
    np.testing.assert_allclose(normalised[:2, :3, 2].mean(0)[:2], 0.0, atol=1e-5)
  scale = transforms.translation_scale(normalised, 2, 0.25, scale_method)
  normalised[:, :3, 3] *= scale
  reference = c2w[0] if method == "first_cam" else transforms._mean_camera(c2w[:2])
  moved = (transforms.rigid_inverse(reference) @ np.append(point, 1.0))[:3] * scale
  for view in range(3):
    np.testing.assert_allclose(
      _project(moved, normalised[view], intrinsics[view]),
      _project(point, c2w[view], intrinsics[view]),
      atol=2e-3,
    )


def test_all_transforms_chained(scene):
  """Crop, normalise + scale, flip: the point still lands on the blob in every view."""
  c2w, intrinsics, point, images = scene
  images, intrinsics = transforms.resize_and_center_crop(images, intrinsics, (32, 32))
  normalised = transforms.normalize_cameras(c2w, 2, "first_cam")
  images, normalised, intrinsics = transforms.flip_horizontal(images, normalised, intrinsics)
  normalised[:, :3, 3] *= 0.25
  moved = (
    (transforms.rigid_inverse(c2w[0]) @ np.append(point, 1.0))[:3] * 0.25 * np.array([-1, 1, 1])
  )
  for view in range(3):
    np.testing.assert_allclose(
      _centroid(images[view]), _project(moved, normalised[view], intrinsics[view]), atol=0.3
    )


def test_unknown_methods_raise(scene):
  with pytest.raises(ValueError, match="normalisation"):
    transforms.normalize_cameras(scene[0], 2, "median_cam")
  with pytest.raises(ValueError, match="scale method"):
    transforms.translation_scale(scene[0], 2, 0.1, "huge")


def test_depth_follows_the_image_crop_and_keeps_unknown_pixels_unknown():

  depth = np.full((1, 48, 64), 3.0, np.float32)
  depth[:, :, 40:] = 0.0  # nothing hit on the right: unknown
  image = np.where(depth[..., None] > 0, 200, 0).astype(np.uint8).repeat(3, -1)
  for shape in [(24, 24), (24, 32), (40, 40)]:
    cropped, _ = transforms.resize_and_center_crop(image, np.array([[40.0, 40, 32, 24]]), shape)
    resized = transforms.resize_and_center_crop_depth(depth, shape)
    assert resized.shape == (1, *shape) and resized.dtype == np.float32
    assert set(np.unique(resized)) <= {0.0, 3.0}  # no blend of a surface with "unknown"
    # Known where the image is fully the surface, unknown where it is fully empty.
    assert (resized[cropped[..., 0] == 200] == 3.0).all()
    assert (resized[cropped[..., 0] == 0] == 0.0).all()


def test_values_follow_the_image_crop_with_their_sign():
  """Signed per-pixel values (a scene-flow component) go through the images' scale and crop:
  negative on the left of the frame, positive on the right, wherever the image is dark / light."""
  values = np.full((1, 48, 64), -0.5, np.float32)
  values[:, :, 32:] = 2.0
  image = np.where(values[..., None] > 0, 200, 0).astype(np.uint8).repeat(3, -1)
  for shape in [(24, 24), (24, 32), (40, 40)]:
    cropped, _ = transforms.resize_and_center_crop(image, np.array([[40.0, 40, 32, 24]]), shape)
    resized = transforms.resize_and_center_crop_values(values, shape)
    assert resized.shape == (1, *shape) and resized.dtype == np.float32
    np.testing.assert_allclose(resized[cropped[..., 0] == 0], -0.5, atol=1e-6)
    np.testing.assert_allclose(resized[cropped[..., 0] == 200], 2.0, atol=1e-6)


@pytest.mark.parametrize("field", ["target_depths", "target_objects", "target_masks"])
def test_make_example_per_target_maps_follow_the_targets_images(field):
  """`target_depths` (the record's depths, scaled as the cameras), `target_objects` (its
  segmentations > 0, float32) and `target_masks` (its alphas / 255) are the targets' maps,
  mirrored whenever the images are; absent when not asked for; objects without segmentations
  or masks without alphas are a bad example."""
  import dataclasses

  from tokengs_jax.data import BadExampleError, BoundedSamplerConfig, ExampleConfig, make_example

  rng = np.random.default_rng(0)
  frames, height, width = 4, 8, 12
  if field == "target_depths":
    stored, maps = "depths", rng.uniform(1.0, 5.0, (frames, height, width)).astype(np.float32)
    expected = 0.25 * maps[[2]]
  elif field == "target_objects":
    stored, maps = "segmentations", rng.integers(0, 3, (frames, height, width)).astype(np.int32)
    expected = (maps[[2]] > 0).astype(np.float32)
  else:
    stored, maps = "alphas", rng.integers(0, 256, (frames, height, width), dtype=np.uint8)
    expected = maps[[2]] / np.float32(255.0)
  record = {
    "key": "k",
    "height": height,
    "width": width,
    "c2w": np.tile(np.eye(4, dtype=np.float32), (frames, 1, 1)),
    "intrinsics": np.tile(np.array([10.0, 10.0, 6.0, 4.0], np.float32), (frames, 1)),
    "images": list(rng.integers(0, 255, (frames, height, width, 3), dtype=np.uint8)),
    stored: list(maps),
  }
  sampler = BoundedSamplerConfig(2, 1, 1, 3, 0, 0, 1, 3)
  config = ExampleConfig((height, width), sampler, 0.25, random_flip=False, **{field: True})
  views = (np.array([0, 3]), np.array([2]))
  example = make_example(record, config, rng, views=views)
  assert example[field].dtype == np.float32
  np.testing.assert_allclose(example[field], expected, rtol=1e-6)
  flipped = dataclasses.replace(config, random_flip=True)
  flips = 0
  for seed in range(8):
    other = make_example(record, flipped, np.random.default_rng(seed), views=views)
    mirrored = np.allclose(other["target_images"], example["target_images"][:, :, ::-1])
    flips += mirrored
    np.testing.assert_allclose(
      other[field], example[field][:, :, ::-1] if mirrored else example[field]
    )
  assert 0 < flips < 8
  off = make_example(record, dataclasses.replace(config, **{field: False}), rng, views=views)
  assert field not in off
  if field != "target_depths":
    without = {name: value for name, value in record.items() if name != stored}
    with pytest.raises(BadExampleError, match=f"{field} needs the record's '{stored}'"):
      make_example(without, config, rng, views=views)


def test_rigid_inverse_matches_the_jax_camera_inverse():
  rng = np.random.default_rng(0)
  q, _ = np.linalg.qr(rng.normal(size=(5, 3, 3)))
  pose = np.tile(np.eye(4), (5, 1, 1))
  pose[:, :3, :3], pose[:, :3, 3] = q, rng.normal(size=(5, 3))
  host = transforms.rigid_inverse(pose)
  np.testing.assert_allclose(
    host, np.asarray(camera.invert_rigid(jnp.asarray(pose, jnp.float32))), atol=1e-5
  )
  np.testing.assert_allclose(host @ pose, np.broadcast_to(np.eye(4), pose.shape), atol=1e-12)
