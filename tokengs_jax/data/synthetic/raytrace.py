"""An analytic numpy ray tracer of textured planes, boxes and spheres.

It is deliberately independent of the Gaussian splatting renderer (no shared code, not even the
camera helpers), so that synthetic data checks the model and renderer against ground truth made by
a different method. Everything is vectorised over rays; a scene has only a handful of primitives,
so the Python loop over primitives is cheap.

Conventions: OpenCV camera axes (+x right, +y down, +z forward), `c2w [4, 4]` camera-to-world,
intrinsics (fx, fy, cx, cy) in pixels, pixel (row i, column j) centred at (j + 0.5, i + 0.5).
Depth is the planar camera z (the Kubric writers convert it to Kubric's ray distance).

Shading: Lambert + ambient under one directional (optionally coloured) light, with hard shadows
cast by the objects (boxes and spheres) only; the enclosing planes (floor, walls) do not cast
shadows, so a room with a ceiling is still lit ("light through the ceiling").
"""

from __future__ import annotations

import dataclasses
import itertools
from typing import NamedTuple, Union

import numpy as np

_EPS = 1e-4  # minimum hit distance: avoids self-intersection of shadow rays
TEXTURE_KINDS = (
  "solid",
  "checker",
  "stripes",
  "gradient",
  "noise",
  "rings",
  "dots",
  "bricks",
  "photo",
)


@dataclasses.dataclass(frozen=True)
class Texture:
  """A procedural texture evaluated on the 3D local coordinates of a primitive.

  Attributes:
    kind: one of `TEXTURE_KINDS`.
    color_a, color_b: linear RGB in [0, 1]; the pattern mixes between them.
    frequency: pattern cells per metre (of local coordinates).
    axis: local axis of `stripes` / `gradient`.
    seed: lattice seed of `noise`; the photograph's offset for `photo`.
    image: for `photo`, the name of a photograph in `synthetic.photos` (natural-image
      statistics: edges, gradients and clutter that no procedural kind has). Its grey level
      mixes `color_a` to `color_b` when `tint` is set, else its own colours are the albedo.
    tint: see `image`.

  `rings` (concentric about the local origin), `dots` (a lattice of discs) and `bricks`
  (staggered rows, mortar in `color_b`) are drawn only by the gallery family (`scenes.py`), so
  a model trained on the rooms never sees them.
  """

  kind: str = "solid"
  color_a: tuple[float, float, float] = (0.8, 0.8, 0.8)
  color_b: tuple[float, float, float] = (0.2, 0.2, 0.2)
  frequency: float = 1.0
  axis: int = 0
  seed: int = 0
  image: str = ""
  tint: bool = False

  def __post_init__(self):
    if self.kind not in TEXTURE_KINDS:
      raise ValueError(f"unknown texture kind {self.kind!r}; expected one of {TEXTURE_KINDS}")
    if (self.kind == "photo") != bool(self.image):
      raise ValueError("a `photo` texture names its `image`, and only a `photo` texture does")


def _hash3(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, seed: int) -> np.ndarray:
  """Integer lattice hash -> uniform floats in [0, 1).  ix, iy, iz: [...] int64 -> [...] float32."""
  h = (ix.astype(np.uint32) * np.uint32(73856093)) ^ (iy.astype(np.uint32) * np.uint32(19349663))
  h ^= iz.astype(np.uint32) * np.uint32(83492791)
  h ^= np.uint32((seed * 2654435761) & 0xFFFFFFFF)
  # Murmur3 finaliser: spreads the low-entropy products over all bits.
  h ^= h >> np.uint32(16)
  h *= np.uint32(0x85EBCA6B)
  h ^= h >> np.uint32(13)
  h *= np.uint32(0xC2B2AE35)
  h ^= h >> np.uint32(16)
  return (h >> np.uint32(8)).astype(np.float32) / np.float32(1 << 24)


