"""The held-out dynamic family (issue 24): Kubric-4D-layout scenes unlike the Kubric-like training
scenes (`scenes.sample_dynamic_scene`), never trained on and scored in every synthetic Kubric run.

Frozen like `courtyards`: this file, `photos.HELD_OUT_PHOTOS` and `FROZEN_SEED` define the set;
scene `index` is drawn from `default_rng([FROZEN_SEED, 13, index])` whatever the experiment's
seed. Change nothing here to move a score: a changed family is a new, unfrozen one.

| | training (`sample_dynamic_scene`) | this family |
|---|---|---|
| objects | 3-6 single spheres and boxes, 0.3-0.8 m | 3-5 composites of 2-3 parts moving rigidly: dumbbells, jacks, snowmen, arches, satellites |
| motion | straight slides folded at the arena walls, bounces off the floor, spin 0-3 rad/s | floating (lowest point 0.1-2 m up) along ellipses and figure-eights (0.6-1.6 rad/s), bobbing, tumbling 1.5-4 rad/s |
| textures | checker / stripes / gradient / noise | only the held-out photographs and flat colours |
| backdrop | floor + 4 axis-aligned walls 20 m out | floor + a turned polygon of 5-7 walls 15-19 m out |
| light | white, from above (elevation > 49 degrees), ambient 0.3-0.45 | a low sun (11-32 degrees) tinted warm or cool, ambient 0.18-0.3 |
| cameras | one ring 7-10 m out, elevation 14-34 degrees, all aimed at one point, azimuth drift up to 0.15 rad, 35 mm | 5-12 m out, elevation 7-54 degrees drifting up to 11 either way, each aimed up to 1.2 m off the middle, azimuth drift 0.25-0.6 rad, dolly up to 10 %, 28-45 mm lenses |

Motion is analytic (`OrbitScene.poses` is a pure function of time) and cameras are re-drawn
(bounded) until every one keeps its distance from every object at every frame. The written scenes
carry that truth as Kubric does (`generate.render_kubric_views`): each composite is one instance,
with its segmentation and its pose at every frame; adding them changed no drawn byte.
"""

from __future__ import annotations

import colorsys
import dataclasses
import os
import pathlib

import numpy as np

from tokengs_jax.data import kubric
from tokengs_jax.data.synthetic import cameras, photos
from tokengs_jax.data.synthetic.generate import _run_jobs, render_kubric_views, write_kubric_scene
from tokengs_jax.data.synthetic.raytrace import Box, Plane, Scene, Sphere, Texture
from tokengs_jax.data.synthetic.scenes import (
  axis_angle,
  light_direction,
  random_color,
  random_rotation,
)
from tokengs_jax.data.synthetic.varied import photo_texture

FROZEN_SEED = 20261207
_STREAM = 13  # rng stream of this family: disjoint from the rooms' (0, 1) and the static sets'
SHAPES = ("dumbbell", "jack", "snowman", "arch", "satellite")


@dataclasses.dataclass(frozen=True)
class KubricOodConfig:
  """Ranges of the family (metres, radians, seconds) and the writer's options."""

  num_objects: tuple[int, int] = (3, 6)  # [low, high)
  object_scale: tuple[float, float] = (0.5, 0.9)  # a composite's characteristic size
  photo_probability: float = 0.75
  path_radius: tuple[float, float] = (0.5, 1.6)  # semi-axes of an object's path
  path_centre: float = 0.6  # path centres within [-path_centre, path_centre]^2
  path_speed: tuple[float, float] = (0.6, 1.6)  # rad/s along the path
  bob: tuple[float, float] = (0.0, 0.4)  # vertical oscillation amplitude
  lift: tuple[float, float] = (0.1, 1.2)  # clearance of the lowest point above the floor
  tumble: tuple[float, float] = (1.5, 4.0)  # rad/s
  walls: tuple[int, int] = (5, 8)  # [low, high)
  apothem: tuple[float, float] = (15.0, 19.0)
  sun_elevation: tuple[float, float] = (0.2, 0.55)
  ambient: tuple[float, float] = (0.18, 0.3)
  camera_radius: tuple[float, float] = (5.0, 12.0)
  camera_elevation: tuple[float, float] = (0.12, 0.95)
  azimuth_drift: tuple[float, float] = (0.25, 0.6)  # over the sequence, either way
  elevation_drift: float = 0.2  # up to this much over the sequence, either way
  dolly: float = 0.1  # the distance changes by up to this fraction over the sequence
  look_offset: float = 1.2  # the point looked at is up to this far off the middle (x, z)
  look_height: tuple[float, float] = (0.3, 1.8)
  camera_clearance: float = 0.6  # gap kept between a camera and any object's bounding sphere
  focal_length: tuple[float, float] = (28.0, 45.0)  # per camera, millimetres
  sensor_width: float = 32.0
  frame_rate: float = 12.0
  supersample: int = 2


