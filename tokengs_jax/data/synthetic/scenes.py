"""Random scene layouts: RE10K-like rooms with a walking camera, Kubric-like dynamic scenes, and
galleries (a held-out family for out-of-distribution tests: nothing is trained on it).

World frame: +y up, floor at y = 0. All randomness comes from the `np.random.Generator` passed in,
so a scene is a pure function of its seed.
"""

from __future__ import annotations

import colorsys
import dataclasses

import numpy as np

from tokengs_jax.data.synthetic import cameras
from tokengs_jax.data.synthetic.raytrace import Box, Plane, Scene, Sphere, Texture

_PATTERNS = ("checker", "stripes", "gradient", "noise")
# The gallery family's textures share no kind with the rooms' `_PATTERNS`.
_GALLERY_PATTERNS = ("solid", "rings", "dots", "bricks")


def random_color(rng: np.random.Generator, saturation=(0.2, 0.8), value=(0.3, 0.95)) -> tuple:
  return colorsys.hsv_to_rgb(rng.uniform(), rng.uniform(*saturation), rng.uniform(*value))


def random_texture(
  rng: np.random.Generator, frequency=(0.5, 3.0), kinds=_PATTERNS, saturation=(0.2, 0.8)
) -> Texture:
  """A random pattern between two random colours."""
  return Texture(
    kind=str(rng.choice(kinds)),
    color_a=random_color(rng, saturation),
    color_b=random_color(rng, saturation),
    frequency=float(rng.uniform(*frequency)),
    axis=int(rng.integers(0, 3)),
    seed=int(rng.integers(0, 2**31)),
  )


def light_direction(elevation: float, azimuth: float) -> tuple[float, float, float]:
  """Unit vector towards a directional light at `elevation` above the floor and `azimuth` about
  +y (radians; 0 along +z)."""
  return (
    float(np.cos(elevation) * np.sin(azimuth)),
    float(np.sin(elevation)),
    float(np.cos(elevation) * np.cos(azimuth)),
  )


def random_rotation(rng: np.random.Generator) -> np.ndarray:
  """Uniform random rotation (QR of a Gaussian matrix, sign-fixed).  -> [3, 3]."""
  q, r = np.linalg.qr(rng.normal(size=(3, 3)))
  q = q * np.sign(np.diag(r))
  return q if np.linalg.det(q) > 0 else -q


def yaw_rotation(angle: float) -> np.ndarray:
  c, s = np.cos(angle), np.sin(angle)
  return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
  """Rodrigues' formula.  axis: [3] unit -> [3, 3]."""
  k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
  return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def room_planes(
  rng: np.random.Generator, half_width: float, half_depth: float, height: float
) -> tuple[Plane, ...]:
  """Floor, ceiling and four walls of an axis-aligned room centred on x = z = 0 (normals inward)."""
  x, y, z = np.eye(3)
  specs = [  # (point, inward normal, tangent)
    (np.zeros(3), y, x),
    (height * y, -y, x),
    (-half_width * x, x, z),
    (half_width * x, -x, z),
    (-half_depth * z, z, x),
    (half_depth * z, -z, x),
  ]
  return tuple(
    Plane(point=p, normal=n, tangent=t, texture=random_texture(rng)) for p, n, t in specs
  )


def _random_object(
  rng: np.random.Generator, center_xz: np.ndarray, size: float, texture: Texture
) -> Sphere | Box:
  """A sphere or box of characteristic size `size`, resting on the floor at `center_xz [2]`."""
  if rng.uniform() < 0.5:
    center = np.array([center_xz[0], size, center_xz[1]])
    return Sphere(center=center, radius=size, texture=texture, rotation=random_rotation(rng))
  half = size * rng.uniform(0.5, 1.2, 3)
  center = np.array([center_xz[0], half[1], center_xz[1]])
  return Box(
    center=center, half_size=half, texture=texture, rotation=yaw_rotation(rng.uniform(0, 2 * np.pi))
  )


