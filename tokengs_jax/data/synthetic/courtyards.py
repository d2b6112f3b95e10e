"""Courtyards: the frozen test family (issue 23). No training generator draws anything from it,
and no tuning decision may look at it before it is reported.

Frozen means: this file, `photos.HELD_OUT_PHOTOS` and `FROZEN_SEED` define the set, and the set
does not follow the experiment's `--seed` (the same 24 scenes in every run). It was written before
any lever of the varied training family was tried; `docs/generalisation.md` records when it was
first scored. Change nothing here to move a score: a changed family is a new, unfrozen one.

What differs from every training family (rooms, varied rooms) and from the galleries:

| | courtyards |
|---|---|
| enclosure | open to the sky (no ceiling; rays that miss see a sky colour, with no depth), 4-6 facades 4-9 m high |
| textures | only the held-out photographs (`photos.HELD_OUT_PHOTOS`) and flat colours |
| objects | crates (turned, some stacked), bollards, balls, benches, arches (two posts and a lintel) |
| light | a low-to-mid sun (15-65 degrees), warm, ambient 0.25-0.5 |
| camera | a sideways track: travel across the view direction while the view pans (`track_and_pan`) |
"""

from __future__ import annotations

import dataclasses

import numpy as np

from tokengs_jax.data.synthetic import cameras, photos
from tokengs_jax.data.synthetic.raytrace import Box, Plane, Scene, Sphere, Texture
from tokengs_jax.data.synthetic.scenes import light_direction, random_color, yaw_rotation
from tokengs_jax.data.synthetic.varied import photo_texture

FROZEN_SEED = 20261125


@dataclasses.dataclass(frozen=True)
class CourtyardConfig:
  """Ranges of `sample_courtyard` (metres, radians)."""

  facades: tuple[int, int] = (4, 7)  # [low, high)
  apothem: tuple[float, float] = (4.0, 7.0)
  height: tuple[float, float] = (4.0, 9.0)
  num_items: tuple[int, int] = (4, 10)  # [low, high)
  clearance: float = 0.5
  photo_probability: float = 0.8
  sun_elevation: tuple[float, float] = (0.26, 1.13)
  ambient: tuple[float, float] = (0.25, 0.5)
  step: tuple[float, float] = (0.05, 0.1)  # sideways travel per frame
  pan: tuple[float, float] = (0.1, 0.5)  # total pan of the view over the path (either way)
  camera_height: tuple[float, float] = (1.0, 2.4)
  pitch: tuple[float, float] = (-0.35, 0.1)


def _texture(rng: np.random.Generator, config: CourtyardConfig) -> Texture:
  if rng.uniform() < config.photo_probability:
    return photo_texture(rng, photos.HELD_OUT_PHOTOS, tiles_per_metre=(0.15, 0.7))
  return Texture(kind="solid", color_a=random_color(rng, saturation=(0.1, 0.7)))


def track_and_pan(
  rng: np.random.Generator, frames: int, start: np.ndarray, config: CourtyardConfig
) -> np.ndarray:
  """A camera travelling sideways (perpendicular to its initial view) while its view pans
  steadily: a tracking shot, unlike a forward walk (travel along the view) or an orbit (view
  fixed on a point).  start: [3] (x, z used) -> c2w [F, 4, 4] (OpenCV)."""
  view_yaw = rng.uniform(0, 2 * np.pi)
  travel_yaw = view_yaw + rng.choice([-0.5, 0.5]) * np.pi + rng.uniform(-0.25, 0.25)
  travel = np.array([np.sin(travel_yaw), 0.0, np.cos(travel_yaw)])
  steps = rng.uniform(*config.step) * np.arange(frames)
  positions = (
    np.array([start[0], rng.uniform(*config.camera_height), start[2]]) + steps[:, None] * travel
  )
  pan = rng.choice([-1.0, 1.0]) * rng.uniform(*config.pan) * np.linspace(0.0, 1.0, frames)
  pitch = np.full(frames, rng.uniform(*config.pitch))
  yaw = view_yaw + pan
  forward = np.stack([np.sin(yaw) * np.cos(pitch), np.sin(pitch), np.cos(yaw) * np.cos(pitch)], -1)
  return cameras.pose_matrix(cameras.look_rotation(forward), positions)