def _texture(rng: np.random.Generator, config: KubricOodConfig, tiles=(0.6, 2.0)) -> Texture:
  if rng.uniform() < config.photo_probability:
    return photo_texture(rng, photos.HELD_OUT_PHOTOS, tiles_per_metre=tiles)
  return Texture(kind="solid", color_a=random_color(rng, saturation=(0.3, 0.9)))


def _composite(rng: np.random.Generator, config: KubricOodConfig) -> tuple[Sphere | Box, ...]:
  """One composite object in its own frame (parts around the origin, which it turns about)."""
  shape = SHAPES[int(rng.integers(len(SHAPES)))]
  size = rng.uniform(*config.object_scale)
  main, accent = _texture(rng, config), _texture(rng, config)
  eye = np.eye(3)
  if shape == "dumbbell":  # a bar with a ball at each end
    radius = size * rng.uniform(0.4, 0.6)
    bar = Box(np.zeros(3), np.array([size, 0.15 * size, 0.15 * size]), accent, eye)
    balls = [Sphere(np.array([s * size, 0.0, 0.0]), radius, main, eye) for s in (-1.0, 1.0)]
    return (bar, *balls)
  if shape == "jack":  # three orthogonal bars
    thin = size * rng.uniform(0.12, 0.22)
    return tuple(
      Box(np.zeros(3), np.where(np.arange(3) == axis, size, thin), (main, accent)[axis % 2], eye)
      for axis in range(3)
    )
  if shape == "snowman":  # 2-3 balls stacked along the local y axis
    radii = size * np.array([0.7, 0.5, 0.35])[: int(rng.integers(2, 4))]
    heights = np.concatenate([[0.0], np.cumsum(1.6 * radii[:-1])])
    heights -= heights.mean()
    return tuple(
      Sphere(np.array([0.0, h, 0.0]), r, (main, accent)[k % 2], eye)
      for k, (h, r) in enumerate(zip(heights, radii))
    )
  if shape == "arch":  # two posts and a lintel
    post = np.array([0.15, 0.7, 0.15]) * size
    lintel = np.array([0.9, 0.15, 0.2]) * size
    posts = [Box(np.array([s * 0.75 * size, -0.15 * size, 0.0]), post, main, eye) for s in (-1, 1)]
    return (*posts, Box(np.array([0.0, 0.7 * size, 0.0]), lintel, accent, eye))
  # satellite: a body with a flat panel on each side
  body = Box(np.zeros(3), size * rng.uniform(0.3, 0.45, 3), main, eye)
  panel = np.array([0.5, 0.03, 0.3]) * size
  wings = [Box(np.array([s * 0.85 * size, 0.0, 0.0]), panel, accent, eye) for s in (-1, 1)]
  return (body, *wings)


def bounding_radius(parts: tuple[Sphere | Box, ...]) -> float:
  """Radius about the object's origin of a sphere holding every part, in any pose."""
  return max(
    float(np.linalg.norm(p.center))
    + (float(p.radius) if isinstance(p, Sphere) else float(np.linalg.norm(p.half_size)))
    for p in parts
  )


