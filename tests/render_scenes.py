"""The random Gaussian scenes and the camera that the splatting tests share (imported by them; no
tests here): Gaussians around the origin, seen by a camera 3 units away looking down +z, in an
image whose sides are not tile multiples."""

import numpy as np

from tokengs_jax.gaussians import Gaussians

HEIGHT, WIDTH, NUM = 40, 52, 48  # not tile multiples: exercises edge-tile padding
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
