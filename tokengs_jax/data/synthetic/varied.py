"""The varied-room training family: domain randomisation of everything a room scene has.

`scenes.sample_room_scene` draws one kind of room (a rectangle, four procedural texture kinds,
boxes and spheres on the floor, white light from above, a forward walk). A model trained on it
learns that generator, not geometry (issue 23: −0.34 dB against copying the nearest input view on
rooms from an independent ray tracer). This family widens every axis at once:

| axis | drawn here |
|---|---|
| room | rectangle 1.8-6 m half sizes, 2.2-4.5 m high, plus 0-2 partition walls (occlusion) |
| textures | photographs (`photos.TRAIN_PHOTOS`, natural-image statistics) on most surfaces, else the rooms' procedural kinds |
| objects | 2-11 of: boxes and spheres on the floor, floating ones, stacks, columns; 0.12-0.8 m |
| light | any azimuth, 15-85 degrees elevation, mildly tinted, ambient 0.15-0.55 |
| camera | a randomised forward walk or an inward arc (`cameras.arc_path`) |

The field of view is drawn by the dataset writer (`generate.Re10kLikeConfig.fov_x_degrees`). The
held-out families share none of the photographs (`photos.HELD_OUT_PHOTOS` are only drawn by the
frozen test family, `synthetic.courtyards`) and none of the gallery texture kinds.
"""

from __future__ import annotations

import colorsys
import dataclasses

import numpy as np

from tokengs_jax.data.synthetic import cameras, photos
from tokengs_jax.data.synthetic.raytrace import Box, Scene, Sphere, Texture
from tokengs_jax.data.synthetic.scenes import (
  _PATTERNS,
  light_direction,
  random_color,
  random_rotation,
  random_texture,
  room_planes,
  yaw_rotation,
)


def photo_texture(
  rng: np.random.Generator, pool: tuple[str, ...], tiles_per_metre=(0.25, 1.2)
) -> Texture:
  """A photograph of `pool` tiled over a surface; grey ones tinted between two random colours,
  colour ones tinted with probability 1/4 (so hue is not a property of the photograph)."""
  name = str(rng.choice(pool))
  tint = photos.is_grey(name) or rng.uniform() < 0.25
  dark, light = random_color(rng, value=(0.05, 0.45)), random_color(rng, value=(0.55, 1.0))
  return Texture(
    kind="photo",
    image=name,
    tint=bool(tint),
    color_a=dark,
    color_b=light,
    frequency=float(rng.uniform(*tiles_per_metre)),
    seed=int(rng.integers(0, 2**31)),
  )


@dataclasses.dataclass(frozen=True)
class VariedRoomConfig:
  """Ranges of `sample_varied_room` (metres, radians)."""

  half_size: tuple[float, float] = (1.8, 6.0)
  height: tuple[float, float] = (2.2, 4.5)
  partitions: tuple[int, int] = (0, 3)  # [low, high)
  num_objects: tuple[int, int] = (2, 12)  # [low, high)
  object_size: tuple[float, float] = (0.12, 0.8)
  clearance: float = 0.35  # minimum gap between an object and the camera path
  photo_probability: float = 0.7
  photos: tuple[str, ...] = photos.TRAIN_PHOTOS
  light_elevation: tuple[float, float] = (0.26, 1.48)
  ambient: tuple[float, float] = (0.15, 0.55)
  arc_probability: float = 0.35
  walk: cameras.WalkConfig = cameras.WalkConfig(
    yaw_rate_std=0.03, sideways_probability=0.3, pitch=(-0.6, 0.15)
  )
  arc: cameras.ArcConfig = cameras.ArcConfig(radius=(1.0, 2.6), height=(0.6, 2.2))


def _texture(rng: np.random.Generator, config: VariedRoomConfig) -> Texture:
  if rng.uniform() < config.photo_probability:
    return photo_texture(rng, config.photos)
  return random_texture(rng, kinds=_PATTERNS, saturation=(0.1, 0.9))


def _object(
  rng: np.random.Generator, xz: np.ndarray, size: float, height: float, config: VariedRoomConfig
) -> tuple[Sphere | Box, ...]:
  """One item at `xz [2]`: a box or sphere on the floor, floating, a stack or a column."""
  kind = rng.choice(["box", "sphere", "floating", "stack", "column"], p=[0.3, 0.2, 0.2, 0.15, 0.15])
  if kind == "sphere":
    return (
      Sphere(np.array([xz[0], size, xz[1]]), size, _texture(rng, config), random_rotation(rng)),
    )
  if kind == "floating":
    lift = rng.uniform(size + 0.3, max(size + 0.4, height - size - 0.2))
    if rng.uniform() < 0.5:
      return (Sphere(np.array([xz[0], lift, xz[1]]), size, _texture(rng, config), None),)
    half = size * rng.uniform(0.4, 1.0, 3)
    return (Box(np.array([xz[0], lift, xz[1]]), half, _texture(rng, config), random_rotation(rng)),)
  if kind == "column":
    half = np.array([size * rng.uniform(0.3, 0.6), 0.0, size * rng.uniform(0.3, 0.6)])
    half[1] = 0.5 * rng.uniform(1.0, height)
    yaw = yaw_rotation(rng.uniform(0, 2 * np.pi))
    return (Box(np.array([xz[0], half[1], xz[1]]), half, _texture(rng, config), yaw),)
  parts, base = [], 0.0
  for _ in range(int(rng.integers(2, 4)) if kind == "stack" else 1):
    half = size * rng.uniform(0.5, 1.2, 3)
    yaw = yaw_rotation(rng.uniform(0, 2 * np.pi))
    parts.append(Box(np.array([xz[0], base + half[1], xz[1]]), half, _texture(rng, config), yaw))
    base += 2 * half[1]
    size *= rng.uniform(0.6, 0.9)
  return tuple(parts)