@dataclasses.dataclass(frozen=True, eq=False)
class OrbitScene:
  """A static backdrop and K composite objects on analytic paths.

  Object k at time s (seconds), with angle a = speed_k s + phase_k: its origin is at
  centre_k + yaw_k (axes_k[0] sin(a + shift_k), axes_k[1] sin(lobes_k a)) on the floor (lobes 1,
  shift pi/2: an ellipse; lobes 2, shift 0: a figure-eight) at height height_k + bob_k sin(2 a),
  and it is turned by tumble_k s about tumble_axis_k from `orientation_k`.
  """

  backdrop: tuple[Plane, ...]
  parts: tuple[tuple[Sphere | Box, ...], ...]  # [K] each object's parts in its own frame
  centre: np.ndarray  # [K, 2] path centres (x, z)
  axes: np.ndarray  # [K, 2] path semi-axes
  yaw: np.ndarray  # [K] path turn about +y
  lobes: np.ndarray  # [K] 1 or 2
  shift: np.ndarray  # [K]
  speed: np.ndarray  # [K] rad/s
  phase: np.ndarray  # [K]
  height: np.ndarray  # [K] of the origin
  bob: np.ndarray  # [K]
  tumble_axis: np.ndarray  # [K, 3] unit
  tumble: np.ndarray  # [K] rad/s
  orientation: np.ndarray  # [K, 3, 3] at time 0
  light_direction: tuple[float, float, float]
  light_color: tuple[float, float, float]
  ambient: float

  def poses(self, time: float) -> tuple[np.ndarray, np.ndarray]:
    """(rotations [K, 3, 3] object-to-world, origins [K, 3]) at `time` seconds."""
    angle = self.speed * time + self.phase
    local = np.stack(
      [self.axes[:, 0] * np.sin(angle + self.shift), self.axes[:, 1] * np.sin(self.lobes * angle)],
      -1,
    )
    c, s = np.cos(self.yaw), np.sin(self.yaw)
    x = self.centre[:, 0] + c * local[:, 0] + s * local[:, 1]
    z = self.centre[:, 1] - s * local[:, 0] + c * local[:, 1]
    origins = np.stack([x, self.height + self.bob * np.sin(2.0 * angle), z], -1)
    rotations = np.stack(
      [
        axis_angle(axis, rate * time) @ start
        for axis, rate, start in zip(self.tumble_axis, self.tumble, self.orientation)
      ]
    )
    return rotations, origins

  def at(self, time: float) -> Scene:
    """The static `Scene` at `time` seconds: every part carried by its object's pose, each part
    of object k in instance k."""
    rotations, origins = self.poses(time)
    moved = [
      dataclasses.replace(
        part, center=origin + rotation @ part.center, rotation=rotation @ part.rotation
      )
      for parts, rotation, origin in zip(self.parts, rotations, origins)
      for part in parts
    ]
    return Scene(
      planes=self.backdrop,
      objects=tuple(moved),
      light_direction=self.light_direction,
      ambient=self.ambient,
      light_color=self.light_color,
      instances=tuple(k for k, parts in enumerate(self.parts) for _ in parts),
    )


def _backdrop(rng: np.random.Generator, config: KubricOodConfig) -> tuple[Plane, ...]:
  """The floor and a turned polygon of walls around x = z = 0 (normals inward, no ceiling)."""
  x, y, _ = np.eye(3)
  planes = [Plane(np.zeros(3), y, x, _texture(rng, config, tiles=(0.15, 0.7)))]
  count, apothem = int(rng.integers(*config.walls)), rng.uniform(*config.apothem)
  turn = rng.uniform(0, 2 * np.pi)
  for k in range(count):
    azimuth = turn + 2 * np.pi * k / count
    outward = np.array([np.sin(azimuth), 0.0, np.cos(azimuth)])
    texture = _texture(rng, config, tiles=(0.15, 0.7))
    planes.append(Plane(apothem * outward, -outward, np.cross(y, outward), texture))
  return tuple(planes)


