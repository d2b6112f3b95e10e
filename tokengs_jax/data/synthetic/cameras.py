"""Camera poses and paths for synthetic scenes (numpy, OpenCV axes, world +y up).

RE10K clips are real-estate walk-throughs: smooth forward motion with slow pans and small
hand-held jitter. `forward_walk` reproduces that: a heading that drifts smoothly (integrated
Ornstein-Uhlenbeck yaw rate), a look direction that may be turned away from the direction of travel
(partly sideways dolly shots), small pitch oscillation, tiny roll and positional jitter.
"""

from __future__ import annotations

import dataclasses

import numpy as np

WORLD_UP = np.array([0.0, 1.0, 0.0])


def look_rotation(forward: np.ndarray, up: np.ndarray = WORLD_UP) -> np.ndarray:
  """OpenCV camera-to-world rotation looking along `forward` (+z), upright (-y closest to `up`).

  forward: [..., 3], up: [3] -> [..., 3, 3] with columns (right, down, forward).
  """
  forward = forward / np.linalg.norm(forward, axis=-1, keepdims=True)
  down = -up - np.sum(-up * forward, axis=-1, keepdims=True) * forward
  down = down / np.linalg.norm(down, axis=-1, keepdims=True)
  right = np.cross(down, forward)  # OpenCV is right-handed: x = y cross z
  return np.stack([right, down, forward], axis=-1)


def pose_matrix(rotation: np.ndarray, position: np.ndarray) -> np.ndarray:
  """rotation [..., 3, 3], position [..., 3] -> c2w [..., 4, 4]."""
  pose = np.zeros(rotation.shape[:-2] + (4, 4), dtype=np.float64)
  pose[..., :3, :3] = rotation
  pose[..., :3, 3] = position
  pose[..., 3, 3] = 1.0
  return pose


def look_at(position: np.ndarray, target: np.ndarray, up: np.ndarray = WORLD_UP) -> np.ndarray:
  """c2w [..., 4, 4] of cameras at `position [..., 3]` looking at `target [..., 3]`."""
  return pose_matrix(look_rotation(target - position, up), position)


def _roll(angle: np.ndarray) -> np.ndarray:
  """Rotation about the camera z axis.  angle: [F] -> [F, 3, 3]."""
  c, s = np.cos(angle), np.sin(angle)
  zero, one = np.zeros_like(angle), np.ones_like(angle)
  return np.stack(
    [np.stack([c, -s, zero], -1), np.stack([s, c, zero], -1), np.stack([zero, zero, one], -1)], -2
  )