@dataclasses.dataclass(frozen=True)
class RoomConfig:
  """Ranges for `sample_room_scene` (metres)."""

  half_width: tuple[float, float] = (2.5, 4.5)
  half_depth: tuple[float, float] = (3.5, 6.0)
  height: tuple[float, float] = (2.5, 3.5)
  num_objects: tuple[int, int] = (3, 9)  # [low, high)
  object_size: tuple[float, float] = (0.2, 0.6)
  clearance: float = 0.5  # minimum gap between an object and the camera path
  walk: cameras.WalkConfig = cameras.WalkConfig()


def sample_room_scene(
  rng: np.random.Generator, frames: int, config: RoomConfig = RoomConfig()
) -> tuple[Scene, np.ndarray]:
  """A textured room with objects and an RE10K-like walk through it.

  Returns:
    (scene, c2w [F, 4, 4] OpenCV). The walk starts near one end wall heading into the room; objects
    keep `clearance` from the path so the camera never passes through one.
  """
  half_w, half_d = rng.uniform(*config.half_width), rng.uniform(*config.half_depth)
  height = rng.uniform(*config.height)
  planes = room_planes(rng, half_w, half_d, height)
  end = rng.choice([-1.0, 1.0])  # which end wall the walk starts from
  start = np.array([rng.uniform(-0.4, 0.4) * half_w, 0.0, end * (half_d - 1.0)])
  heading = (0.0 if end < 0 else np.pi) + rng.uniform(-0.3, 0.3)
  c2w = cameras.forward_walk(rng, frames, start, heading, config.walk)
  # Keep the camera inside the room even when the heading drifts strongly.
  margin = 0.3
  c2w[:, 0, 3] = np.clip(c2w[:, 0, 3], -half_w + margin, half_w - margin)
  c2w[:, 2, 3] = np.clip(c2w[:, 2, 3], -half_d + margin, half_d - margin)

  path_xz = c2w[:, [0, 2], 3]
  objects = []
  num_objects = rng.integers(*config.num_objects)
  for _ in range(200):  # rejection sampling of object positions; bounded attempts
    if len(objects) >= num_objects:
      break
    size = rng.uniform(*config.object_size)
    center = rng.uniform(
      [-half_w + 2 * size, -half_d + 2 * size], [half_w - 2 * size, half_d - 2 * size]
    )
    if np.min(np.linalg.norm(path_xz - center, axis=-1)) < config.clearance + 1.5 * size:
      continue
    if any(
      np.linalg.norm(np.asarray(o.center)[[0, 2]] - center) < 2.5 * size + _extent(o)
      for o in objects
    ):
      continue
    objects.append(_random_object(rng, center, size, random_texture(rng)))
  light = np.array([rng.uniform(-0.5, 0.5), 1.0, rng.uniform(-0.5, 0.5)])
  scene = Scene(
    planes=planes,
    objects=tuple(objects),
    light_direction=tuple(light),
    ambient=float(rng.uniform(0.3, 0.5)),
  )
  return scene, c2w


def _extent(obj: Sphere | Box) -> float:
  return (
    float(obj.radius) if isinstance(obj, Sphere) else float(np.linalg.norm(obj.half_size[[0, 2]]))
  )


@dataclasses.dataclass(frozen=True)
class DynamicConfig:
  """Ranges for `sample_dynamic_scene` (metres, seconds)."""

  arena: float = 3.0  # objects start within [-arena, arena]^2 on the floor
  room: float = 20.0  # half size of the enclosing backdrop (floor + walls, no ceiling)
  num_objects: tuple[int, int] = (3, 7)
  object_size: tuple[float, float] = (0.3, 0.8)
  speed: tuple[float, float] = (0.5, 2.0)  # floor speed (m/s)
  bounce_height: tuple[float, float] = (0.0, 1.5)
  spin: tuple[float, float] = (0.0, 3.0)  # angular speed (rad/s)
  frame_rate: float = 12.0