def _item(
  rng: np.random.Generator, xz: np.ndarray, config: CourtyardConfig
) -> tuple[tuple[Sphere | Box, ...], float]:
  """A crate (or crate stack), bollard, ball, bench or arch at `xz [2]`.  -> (parts, footprint)."""
  kind = rng.choice(["crates", "bollard", "ball", "bench", "arch"])
  yaw = yaw_rotation(rng.uniform(0, 2 * np.pi))
  texture = _texture(rng, config)
  if kind == "ball":
    radius = rng.uniform(0.2, 0.7)
    return (Sphere(np.array([xz[0], radius, xz[1]]), radius, texture, None),), radius
  if kind == "bollard":
    half = np.array([0.12, rng.uniform(0.4, 0.7), 0.12])
    return (Box(np.array([xz[0], half[1], xz[1]]), half, texture, yaw),), 0.2
  if kind == "bench":
    half = np.array([rng.uniform(0.6, 1.2), rng.uniform(0.2, 0.3), rng.uniform(0.2, 0.35)])
    return (Box(np.array([xz[0], half[1], xz[1]]), half, texture, yaw),), float(half[0])
  if kind == "arch":
    span, post, rise = rng.uniform(0.6, 1.2), rng.uniform(0.12, 0.25), rng.uniform(1.6, 2.6)
    parts = []
    for side in (-1.0, 1.0):
      offset = yaw @ np.array([side * (span + post), 0.0, 0.0])
      parts.append(
        Box(
          np.array([xz[0] + offset[0], 0.5 * rise, xz[1] + offset[2]]),
          np.array([post, 0.5 * rise, post]),
          texture,
          yaw,
        )
      )
    lintel = np.array([span + 2 * post, rng.uniform(0.12, 0.3), post])
    parts.append(Box(np.array([xz[0], rise + lintel[1], xz[1]]), lintel, texture, yaw))
    return tuple(parts), float(span + 2 * post)
  parts, base = [], 0.0
  for _ in range(int(rng.integers(1, 4))):
    half = np.full(3, rng.uniform(0.2, 0.5))
    turn = yaw_rotation(rng.uniform(0, 2 * np.pi))
    parts.append(Box(np.array([xz[0], base + half[1], xz[1]]), half, _texture(rng, config), turn))
    base += 2 * half[1]
  return tuple(parts), float(np.sqrt(2.0) * parts[0].half_size[0])


def _facades(rng: np.random.Generator, apothem: float, config: CourtyardConfig) -> tuple[Box, ...]:
  """The walls of a regular polygon around x = z = 0 at a random turn, each a finite slab of its
  own height (so the sky shows above them; an infinite plane would close the courtyard)."""
  count = int(rng.integers(*config.facades))
  turn = rng.uniform(0, 2 * np.pi)
  up = np.array([0.0, 1.0, 0.0])
  walls = []
  for k in range(count):
    azimuth = turn + 2 * np.pi * k / count
    outward = np.array([np.sin(azimuth), 0.0, np.cos(azimuth)])
    along = np.cross(up, outward)
    height = rng.uniform(*config.height)
    half = np.array([apothem * np.tan(np.pi / count) + 0.3, 0.5 * height, 0.15])
    centre = (apothem + half[2]) * outward + half[1] * up
    walls.append(Box(centre, half, _texture(rng, config), np.stack([along, up, outward], -1)))
  return tuple(walls)


def sample_courtyard(
  rng: np.random.Generator, frames: int, config: CourtyardConfig = CourtyardConfig()
) -> tuple[Scene, np.ndarray]:
  """An open courtyard with items and a sideways tracking camera (see the module docstring).

  Returns:
    (scene, c2w [F, 4, 4] OpenCV); items keep `config.clearance` from the camera path.
  """
  apothem = rng.uniform(*config.apothem)
  ground = Plane(np.zeros(3), np.array([0.0, 1.0, 0.0]), np.eye(3)[0], _texture(rng, config))
  facades = _facades(rng, apothem, config)
  inside = apothem - 1.0
  start = rng.uniform(-0.5, 0.5, 2) * inside
  c2w = track_and_pan(rng, frames, np.array([start[0], 0.0, start[1]]), config)
  radius = np.linalg.norm(c2w[:, [0, 2], 3], axis=-1, keepdims=True)
  c2w[:, [0, 2], 3] *= np.minimum(1.0, (apothem - 0.6) / np.maximum(radius, 1e-9))
  path_xz = c2w[:, [0, 2], 3]
  objects, placed = [], []
  count = int(rng.integers(*config.num_items))
  for _ in range(200):  # rejection sampling with bounded attempts
    if len(placed) >= count:
      break
    xz = rng.uniform(-inside, inside, 2)
    if np.linalg.norm(xz) > inside:
      continue
    parts, extent = _item(rng, xz, config)
    if np.min(np.linalg.norm(path_xz - xz, axis=-1)) < config.clearance + extent:
      continue
    if any(np.linalg.norm(xz - p) < extent + e + 0.2 for p, e in placed):
      continue
    placed.append((xz, extent))
    objects.extend(parts)
  elevation, azimuth = rng.uniform(*config.sun_elevation), rng.uniform(0, 2 * np.pi)
  warmth = rng.uniform(0.0, 1.0)
  sky = np.array(random_color(rng, saturation=(0.1, 0.6), value=(0.6, 1.0)))
  scene = Scene(
    planes=(ground,),
    objects=facades + tuple(objects),
    light_direction=light_direction(elevation, azimuth),
    ambient=float(rng.uniform(*config.ambient)),
    light_color=(1.0, 1.0 - 0.1 * warmth, 1.0 - 0.3 * warmth),
    background=tuple(float(c) for c in sky),
  )
  return scene, c2w
