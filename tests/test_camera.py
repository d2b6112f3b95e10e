import jax
import jax.numpy as jnp
import numpy as np

from conftest import reference_fixture
from tokengs_jax import camera


def _random_pose(key):
  q = jax.random.normal(key, (4,))
  from tokengs_jax.math import quat_to_rotmat

  pose = jnp.eye(4).at[:3, :3].set(quat_to_rotmat(q)).at[:3, 3].set(jax.random.normal(key, (3,)))
  return pose


def test_invert_rigid_matches_inverse():
  pose = _random_pose(jax.random.PRNGKey(1))
  np.testing.assert_allclose(camera.invert_rigid(pose), np.linalg.inv(np.asarray(pose)), atol=1e-5)


def test_plucker_matches_official_ray_condition_fixture():
  io = np.load(reference_fixture("official_tokengs_tiny", "io.npz"))
  expected = np.moveaxis(io["plucker"], 2, -1)  # [B, V, H, W, 6]
  h, w = expected.shape[2:4]
  ours = camera.plucker_rays(jnp.asarray(io["c2w"]), jnp.asarray(io["intrinsics"]), h, w)
  assert ours.shape == expected.shape
  np.testing.assert_allclose(ours, expected, atol=1e-5)


def test_project_points_hits_the_pixel_its_ray_came_from():
  c2w = _random_pose(jax.random.PRNGKey(2))
  intr = jnp.array([40.0, 42.0, 16.5, 11.0])
  dirs = camera.ray_directions(c2w, intr, 24, 32)
  pts = c2w[:3, 3] + 3.0 * dirs[7, 5]
  uv, depth = camera.project_points(pts[None], camera.invert_rigid(c2w)[None], intr[None])
  np.testing.assert_allclose(uv[0, 0], [5.5, 7.5], atol=1e-3)
  assert depth[0, 0] > 0


def test_intrinsics_round_trip():
  k = camera.intrinsics_matrix(jnp.array([1.0, 2.0, 3.0, 4.0]))
  np.testing.assert_allclose(k, [[1, 0, 3], [0, 2, 4], [0, 0, 1]])
  np.testing.assert_allclose(
    camera.intrinsics_to_pixels(jnp.array([0.5, 0.5, 0.5, 0.5]), 36, 64), [32, 18, 32, 18]
  )