@dataclasses.dataclass(frozen=True, eq=False)
class DynamicScene:
  """Static backdrop plus objects moving on analytic trajectories.

  Object k at time s (seconds): floor position p0 + v s (reflected at the arena bounds), lifted by
  a bouncing |sin| arc, and turned by `spin` about its spin axis.
  """

  backdrop: tuple[Plane, ...]
  objects: tuple[Sphere | Box, ...]  # poses at time 0
  velocity: np.ndarray  # [K, 2] floor velocity (x, z)
  bounce_height: np.ndarray  # [K]
  bounce_period: np.ndarray  # [K] seconds
  spin_axis: np.ndarray  # [K, 3]
  spin: np.ndarray  # [K] rad/s
  arena: float
  light_direction: tuple[float, float, float]
  ambient: float

  def at(self, time: float) -> Scene:
    """The static `Scene` at `time` seconds."""
    moved = []
    for k, obj in enumerate(self.objects):
      start = np.asarray(obj.center)
      xz = _reflect(start[[0, 2]] + self.velocity[k] * time, self.arena)
      lift = self.bounce_height[k] * np.abs(np.sin(np.pi * time / self.bounce_period[k]))
      center = np.array([xz[0], start[1] + lift, xz[1]])
      rotation = axis_angle(self.spin_axis[k], self.spin[k] * time) @ np.asarray(obj.rotation)
      moved.append(dataclasses.replace(obj, center=center, rotation=rotation))
    return Scene(
      planes=self.backdrop,
      objects=tuple(moved),
      light_direction=self.light_direction,
      ambient=self.ambient,
    )


def _reflect(x: np.ndarray, bound: float) -> np.ndarray:
  """Fold x into [-bound, bound] as a ball bouncing between walls would move."""
  period = 4.0 * bound
  y = np.mod(x + bound, period)
  return np.where(y <= 2 * bound, y, period - y) - bound


def sample_dynamic_scene(
  rng: np.random.Generator, config: DynamicConfig = DynamicConfig()
) -> DynamicScene:
  """A Kubric-like scene: a textured floor and far walls, several objects moving and spinning."""
  x, y, z = np.eye(3)
  half = config.room
  specs = [
    (np.zeros(3), y, x),
    (-half * x, x, z),
    (half * x, -x, z),
    (-half * z, z, x),
    (half * z, -z, x),
  ]
  backdrop = tuple(
    Plane(point=p, normal=n, tangent=t, texture=random_texture(rng, frequency=(0.3, 1.5)))
    for p, n, t in specs
  )
  count = int(rng.integers(*config.num_objects))
  objects = []
  for _ in range(count):
    size = rng.uniform(*config.object_size)
    center = rng.uniform(-config.arena, config.arena, 2)
    obj = _random_object(rng, center, size, random_texture(rng))
    # Boxes also get a full random orientation so their spin shows all faces.
    if isinstance(obj, Box):
      obj = dataclasses.replace(
        obj,
        rotation=random_rotation(rng),
        center=np.array([center[0], float(np.max(obj.half_size)) * 1.8, center[1]]),
      )
    objects.append(obj)
  angle = rng.uniform(0, 2 * np.pi, count)
  speed = rng.uniform(*config.speed, count)
  axes = rng.normal(size=(count, 3))
  return DynamicScene(
    backdrop=backdrop,
    objects=tuple(objects),
    velocity=np.stack([np.cos(angle), np.sin(angle)], -1) * speed[:, None],
    bounce_height=rng.uniform(*config.bounce_height, count),
    bounce_period=rng.uniform(0.5, 2.0, count),
    spin_axis=axes / np.linalg.norm(axes, axis=-1, keepdims=True),
    spin=rng.uniform(*config.spin, count),
    arena=config.arena,
    light_direction=(float(rng.uniform(-0.6, 0.6)), 1.0, float(rng.uniform(-0.6, 0.6))),
    ambient=float(rng.uniform(0.3, 0.45)),
  )


