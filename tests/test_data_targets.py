"""Tests for tokengs_jax.data.targets: the target views' per-pixel truth (scene flow here; the
object and mask fields are tested through `make_example` in test_data_transforms.py)."""

import dataclasses

import numpy as np
import pytest

from tokengs_jax.data import BadExampleError, BoundedSamplerConfig, ExampleConfig, make_example

FRAMES, HEIGHT, WIDTH = 6, 8, 12


def _rotation(rng) -> np.ndarray:
  q, r = np.linalg.qr(rng.normal(size=(3, 3)))
  q = q * np.sign(np.diag(r))
  return q if np.linalg.det(q) > 0 else -q


def _moving_object_record(rng, step: np.ndarray) -> dict:
  """One camera over FRAMES frames (a new pose each), depth 2 everywhere, the left half of every
  frame on object 1, which translates by `step` per frame under a fixed rotation."""
  c2w = np.tile(np.eye(4), (FRAMES, 1, 1))
  for f in range(FRAMES):
    c2w[f, :3, :3], c2w[f, :3, 3] = _rotation(rng), rng.normal(size=3)
  poses = np.tile(np.eye(4), (1, FRAMES, 1, 1))
  poses[0, :, :3, :3] = _rotation(rng)
  poses[0, :, :3, 3] = rng.normal(size=3) + np.arange(FRAMES)[:, None] * step
  segmentation = np.zeros((HEIGHT, WIDTH), np.int32)
  segmentation[:, : WIDTH // 2] = 1
  return {
    "key": "k",
    "height": HEIGHT,
    "width": WIDTH,
    "c2w": c2w.astype(np.float32),
    "intrinsics": np.tile(np.array([10.0, 10.0, 6.0, 4.0], np.float32), (FRAMES, 1)),
    "images": list(rng.integers(0, 255, (FRAMES, HEIGHT, WIDTH, 3), dtype=np.uint8)),
    "depths": [np.full((HEIGHT, WIDTH), 2.0, np.float32)] * FRAMES,
    "segmentations": [segmentation] * FRAMES,
    "times": np.arange(FRAMES),
    "object_poses": poses,
  }


@pytest.mark.parametrize("target", [2, 5])
def test_target_flows_are_the_objects_velocity_in_the_example_frame(target):
  """A translating object: every pixel on it moves by its per-frame step (one-sided at the last
  frame), carried into the example's frame (first input camera, scale 0.25) per unit of
  normalised time (the example spans frames 0..5); the background does not move; a flipped
  example mirrors the map and the world's x."""
  rng = np.random.default_rng(0)
  step = np.array([0.3, -0.1, 0.2])
  record = _moving_object_record(rng, step)
  sampler = BoundedSamplerConfig(2, 1, 1, 5, 0, 0, 1, 5)
  config = ExampleConfig((HEIGHT, WIDTH), sampler, 0.25, random_flip=False, target_flows=True)
  views = (np.array([0, 3 if target == 5 else 5]), np.array([target]))
  example = make_example(record, config, rng, views=views)
  flows = example["target_flows"]
  assert flows.shape == (1, HEIGHT, WIDTH, 3) and flows.dtype == np.float32
  first_camera = np.asarray(record["c2w"][0], np.float64)[:3, :3]
  expected = 0.25 * 5 * first_camera.T @ step
  np.testing.assert_allclose(
    flows[0, :, : WIDTH // 2], np.broadcast_to(expected, (HEIGHT, 6, 3)), rtol=1e-5, atol=1e-6
  )
  assert (flows[0, :, WIDTH // 2 :] == 0).all()
  flipped = dataclasses.replace(config, random_flip=True)
  mirrored = 0
  for seed in range(8):
    other = make_example(record, flipped, np.random.default_rng(seed), views=views)
    if np.allclose(other["target_images"], example["target_images"][:, :, ::-1]):
      mirrored += 1
      np.testing.assert_allclose(
        other["target_flows"], flows[:, :, ::-1] * np.array([-1.0, 1.0, 1.0]), atol=1e-6
      )
  assert 0 < mirrored < 8


def test_target_flows_need_the_object_poses():
  record = _moving_object_record(np.random.default_rng(1), np.ones(3))
  del record["object_poses"]
  sampler = BoundedSamplerConfig(2, 1, 1, 5, 0, 0, 1, 5)
  config = ExampleConfig((HEIGHT, WIDTH), sampler, 0.25, random_flip=False, target_flows=True)
  with pytest.raises(BadExampleError, match="object_poses"):
    make_example(record, config, np.random.default_rng(0), views=(np.array([0, 1]), np.array([2])))


def test_target_flows_refuse_a_non_finite_depth_map():
  """A NaN on an object pixel of the target's depth map would be a NaN velocity and a NaN loss:
  the example is refused as bad data instead, naming the frame."""
  record = _moving_object_record(np.random.default_rng(2), np.ones(3))
  damaged = np.full((HEIGHT, WIDTH), 2.0, np.float32)
  damaged[3, 2] = np.nan
  record["depths"] = [damaged if f == 2 else d for f, d in enumerate(record["depths"])]
  sampler = BoundedSamplerConfig(2, 1, 1, 5, 0, 0, 1, 5)
  config = ExampleConfig((HEIGHT, WIDTH), sampler, 0.25, random_flip=False, target_flows=True)
  with pytest.raises(BadExampleError, match=r"frames \[2\].*1 of 96 depth values are NaN or inf"):
    make_example(record, config, np.random.default_rng(0), views=(np.array([0, 1]), np.array([2])))
  # the same record with the damage in a frame no example view uses still gives its flows
  example = make_example(
    record, config, np.random.default_rng(0), views=(np.array([0, 1]), np.array([3]))
  )
  assert np.isfinite(example["target_flows"]).all()