def _direction(yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
  """Unit vectors; yaw about +y (0 looks along +z), pitch > 0 looks up.  -> [..., 3]."""
  return np.stack([np.sin(yaw) * np.cos(pitch), np.sin(pitch), np.cos(yaw) * np.cos(pitch)], -1)


@dataclasses.dataclass(frozen=True)
class WalkConfig:
  """Ranges of the RE10K-like walk (metres, radians, per frame unless said otherwise)."""

  step: tuple[float, float] = (0.03, 0.08)  # distance travelled per frame
  yaw_rate_std: float = 0.012  # stationary std of the heading's angular velocity
  yaw_rate_decay: float = 0.85  # OU persistence of the angular velocity per frame
  look_offset: tuple[float, float] = (-0.5, 0.5)  # look direction minus travel direction (yaw)
  sideways_probability: float = 0.15  # chance of a lateral dolly (look offset +-90 degrees)
  pitch: tuple[float, float] = (-0.15, 0.05)  # mean camera pitch
  pitch_wobble: float = 0.03  # amplitude of the slow pitch oscillation
  roll_std: float = 0.01
  position_jitter: float = 0.005  # hand-held shake (std, metres)
  height: tuple[float, float] = (1.2, 1.7)  # camera height above the floor


def forward_walk(
  rng: np.random.Generator,
  frames: int,
  start: np.ndarray,
  heading: float,
  config: WalkConfig = WalkConfig(),
) -> np.ndarray:
  """A smooth hand-held walk of `frames` OpenCV c2w poses, starting at `start [3]` (x, z used;
  the height is sampled) with travel direction `heading` (yaw, radians).  -> [F, 4, 4].
  """
  step = rng.uniform(*config.step)
  yaw_rate = np.zeros(frames)
  # OU process with the stationary std `yaw_rate_std`: the heading bends smoothly, never jerks.
  innovation = config.yaw_rate_std * np.sqrt(1.0 - config.yaw_rate_decay**2)
  rate = rng.normal(0.0, config.yaw_rate_std)
  for f in range(frames):
    yaw_rate[f] = rate
    rate = config.yaw_rate_decay * rate + innovation * rng.normal()
  travel_yaw = heading + np.concatenate([[0.0], np.cumsum(yaw_rate[:-1])])
  travel = _direction(travel_yaw, np.zeros(frames))
  positions = np.concatenate([[np.zeros(3)], np.cumsum(step * travel[:-1], axis=0)])
  positions += np.array([start[0], rng.uniform(*config.height), start[2]])
  positions += rng.normal(0.0, config.position_jitter, positions.shape)

  if rng.uniform() < config.sideways_probability:
    look_offset = rng.choice([-0.5, 0.5]) * np.pi + rng.uniform(-0.2, 0.2)
  else:
    look_offset = rng.uniform(*config.look_offset)
  phase = rng.uniform(0.0, 2.0 * np.pi)
  period = rng.uniform(0.5, 1.5) * frames
  pitch = rng.uniform(*config.pitch) + config.pitch_wobble * np.sin(
    phase + 2.0 * np.pi * np.arange(frames) / period
  )
  rotation = look_rotation(_direction(travel_yaw + look_offset, pitch))
  rotation = rotation @ _roll(rng.normal(0.0, config.roll_std, frames))
  return pose_matrix(rotation, positions)


def orbit_cameras(
  rng: np.random.Generator,
  num_cameras: int,
  frames: int,
  target: np.ndarray,
  radius: tuple[float, float] = (7.0, 10.0),
  elevation: tuple[float, float] = (0.25, 0.6),
  drift: float = 0.15,
) -> np.ndarray:
  """Kubric-like rig: cameras spread around `target [3]` on a ring, each drifting slowly along
  its orbit over time (`drift` radians over the sequence) while looking at the target.

  -> c2w [num_cameras, frames, 4, 4] (OpenCV).
  """
  azimuth0 = rng.uniform(0, 2 * np.pi) + 2 * np.pi * np.arange(num_cameras) / num_cameras
  azimuth0 += rng.uniform(-0.2, 0.2, num_cameras)
  elevation = rng.uniform(*elevation, num_cameras)
  distance = rng.uniform(*radius, num_cameras)
  sweep = rng.uniform(-drift, drift, num_cameras)[:, None] * np.linspace(0.0, 1.0, frames)[None]
  azimuth = azimuth0[:, None] + sweep  # [C, F]
  offset = distance[:, None, None] * _direction(
    azimuth, np.broadcast_to(elevation[:, None], azimuth.shape)
  )
  positions = target + offset
  return look_at(positions, np.broadcast_to(target, positions.shape))


def pinhole_intrinsics(height: int, width: int, fov_x: float) -> np.ndarray:
  """Square-pixel intrinsics with horizontal field of view `fov_x` (radians).  -> [4] pixels."""
  focal = 0.5 * width / np.tan(0.5 * fov_x)
  return np.array([focal, focal, 0.5 * width, 0.5 * height])


@dataclasses.dataclass(frozen=True)
class ArcConfig:
  """Ranges of `arc_path`, the gallery family's camera path (metres, radians)."""

  radius: tuple[float, float] = (1.3, 2.3)  # distance from the point of interest
  step: tuple[float, float] = (0.04, 0.09)  # arc length travelled per frame
  height: tuple[float, float] = (0.9, 2.0)  # camera height above the floor
  look_height: tuple[float, float] = (0.6, 1.4)  # height of the point looked at
  look_wander: float = 0.3  # the look-at point drifts by up to this much over the path
  position_jitter: float = 0.004


def arc_path(
  rng: np.random.Generator, frames: int, centre: np.ndarray, config: ArcConfig = ArcConfig()
) -> np.ndarray:
  """Cameras on a circular arc around `centre [3]` (x, z used), all looking inwards at a slowly
  drifting point near it: an object-centric orbit, unlike `forward_walk`'s travel along the view
  direction.  -> c2w [F, 4, 4] (OpenCV).
  """
  radius = rng.uniform(*config.radius)
  angle_step = rng.choice([-1.0, 1.0]) * rng.uniform(*config.step) / radius
  angle = rng.uniform(0, 2 * np.pi) + angle_step * np.arange(frames)
  height = rng.uniform(*config.height)
  positions = np.stack(
    [
      centre[0] + radius * np.sin(angle),
      np.full(frames, height),
      centre[2] + radius * np.cos(angle),
    ],
    -1,
  )
  positions += rng.normal(0.0, config.position_jitter, positions.shape)
  wander = rng.uniform(-1.0, 1.0, 3) * config.look_wander
  look = np.array([centre[0], rng.uniform(*config.look_height), centre[2]])
  targets = look + np.linspace(0.0, 1.0, frames)[:, None] * wander
  return look_at(positions, targets)