# ----------------------------------------------------------------------------------------------
# Galleries: the out-of-distribution family


@dataclasses.dataclass(frozen=True)
class GalleryConfig:
  """Ranges for `sample_gallery_scene` (metres, radians). Every choice differs from the rooms':

  room: a convex polygon of 5-8 walls at a random orientation (rooms: axis-aligned rectangles);
  textures: solid / rings / dots / bricks in more saturated colours (rooms: checker / stripes /
    gradient / noise);
  objects: pillars, tables, floating spheres, stacks of boxes (rooms: single boxes and spheres on
    the floor);
  light: low (20-50 degrees elevation) and tinted warm or cool (rooms: high, white);
  camera: an inward orbit around the room's middle (`cameras.arc_path`; rooms: a forward walk),
    with a wider range of fields of view (set in `generate.GalleryConfig`).
  """

  walls: tuple[int, int] = (5, 9)  # [low, high)
  apothem: tuple[float, float] = (3.2, 5.0)  # centre-to-wall distance
  height: tuple[float, float] = (2.2, 4.5)
  num_items: tuple[int, int] = (3, 8)
  clearance: float = 0.4  # minimum gap between an item and the camera path
  light_elevation: tuple[float, float] = (0.35, 0.9)
  ambient: tuple[float, float] = (0.2, 0.45)
  arc: cameras.ArcConfig = cameras.ArcConfig()


def polygon_room_planes(
  rng: np.random.Generator, walls: int, apothem: float, height: float, kinds: tuple[str, ...]
) -> tuple[Plane, ...]:
  """Floor, ceiling and `walls` walls of a regular polygon room around x = z = 0, turned by a
  random angle (normals inward). The room is convex, so the nearest plane hit from inside is the
  room's surface."""
  x, y, _ = np.eye(3)
  planes = [
    Plane(point=np.zeros(3), normal=y, tangent=x, texture=random_texture(rng, kinds=kinds)),
    Plane(point=height * y, normal=-y, tangent=x, texture=random_texture(rng, kinds=kinds)),
  ]
  turn = rng.uniform(0, 2 * np.pi)
  for k in range(walls):
    azimuth = turn + 2 * np.pi * k / walls
    outward = np.array([np.sin(azimuth), 0.0, np.cos(azimuth)])
    planes.append(
      Plane(
        point=apothem * outward,
        normal=-outward,
        tangent=np.cross(y, outward),
        texture=random_texture(rng, kinds=kinds, saturation=(0.4, 1.0)),
      )
    )
  return tuple(planes)