def _sun(rng: np.random.Generator, config: KubricOodConfig) -> tuple[tuple, tuple]:
  """(direction towards a low sun, its colour: warm or cool, clearly tinted)."""
  elevation, azimuth = rng.uniform(*config.sun_elevation), rng.uniform(0, 2 * np.pi)
  hue = rng.uniform(0.02, 0.12) if rng.uniform() < 0.5 else rng.uniform(0.55, 0.65)
  colour = colorsys.hsv_to_rgb(hue, rng.uniform(0.25, 0.5), 1.0)
  return light_direction(elevation, azimuth), tuple(float(c) for c in colour)


def sample_orbit_scene(
  rng: np.random.Generator, config: KubricOodConfig = KubricOodConfig()
) -> OrbitScene:
  """A scene of the family (module docstring); cameras are drawn by `orbit_rig`."""
  backdrop = _backdrop(rng, config)
  count = int(rng.integers(*config.num_objects))
  parts = tuple(_composite(rng, config) for _ in range(count))
  reach = np.array([bounding_radius(p) for p in parts])
  bob = rng.uniform(*config.bob, count)
  axes = rng.normal(size=(count, 3))
  figure_eight = rng.uniform(size=count) < 0.5
  direction, colour = _sun(rng, config)
  return OrbitScene(
    backdrop=backdrop,
    parts=parts,
    centre=rng.uniform(-config.path_centre, config.path_centre, (count, 2)),
    axes=rng.uniform(*config.path_radius, (count, 2)),
    yaw=rng.uniform(0, 2 * np.pi, count),
    lobes=np.where(figure_eight, 2.0, 1.0),
    shift=np.where(figure_eight, 0.0, 0.5 * np.pi),
    speed=rng.choice([-1.0, 1.0], count) * rng.uniform(*config.path_speed, count),
    phase=rng.uniform(0, 2 * np.pi, count),
    height=reach + bob + rng.uniform(*config.lift, count),
    bob=bob,
    tumble_axis=axes / np.linalg.norm(axes, axis=-1, keepdims=True),
    tumble=rng.choice([-1.0, 1.0], count) * rng.uniform(*config.tumble, count),
    orientation=np.stack([random_rotation(rng) for _ in range(count)]),
    light_direction=direction,
    light_color=colour,
    ambient=float(rng.uniform(*config.ambient)),
  )


def _camera_path(rng: np.random.Generator, frames: int, azimuth: float, config: KubricOodConfig):
  """One camera drifting in azimuth, elevation and distance while it looks at a point off the
  middle.  -> c2w [F, 4, 4] (OpenCV)."""
  ramp = np.linspace(0.0, 1.0, frames)
  sweep = rng.choice([-1.0, 1.0]) * rng.uniform(*config.azimuth_drift)
  start = rng.uniform(*config.camera_elevation)
  end = start + rng.uniform(-1, 1) * config.elevation_drift
  elevation = np.clip(np.linspace(start, end, frames), 0.05, 1.2)
  distance = rng.uniform(*config.camera_radius) * (1.0 + rng.uniform(-1, 1) * config.dolly * ramp)
  look = np.array(
    [
      rng.uniform(-1, 1) * config.look_offset,
      rng.uniform(*config.look_height),
      rng.uniform(-1, 1) * config.look_offset,
    ]
  )
  yaw = azimuth + sweep * ramp
  direction = np.stack(
    [np.sin(yaw) * np.cos(elevation), np.sin(elevation), np.cos(yaw) * np.cos(elevation)], -1
  )
  positions = np.array([0.0, look[1], 0.0]) + distance[:, None] * direction
  return cameras.look_at(positions, np.broadcast_to(look, positions.shape))