def value_noise(points: np.ndarray, seed: int, octaves: int = 3) -> np.ndarray:
  """Fractal 3D value noise (smoothstep-trilinear lattice noise, octaves halve in amplitude).

  points: [N, 3] -> [N] in [0, 1].
  """
  total = np.zeros(points.shape[0], np.float32)
  norm = 0.0
  for octave in range(octaves):
    p = points * np.float32(2.0**octave)
    base = np.floor(p)
    frac = p - base
    w = frac * frac * (3.0 - 2.0 * frac)  # smoothstep: C1 across lattice cells
    base = base.astype(np.int64)
    weights = (1.0 - w, w)  # per axis: weight of the lower / upper lattice corner
    layer = np.zeros_like(total)
    for dx, dy, dz in itertools.product((0, 1), repeat=3):
      weight = weights[dx][:, 0] * weights[dy][:, 1] * weights[dz][:, 2]
      layer += weight * _hash3(base[:, 0] + dx, base[:, 1] + dy, base[:, 2] + dz, seed + octave)
    amplitude = 0.5**octave
    total += amplitude * layer
    norm += amplitude
  return total / np.float32(norm)


def _photo_color(texture: Texture, p: np.ndarray, face_axis: np.ndarray) -> np.ndarray:
  """A photograph tiled over the surface: the two local axes other than the face's normal axis
  (`face_axis [N]`) address it, one tile per unit of `p`; nearest texel.  -> [N, 3]."""
  from tokengs_jax.data.synthetic.photos import photo

  image = photo(texture.image)
  rows = np.arange(len(p))
  keep = np.array([[1, 2], [0, 2], [0, 1]])[face_axis]  # [N, 2] the in-face axes
  uv = p[rows[:, None], keep] + np.float32(texture.seed % 997) / 997.0
  uv = uv - np.floor(uv)
  height, width = image.shape[:2]
  texels = image[
    np.minimum((uv[:, 1] * height).astype(np.int64), height - 1),
    np.minimum((uv[:, 0] * width).astype(np.int64), width - 1),
  ]
  if not texture.tint:
    return texels
  grey = texels.mean(-1, keepdims=True)
  color_a = np.asarray(texture.color_a, np.float32)
  return color_a + grey * (np.asarray(texture.color_b, np.float32) - color_a)


def texture_color(
  texture: Texture, local: np.ndarray, face_axis: np.ndarray | None = None
) -> np.ndarray:
  """Albedo of `texture` at local surface coordinates.

  local: [N, 3] (metres); face_axis: [N] the local axis closest to the surface normal (only
  `photo` reads it; default 2, a plane's) -> [N, 3].
  """
  p = local * np.float32(texture.frequency)
  if texture.kind == "photo":
    if face_axis is None:
      face_axis = np.full(len(local), 2, np.int64)
    return _photo_color(texture, p, face_axis)
  if texture.kind == "solid":
    mix = np.zeros(local.shape[0], np.float32)
  elif texture.kind == "checker":
    mix = (np.floor(p).astype(np.int64).sum(-1) % 2).astype(np.float32)
  elif texture.kind == "stripes":
    mix = (np.floor(p[:, texture.axis]).astype(np.int64) % 2).astype(np.float32)
  elif texture.kind == "gradient":
    # Triangle wave: linear ramps without the jump a sawtooth would have.
    mix = np.abs(2.0 * (p[:, texture.axis] - np.floor(p[:, texture.axis])) - 1.0)
  elif texture.kind == "noise":
    mix = value_noise(p, texture.seed)
  elif texture.kind == "rings":
    mix = (np.floor(np.linalg.norm(p, axis=-1)).astype(np.int64) % 2).astype(np.float32)
  elif texture.kind == "dots":
    mix = (np.linalg.norm(p - np.round(p), axis=-1) < 0.3).astype(np.float32)
  else:  # bricks: rows of height 1/2 along local axis 1, every other row shifted half a brick
    row = np.floor(2.0 * p[:, 1])
    along = p[:, 0] + 0.5 * (row % 2)
    mortar = ((along - np.floor(along)) < 0.08) | ((2.0 * p[:, 1] - row) < 0.12)
    mix = mortar.astype(np.float32)
  color_a = np.asarray(texture.color_a, np.float32)
  color_b = np.asarray(texture.color_b, np.float32)
  return color_a + mix[:, None] * (color_b - color_a)