def _gallery_item(
  rng: np.random.Generator, centre_xz: np.ndarray, height: float, kinds: tuple[str, ...]
) -> tuple[tuple[Sphere | Box, ...], float]:
  """One item at `centre_xz [2]`: a pillar, a table, a floating sphere or a stack of boxes.

  Returns (its primitives, its footprint radius on the floor).
  """
  texture = random_texture(rng, kinds=kinds, saturation=(0.4, 1.0))
  yaw = yaw_rotation(rng.uniform(0, 2 * np.pi))
  kind = rng.integers(0, 4)
  if kind == 0:  # pillar, up to just below the ceiling
    half = np.array([rng.uniform(0.1, 0.25), 0.0, rng.uniform(0.1, 0.25)])
    half[1] = 0.5 * rng.uniform(1.2, height - 0.2)
    box = Box(np.array([centre_xz[0], half[1], centre_xz[1]]), half, texture, yaw)
    return (box,), float(np.hypot(half[0], half[2]))
  if kind == 1:  # table: a top on four legs
    top = np.array([rng.uniform(0.3, 0.6), 0.03, rng.uniform(0.25, 0.5)])
    legs_height = rng.uniform(0.5, 0.9)
    parts = [Box(np.array([centre_xz[0], legs_height + top[1], centre_xz[1]]), top, texture, yaw)]
    leg_texture = random_texture(rng, kinds=kinds)
    for sx, sz in ((-1, -1), (-1, 1), (1, -1), (1, 1)):
      offset = yaw @ np.array([sx * (top[0] - 0.05), 0.0, sz * (top[2] - 0.05)])
      centre = np.array([centre_xz[0] + offset[0], 0.5 * legs_height, centre_xz[1] + offset[2]])
      parts.append(Box(centre, np.array([0.03, 0.5 * legs_height, 0.03]), leg_texture, yaw))
    return tuple(parts), float(np.hypot(top[0], top[2]))
  if kind == 2:  # a sphere floating in the air
    radius = rng.uniform(0.15, 0.4)
    lift = rng.uniform(0.7, min(2.0, height - radius - 0.1))
    centre = np.array([centre_xz[0], lift, centre_xz[1]])
    return (Sphere(centre, radius, texture, random_rotation(rng)),), float(radius)
  # A stack of 2-3 boxes, each smaller and turned on the one below.
  parts, base, size = [], 0.0, rng.uniform(0.25, 0.45)
  for _ in range(int(rng.integers(2, 4))):
    half = size * rng.uniform(0.7, 1.0, 3)
    parts.append(
      Box(
        np.array([centre_xz[0], base + half[1], centre_xz[1]]),
        half,
        random_texture(rng, kinds=kinds, saturation=(0.4, 1.0)),
        yaw_rotation(rng.uniform(0, 2 * np.pi)),
      )
    )
    base += 2 * half[1]
    size *= 0.7
  return tuple(parts), float(np.linalg.norm(parts[0].half_size[[0, 2]]))


def sample_gallery_scene(
  rng: np.random.Generator, frames: int, config: GalleryConfig = GalleryConfig()
) -> tuple[Scene, np.ndarray]:
  """A polygonal gallery with items and an inward orbit around its middle (see `GalleryConfig`).

  Returns:
    (scene, c2w [F, 4, 4] OpenCV). Items keep `clearance` from the camera path.
  """
  walls = int(rng.integers(*config.walls))
  apothem, height = rng.uniform(*config.apothem), rng.uniform(*config.height)
  planes = polygon_room_planes(rng, walls, apothem, height, _GALLERY_PATTERNS)
  centre = np.array([rng.uniform(-0.3, 0.3), 0.0, rng.uniform(-0.3, 0.3)])
  c2w = cameras.arc_path(rng, frames, centre, config.arc)
  path_xz = c2w[:, [0, 2], 3]

  items, objects = [], []
  count = int(rng.integers(*config.num_items))
  # The room's inscribed circle (radius = apothem) minus a margin: items stay inside any polygon.
  inside = apothem - 0.7
  for _ in range(200):  # rejection sampling with bounded attempts
    if len(items) >= count:
      break
    position = rng.uniform(-inside, inside, 2)
    if np.linalg.norm(position) > inside:
      continue
    parts, extent = _gallery_item(rng, position, height, _GALLERY_PATTERNS)
    if np.min(np.linalg.norm(path_xz - position, axis=-1)) < config.clearance + extent:
      continue
    if any(np.linalg.norm(position - p) < extent + e + 0.2 for p, e in items):
      continue
    items.append((position, extent))
    objects.extend(parts)

  elevation, azimuth = rng.uniform(*config.light_elevation), rng.uniform(0, 2 * np.pi)
  warmth = rng.uniform(-1.0, 1.0)  # > 0 warm (reddish), < 0 cool (bluish)
  tint = (
    (1.0, 1.0 - 0.15 * abs(warmth), 1.0 - 0.35 * warmth)
    if warmth > 0
    else (1.0 + 0.3 * warmth, 1.0 + 0.15 * warmth, 1.0)
  )
  scene = Scene(
    planes=planes,
    objects=tuple(objects),
    light_direction=light_direction(elevation, azimuth),
    ambient=float(rng.uniform(*config.ambient)),
    light_color=tuple(float(c) for c in tint),
  )
  return scene, c2w