def orbit_rig(
  rng: np.random.Generator,
  scene: OrbitScene,
  frames: int,
  num_cameras: int,
  config: KubricOodConfig = KubricOodConfig(),
) -> tuple[np.ndarray, np.ndarray]:
  """The scene's cameras, spread around it with wide jitter (`_camera_path`), each re-drawn
  until it keeps `camera_clearance` from every object's bounding sphere at every frame.

  Returns:
    (c2w [C, F, 4, 4] OpenCV, focal lengths [C] millimetres).

  Raises:
    RuntimeError: a camera found no clear path in 100 draws (ranges that leave no room).
  """
  times = np.arange(frames) / config.frame_rate
  origins = np.stack([scene.poses(t)[1] for t in times], 1)  # [K, F, 3]
  keep_out = np.array([bounding_radius(p) for p in scene.parts]) + config.camera_clearance
  spacing = 2 * np.pi / num_cameras
  start = rng.uniform(0, 2 * np.pi)
  rig = []
  for camera in range(num_cameras):
    for _ in range(100):
      azimuth = start + spacing * (camera + rng.uniform(-0.45, 0.45))
      c2w = _camera_path(rng, frames, azimuth, config)
      gaps = np.linalg.norm(origins - c2w[None, :, :3, 3], axis=-1)  # [K, F]
      if (gaps > keep_out[:, None]).all():
        break
    else:
      raise RuntimeError(f"camera {camera}: no path clear of the objects in 100 draws")
    rig.append(c2w)
  return np.stack(rig), rng.uniform(*config.focal_length, num_cameras)


def sample_scene(
  index: int, frames: int, num_cameras: int, config: KubricOodConfig = KubricOodConfig()
) -> tuple[OrbitScene, np.ndarray, np.ndarray]:
  """Scene `index` of the frozen set: (scene, c2w [C, F, 4, 4], focal lengths [C] mm). The
  objects depend on `index` only; the rig also on the clip length and camera count."""
  rng = np.random.default_rng([FROZEN_SEED, _STREAM, index])
  scene = sample_orbit_scene(rng, config)
  return (scene, *orbit_rig(rng, scene, frames, num_cameras, config))


def render_kubric_ood_scene(
  index: int,
  height: int,
  width: int,
  frames: int,
  num_cameras: int,
  config: KubricOodConfig = KubricOodConfig(),
) -> dict:
  """Renders scene `index` from every camera at every frame.

  Returns:
    `images` uint8 [C, F, H, W, 3], `depths` float32 [C, F, H, W] (distance along each
    pixel-centre ray, Kubric's convention; 0 where nothing was hit), `segmentations` uint8
    [C, F, H, W] (composite k + 1 per pixel, 0 the backdrop), `c2w` [C, F, 4, 4] (OpenCV),
    `intrinsics` [C, 4] (pixels, as the Kubric reader derives them) and `metadata` [C] (each
    camera's `metadata.json`, with each composite's poses `OrbitScene.poses`), as
    `generate.render_kubric_like_scene`.
  """
  scene, c2w, focal = sample_scene(index, frames, num_cameras, config)
  intrinsics = np.stack(
    [kubric.intrinsics_from_metadata(f, config.sensor_width, height, width) for f in focal]
  )
  images, depths, segmentations, metadata = render_kubric_views(
    scene.at,
    scene.poses,
    c2w,
    intrinsics,
    focal,
    config.sensor_width,
    config.frame_rate,
    height,
    width,
    config.supersample,
  )
  return {
    "images": images,
    "depths": depths,
    "segmentations": segmentations,
    "c2w": c2w,
    "intrinsics": intrinsics,
    "metadata": metadata,
  }


def _write_scene(
  directory: str, index: int, height: int, width: int, frames: int, num_cameras: int, config
) -> None:
  write_kubric_scene(
    directory, render_kubric_ood_scene(index, height, width, frames, num_cameras, config)
  )


def generate_kubric_ood(
  root: str | os.PathLike,
  num_scenes: int,
  height: int = 64,
  width: int = 64,
  frames: int = 24,
  num_cameras: int = 9,
  *,
  subset: str = "ood_kubric",
  config: KubricOodConfig = KubricOodConfig(),
  workers: int = 1,
) -> list[pathlib.Path]:
  """Writes the first `num_scenes` scenes of the frozen set as
  `<root>/<subset>/scene_NNNNNN/output_{camera:03d}.tar` (the layout of
  `generate.generate_kubric_like`). Returns the scene directories."""
  directories = [pathlib.Path(root) / subset / f"scene_{index:06d}" for index in range(num_scenes)]
  jobs = [
    (str(d), index, height, width, frames, num_cameras, config)
    for index, d in enumerate(directories)
  ]
  _run_jobs(_write_scene, jobs, workers)
  return directories