def _footprint(parts: tuple[Sphere | Box, ...]) -> float:
  return max(
    float(p.radius) if isinstance(p, Sphere) else float(np.linalg.norm(p.half_size)) for p in parts
  )


def _light(rng: np.random.Generator, config: VariedRoomConfig) -> tuple[tuple, tuple]:
  """(direction towards the light, colour): any azimuth, a mild random tint."""
  elevation, azimuth = rng.uniform(*config.light_elevation), rng.uniform(0, 2 * np.pi)
  colour = colorsys.hsv_to_rgb(rng.uniform(), rng.uniform(0.0, 0.3), 1.0)
  return light_direction(elevation, azimuth), tuple(float(c) for c in colour)


def sample_varied_room(
  rng: np.random.Generator, frames: int, config: VariedRoomConfig = VariedRoomConfig()
) -> tuple[Scene, np.ndarray]:
  """A room of the varied family (see the module docstring) and its camera path.

  Returns:
    (scene, c2w [F, 4, 4] OpenCV); the camera stays inside the room and objects keep
    `config.clearance` from its path.
  """
  half_w, half_d = rng.uniform(*config.half_size, 2)
  height = rng.uniform(*config.height)
  planes = tuple(
    dataclasses.replace(plane, texture=_texture(rng, config))
    for plane in room_planes(rng, half_w, half_d, height)
  )
  if rng.uniform() < config.arc_probability:
    centre = np.array([rng.uniform(-0.3, 0.3) * half_w, 0.0, rng.uniform(-0.3, 0.3) * half_d])
    c2w = cameras.arc_path(rng, frames, centre, config.arc)
  else:
    start = np.array([rng.uniform(-0.5, 0.5) * half_w, 0.0, rng.uniform(-0.5, 0.5) * half_d])
    c2w = cameras.forward_walk(rng, frames, start, rng.uniform(0, 2 * np.pi), config.walk)
  margin = 0.3
  c2w[:, 0, 3] = np.clip(c2w[:, 0, 3], -half_w + margin, half_w - margin)
  c2w[:, 1, 3] = np.clip(c2w[:, 1, 3], margin, height - margin)
  c2w[:, 2, 3] = np.clip(c2w[:, 2, 3], -half_d + margin, half_d - margin)
  path_xz = c2w[:, [0, 2], 3]

  objects, placed = [], []
  # Partition walls: thin full-height boxes standing out from a wall, away from the path.
  for _ in range(int(rng.integers(*config.partitions))):
    along_x = rng.uniform() < 0.5
    length = rng.uniform(0.8, 2.5)
    side = rng.choice([-1.0, 1.0])
    if along_x:  # leaves the x = ±half_w wall, reaching into the room along x
      centre = np.array([side * (half_w - 0.5 * length), rng.uniform(-half_d, half_d) * 0.8])
      half = np.array([0.5 * length, 0.5 * height, 0.05])
    else:
      centre = np.array([rng.uniform(-half_w, half_w) * 0.8, side * (half_d - 0.5 * length)])
      half = np.array([0.05, 0.5 * height, 0.5 * length])
    corners = np.abs(path_xz - centre) - half[[0, 2]]
    if np.min(np.max(corners, axis=-1)) < config.clearance:
      continue
    objects.append(Box(np.array([centre[0], half[1], centre[1]]), half, _texture(rng, config)))
  count = int(rng.integers(*config.num_objects))
  for _ in range(200):  # rejection sampling with bounded attempts
    if len(placed) >= count:
      break
    size = rng.uniform(*config.object_size)
    xz = rng.uniform([-half_w + size, -half_d + size], [half_w - size, half_d - size])
    parts = _object(rng, xz, size, height, config)
    extent = _footprint(parts)
    if np.min(np.linalg.norm(path_xz - xz, axis=-1)) < config.clearance + extent:
      continue
    if any(np.linalg.norm(xz - p) < extent + e for p, e in placed):
      continue
    placed.append((xz, extent))
    objects.extend(parts)
  direction, colour = _light(rng, config)
  scene = Scene(
    planes=planes,
    objects=tuple(objects),
    light_direction=direction,
    ambient=float(rng.uniform(*config.ambient)),
    light_color=colour,
  )
  return scene, c2w