def _as_rotation(rotation) -> np.ndarray:
  return np.eye(3, dtype=np.float32) if rotation is None else np.asarray(rotation, np.float32)


@dataclasses.dataclass(frozen=True, eq=False)
class Plane:
  """Infinite plane through `point` with unit `normal`; `tangent` fixes the texture's u axis.

  Local coordinates are (u, v, 0) with u along `tangent`, v along normal x tangent.
  """

  point: np.ndarray
  normal: np.ndarray
  tangent: np.ndarray
  texture: Texture = Texture()

  def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """origins, dirs: [N, 3] -> hit distance t [N] (inf where missed)."""
    normal = np.asarray(self.normal, np.float32)
    denom = dirs @ normal
    with np.errstate(divide="ignore", invalid="ignore"):
      t = ((np.asarray(self.point, np.float32) - origins) @ normal) / denom
    return np.where((np.abs(denom) > 1e-8) & (t > _EPS), t, np.inf).astype(np.float32)

  def surface(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """points: [N, 3] on the plane -> (normals [N, 3], local coordinates [N, 3], the local axis
    of the normal [N])."""
    normal = np.asarray(self.normal, np.float32)
    tangent = np.asarray(self.tangent, np.float32)
    bitangent = np.cross(normal, tangent)
    rel = points - np.asarray(self.point, np.float32)
    local = np.stack([rel @ tangent, rel @ bitangent, np.zeros(len(points), np.float32)], -1)
    return np.broadcast_to(normal, points.shape), local, np.full(len(points), 2, np.int64)


@dataclasses.dataclass(frozen=True, eq=False)
class Sphere:
  """Sphere; `rotation [3, 3]` (object-to-world) turns its texture with it."""

  center: np.ndarray
  radius: float
  texture: Texture = Texture()
  rotation: np.ndarray | None = None

  def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """origins, dirs (unit): [N, 3] -> t [N] (inf where missed; far root when inside)."""
    oc = origins - np.asarray(self.center, np.float32)
    b = np.einsum("ni,ni->n", oc, dirs)
    c = np.einsum("ni,ni->n", oc, oc) - np.float32(self.radius) ** 2
    disc = b * b - c
    root = np.sqrt(np.maximum(disc, 0.0))
    near, far = -b - root, -b + root
    t = np.where(near > _EPS, near, far)
    return np.where((disc >= 0.0) & (t > _EPS), t, np.inf).astype(np.float32)

  def surface(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rel = points - np.asarray(self.center, np.float32)
    normals = rel / np.float32(self.radius)
    local = rel @ _as_rotation(self.rotation)  # world -> object: R^T p, as row vectors
    return normals, local, np.argmax(np.abs(local), axis=-1)


@dataclasses.dataclass(frozen=True, eq=False)
class Box:
  """Oriented box: `center`, `half_size [3]`, `rotation [3, 3]` (object-to-world)."""

  center: np.ndarray
  half_size: np.ndarray
  texture: Texture = Texture()
  rotation: np.ndarray | None = None

  def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Slab test in the box frame.  origins, dirs: [N, 3] -> t [N] (inf where missed)."""
    rot = _as_rotation(self.rotation)
    local_o = (origins - np.asarray(self.center, np.float32)) @ rot
    local_d = dirs @ rot
    # Replace exact zeros so 1/d is a huge finite number: the slab test stays correct.
    local_d = np.where(np.abs(local_d) < 1e-12, np.float32(1e-12), local_d)
    half = np.asarray(self.half_size, np.float32)
    t1 = (-half - local_o) / local_d
    t2 = (half - local_o) / local_d
    near, far = np.minimum(t1, t2), np.maximum(t1, t2)
    # Per-axis columns, not .max(-1): numpy's reduction over a length-3 axis is several times
    # slower, and this is the ray tracer's hottest line.
    t_enter = np.maximum(np.maximum(near[:, 0], near[:, 1]), near[:, 2])
    t_exit = np.minimum(np.minimum(far[:, 0], far[:, 1]), far[:, 2])
    t = np.where(t_enter > _EPS, t_enter, t_exit)
    return np.where((t_exit >= t_enter) & (t > _EPS), t, np.inf).astype(np.float32)

  def surface(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rot = _as_rotation(self.rotation)
    local = (points - np.asarray(self.center, np.float32)) @ rot
    # The face hit is the axis where the point is relatively closest to the box's extent.
    axis = np.argmax(np.abs(local) / np.asarray(self.half_size, np.float32), axis=-1)
    normals_local = np.zeros_like(local)
    rows = np.arange(len(points))
    normals_local[rows, axis] = np.sign(local[rows, axis])
    return normals_local @ rot.T, local, axis


Primitive = Union[Plane, Sphere, Box]


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
  """A scene: enclosing `planes` (no shadows cast) and `objects` (cast shadows).

  Primitive ids (as in `RenderOutput.ids`) number the planes first, then the objects.
  `instances` groups objects into rigid object instances (a composite of several parts is one
  instance): object j belongs to instance `instances[j]`, numbered from 0; empty: each object is
  its own instance, in order. Only `segmentation` reads it.
  """

  planes: tuple[Plane, ...] = ()
  objects: tuple[Union[Sphere, Box], ...] = ()
  light_direction: tuple[float, float, float] = (0.3, 1.0, 0.2)  # towards the light (world)
  ambient: float = 0.35
  light_color: tuple[float, float, float] = (1.0, 1.0, 1.0)  # scales the direct (Lambert) term
  background: tuple[float, float, float] = (0.55, 0.7, 0.9)
  instances: tuple[int, ...] = ()

  @property
  def primitives(self) -> tuple[Primitive, ...]:
    return tuple(self.planes) + tuple(self.objects)

  def segmentation(self, ids: np.ndarray) -> np.ndarray:
    """Primitive ids (`RenderOutput.ids`, -1 where nothing was hit) -> the instance segmentation
    Kubric writes: 0 for the background (nothing, or a plane), k + 1 for object instance k.

    ids: [...] int -> [...] int32.
    """
    instances = self.instances or range(len(self.objects))
    if len(instances) != len(self.objects):
      raise ValueError(f"{len(instances)} instance numbers for {len(self.objects)} objects")
    # index 0: nothing hit (id -1); then the planes (background); then each object's instance
    table = np.concatenate(
      [np.zeros(1 + len(self.planes), np.int32), np.asarray(instances, np.int32) + 1]
    )
    return table[np.asarray(ids) + 1]


class TraceResult(NamedTuple):
  rgb: np.ndarray  # [N, 3] in [0, 1]
  distance: np.ndarray  # [N] ray parameter t (inf where nothing was hit)
  ids: np.ndarray  # [N] int32 primitive id, -1 where nothing was hit


def _nearest_hit(primitives, origins, dirs) -> tuple[np.ndarray, np.ndarray]:
  """-> (t [N], primitive id [N] or -1)."""
  best_t = np.full(len(origins), np.inf, np.float32)
  best_id = np.full(len(origins), -1, np.int32)
  for index, primitive in enumerate(primitives):
    t = primitive.intersect(origins, dirs)
    closer = t < best_t
    best_t = np.where(closer, t, best_t)
    best_id = np.where(closer, index, best_id)
  return best_t, best_id


def trace(scene: Scene, origins: np.ndarray, dirs: np.ndarray) -> TraceResult:
  """Shade the first hit of each ray.

  origins, dirs (unit length): [N, 3] float32 -> `TraceResult`.
  """
  primitives = scene.primitives
  t, ids = _nearest_hit(primitives, origins, dirs)
  hit = ids >= 0
  points = origins + np.where(hit, t, 0.0)[:, None] * dirs
  normals = np.zeros_like(points)
  albedo = np.broadcast_to(np.asarray(scene.background, np.float32), points.shape).copy()
  for index, primitive in enumerate(primitives):
    mask = ids == index
    if not mask.any():
      continue
    normals[mask], local, face_axis = primitive.surface(points[mask])
    albedo[mask] = texture_color(primitive.texture, local, face_axis)
  # Lambert needs the side of the surface that faces the viewer (walls are seen from inside).
  normals = np.where((np.einsum("ni,ni->n", normals, dirs) > 0)[:, None], -normals, normals)
  light = np.asarray(scene.light_direction, np.float32)
  light = light / np.linalg.norm(light)
  lambert = np.maximum(normals @ light, 0.0)
  if scene.objects:
    lit = hit & (lambert > 0)
    shadow_origins = points[lit] + np.float32(1e-3) * normals[lit]
    shadow_t, _ = _nearest_hit(
      scene.objects, shadow_origins, np.broadcast_to(light, shadow_origins.shape)
    )
    lambert[np.flatnonzero(lit)[np.isfinite(shadow_t)]] = 0.0
  direct = lambert[:, None] * np.asarray(scene.light_color, np.float32)
  shade = np.float32(scene.ambient) + np.float32(1.0 - scene.ambient) * direct
  rgb = np.where(hit[:, None], albedo * shade, albedo)
  return TraceResult(np.clip(rgb, 0.0, 1.0).astype(np.float32), t, ids)


class RenderOutput(NamedTuple):
  rgb: np.ndarray  # [H, W, 3] float32 in [0, 1]
  depth: np.ndarray  # [H, W] float32 camera z-depth at pixel centres (0 where nothing was hit)
  ids: np.ndarray  # [H, W] int32 primitive id at pixel centres, -1 where nothing was hit


def camera_rays(
  c2w: np.ndarray,
  intrinsics: np.ndarray,
  height: int,
  width: int,
  offsets: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
  """World-space rays through sub-pixel positions.

  Args:
    c2w: [4, 4] OpenCV camera-to-world.
    intrinsics: [4] (fx, fy, cx, cy) in pixels.
    offsets: [S, 2] sub-pixel (x, y) positions in [0, 1) within a pixel; default the centre.

  Returns:
    origins [H, W, S, 3], unit directions [H, W, S, 3] (float32).
  """
  if offsets is None:
    offsets = np.array([[0.5, 0.5]], np.float32)
  fx, fy, cx, cy = (float(v) for v in intrinsics)
  u = np.arange(width, dtype=np.float32)[None, :, None] + offsets[None, None, :, 0]
  v = np.arange(height, dtype=np.float32)[:, None, None] + offsets[None, None, :, 1]
  u, v = np.broadcast_arrays(u, v)
  dirs_cam = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1)
  dirs_cam /= np.linalg.norm(dirs_cam, axis=-1, keepdims=True)
  c2w = np.asarray(c2w, np.float32)
  dirs = dirs_cam @ c2w[:3, :3].T
  origins = np.broadcast_to(c2w[:3, 3], dirs.shape)
  return origins, dirs.astype(np.float32)


def render(
  scene: Scene,
  c2w: np.ndarray,
  intrinsics: np.ndarray,
  height: int,
  width: int,
  supersample: int = 1,
) -> RenderOutput:
  """Render colour (box-filtered over `supersample`² sub-pixel samples), depth and ids.

  Depth and ids come from the pixel-centre ray, so they are exact analytic values even when the
  colour is anti-aliased.

  c2w: [4, 4] OpenCV camera-to-world; intrinsics: [4] pixels.
  """
  centre_o, centre_d = camera_rays(c2w, intrinsics, height, width)
  centre = trace(scene, centre_o.reshape(-1, 3), centre_d.reshape(-1, 3))
  if supersample > 1:
    grid = (np.arange(supersample, dtype=np.float32) + 0.5) / supersample
    offsets = np.stack(np.meshgrid(grid, grid, indexing="xy"), -1).reshape(-1, 2)
    sub_o, sub_d = camera_rays(c2w, intrinsics, height, width, offsets)
    rgb = trace(scene, sub_o.reshape(-1, 3), sub_d.reshape(-1, 3)).rgb
    rgb = rgb.reshape(height, width, -1, 3).mean(axis=2)
  else:
    rgb = centre.rgb.reshape(height, width, 3)
  forward = np.asarray(c2w, np.float32)[:3, 2]
  z = centre.distance * (centre_d.reshape(-1, 3) @ forward)
  depth = np.where(centre.ids >= 0, z, 0.0).astype(np.float32).reshape(height, width)
  return RenderOutput(rgb.astype(np.float32), depth, centre.ids.reshape(height, width))
