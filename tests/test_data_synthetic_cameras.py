"""Camera paths (`synthetic.cameras`): the forward walk is smooth and upright."""

import numpy as np

from tokengs_jax.data.synthetic import cameras


def test_forward_walk_is_a_smooth_opencv_trajectory():
  frames = 32
  c2w = cameras.forward_walk(np.random.default_rng(7), frames, np.zeros(3), heading=0.3)
  assert c2w.shape == (frames, 4, 4)
  rot = c2w[:, :3, :3]
  np.testing.assert_allclose(
    rot @ np.swapaxes(rot, 1, 2), np.broadcast_to(np.eye(3), rot.shape), atol=1e-9
  )
  np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-9)
  assert (rot[:, :, 1] @ cameras.WORLD_UP < -0.95).all()  # camera +y (down) points down: upright
  steps = np.linalg.norm(np.diff(c2w[:, :3, 3], axis=0), axis=-1)
  config = cameras.WalkConfig()
  assert steps.min() > config.step[0] - 0.05 and steps.max() < config.step[1] + 0.05
  turn = np.arccos(np.clip(np.einsum("fi,fi->f", rot[1:, :, 2], rot[:-1, :, 2]), -1, 1))
  assert turn.max() < 0.1  # no jumps in look direction between frames
