"""Kubric-4D (multi-view dynamic) reader, as the official TokenGS `Kubric` dataset + provider.

Layout: `<root>/<subset>/<scene>/output_{view:03d}.tar` (subsets v0, v1, v2; 9 cameras x 24
frames), each tar holding `./metadata.json`, `./rgba_{frame:05d}.png` and (optional)
`./depth_{frame:05d}.tiff` (float32 z-depth). From the metadata, as official:

- intrinsics: fx = focal_length * W / sensor_width, fy = focal_length * H / sensor_width,
  (cx, cy) = (W / 2, H / 2), with `H, W = metadata.resolution` (the same for every frame);
- frame f's camera-to-world: rotation of the wxyz (Hamilton) quaternion `camera.quaternions[f]`,
  translation `camera.positions[f]`, in Blender/OpenGL axes (+y up, looking down -z); OpenCV
  is obtained by negating the y and z columns.

Examples are built by the shared input pipeline: `KubricSceneSource` yields scene records (the C
cameras x F frames flattened camera-major, lazy PNG/TIFF members) and `kubric_view_selector`
draws the official views (`_get_indices_dynamic` + `_curate_batch_dynamic`): `num_context`
cameras and `num_context` increasing frames spanning a random gap, plus one target frame; context
view v is camera v at frame v, target view v is camera v at the target frame. The pipeline
(`DATASET_PRESETS["kubric"]`) then min-max normalises the times, normalises the cameras
(`mean_cam`) and scales them by `translation_scale / mean distance of the context views' depth
points from the origin` ("pointmap", `pointmap_scale`).

Every failure to read a scene (unreadable or truncated tar, missing member, bad metadata, a
frame whose size is not the metadata's resolution) raises `KubricError` naming the file.
"""

from __future__ import annotations

import collections
import dataclasses
import io
import json
import os
import pathlib
import tarfile
from typing import Sequence

import numpy as np
from PIL import Image

from tokengs_jax.data.chunks import ChunkError, check_regular_file
from tokengs_jax.data.sampler import NotEnoughFramesError

__all__ = [
  "KubricError",
  "KubricSceneSource",
  "KubricView",
  "intrinsics_from_metadata",
  "kubric_view_selector",
  "kubric_pose_to_opencv",
  "list_kubric_scenes",
  "opencv_to_kubric_pose",
  "parse_kubric_view",
  "pointmap_scale",
  "quat_wxyz_to_rotation",
  "read_kubric_view",
  "rotation_to_quat_wxyz",
  "sample_dynamic_indices",
]

DEFAULT_SUBSETS = ("v0", "v1", "v2")
# Blender/OpenGL camera axes (x right, y up, looking down -z) -> OpenCV (x right, y down, +z).
_GL_TO_CV = np.diag([1.0, -1.0, -1.0])
_MAX_METADATA_BYTES = 64 << 20


class KubricError(ValueError):
  """A Kubric scene is malformed; the message names the file."""


def quat_wxyz_to_rotation(quats: np.ndarray) -> np.ndarray:
  """Unit quaternions (w, x, y, z), Hamilton convention -> rotation matrices.

  quats: [..., 4] -> [..., 3, 3] float64.
  """
  w, x, y, z = np.moveaxis(np.asarray(quats, np.float64), -1, 0)
  return np.stack(
    [
      np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
      np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
      np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ],
    -2,
  )


def rotation_to_quat_wxyz(rotation: np.ndarray) -> np.ndarray:
  """Rotation matrices -> unit quaternions (w, x, y, z) with w >= 0.

  Takes the eigenvector of the largest eigenvalue of Bar-Itzhack's symmetric 4x4 matrix, which
  is robust for every rotation (no branch on the trace).  rotation: [..., 3, 3] -> [..., 4].
  """
  r = np.asarray(rotation, np.float64)
  r00, r01, r02 = r[..., 0, 0], r[..., 0, 1], r[..., 0, 2]
  r10, r11, r12 = r[..., 1, 0], r[..., 1, 1], r[..., 1, 2]
  r20, r21, r22 = r[..., 2, 0], r[..., 2, 1], r[..., 2, 2]
  k = (
    np.stack(
      [
        np.stack([r00 + r11 + r22, r21 - r12, r02 - r20, r10 - r01], -1),
        np.stack([r21 - r12, r00 - r11 - r22, r01 + r10, r02 + r20], -1),
        np.stack([r02 - r20, r01 + r10, r11 - r00 - r22, r12 + r21], -1),
        np.stack([r10 - r01, r02 + r20, r12 + r21, r22 - r00 - r11], -1),
      ],
      -2,
    )
    / 3.0
  )
  _, vectors = np.linalg.eigh(k)
  quats = vectors[..., :, -1]  # eigh sorts eigenvalues ascending
  return quats * np.where(quats[..., :1] < 0, -1.0, 1.0)


def kubric_pose_to_opencv(positions: np.ndarray, quats: np.ndarray) -> np.ndarray:
  """Kubric camera poses -> OpenCV c2w.  positions: [F, 3], quats: [F, 4] wxyz -> [F, 4, 4]."""
  positions = np.asarray(positions, np.float64)
  c2w = np.zeros(positions.shape[:-1] + (4, 4))
  c2w[..., :3, :3] = quat_wxyz_to_rotation(quats) @ _GL_TO_CV
  c2w[..., :3, 3] = positions
  c2w[..., 3, 3] = 1.0
  return c2w


def opencv_to_kubric_pose(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """Inverse of `kubric_pose_to_opencv`: c2w [F, 4, 4] -> (positions [F, 3], quats [F, 4] wxyz)."""
  c2w = np.asarray(c2w, np.float64)
  return c2w[..., :3, 3].copy(), rotation_to_quat_wxyz(c2w[..., :3, :3] @ _GL_TO_CV)


def intrinsics_from_metadata(
  focal_length: float, sensor_width: float, height: int, width: int
) -> np.ndarray:
  """(fx, fy, cx, cy) in pixels, as the official loader derives them.  -> [4] float32.

  Note fy uses H / sensor_width like the official code: square pixels only for square images.
  Raises `KubricError` unless focal length, sensor width and resolution are finite and positive.
  """
  values = np.array([focal_length, sensor_width, height, width], np.float64)
  if not (np.isfinite(values).all() and (values > 0).all()):
    raise KubricError(
      f"focal_length {focal_length}, sensor_width {sensor_width} and resolution "
      f"{[height, width]} must be finite and positive"
    )
  return np.array(
    [
      focal_length * width / sensor_width,
      focal_length * height / sensor_width,
      0.5 * width,
      0.5 * height,
    ],
    np.float32,
  )


def list_kubric_scenes(
  root: str | os.PathLike, subsets: Sequence[str] = DEFAULT_SUBSETS
) -> list[pathlib.Path]:
  """Scene directories `<root>/<subset>/<scene>`, subsets in the given order, scenes sorted.

  Missing subsets are skipped (as official); no scene at all is an error.
  """
  root = pathlib.Path(root)
  found = [
    d
    for subset in subsets
    if (root / subset).is_dir()
    for d in sorted((root / subset).iterdir())
    if d.is_dir()
  ]
  if not found:
    raise KubricError(f"{root}: no Kubric scenes under subsets {list(subsets)}")
  return found


@dataclasses.dataclass(frozen=True)
class KubricView:
  """One camera's tar, parsed once: its cameras, and where each member's bytes lie in the file
  (so reading a frame is one seek + read, without rescanning the tar). Picklable.

  Attributes:
    path: the `output_{view:03d}.tar` file.
    c2w: [F, 4, 4] float32 camera-to-world (OpenCV) of every frame.
    intrinsics: [4] float32 (fx, fy, cx, cy) pixels, the same for every frame.
    height, width: the metadata's resolution.
    members: member name (without "./") -> (byte offset, size).
  """

  path: str
  c2w: np.ndarray
  intrinsics: np.ndarray
  height: int
  width: int
  members: dict

  @property
  def num_frames(self) -> int:
    return len(self.c2w)

  def read(self, name: str) -> bytes:
    """The bytes of member `name`; `KubricError` if it is missing or the tar is truncated."""
    if name not in self.members:
      raise KubricError(f"{self.path}: member '{name}' is missing")
    offset, size = self.members[name]
    try:
      with open(self.path, "rb") as handle:
        handle.seek(offset)
        data = handle.read(size)
    except OSError as error:
      raise KubricError(f"{self.path}: cannot read member '{name}' ({error})") from error
    if len(data) != size:
      raise KubricError(f"{self.path}: member '{name}' is truncated ({len(data)} of {size} bytes)")
    return data


def parse_kubric_view(tar_path: str | os.PathLike) -> KubricView:
  """Reads one camera's tar index and metadata (no pixels).  Raises `KubricError`."""
  path = str(tar_path)
  try:
    check_regular_file(path)
    with tarfile.open(path, "r") as tar:
      members = {
        m.name.removeprefix("./"): (m.offset_data, m.size) for m in tar.getmembers() if m.isreg()
      }
  except (ChunkError, tarfile.TarError, OSError, EOFError) as error:
    raise KubricError(f"{path}: not a readable tar ({error})") from error
  view = KubricView(path, np.zeros((0, 4, 4), np.float32), np.zeros(4, np.float32), 0, 0, members)
  if members.get("metadata.json", (0, 0))[1] > _MAX_METADATA_BYTES:
    raise KubricError(f"{path}: metadata.json larger than {_MAX_METADATA_BYTES} bytes")
  try:
    meta = json.loads(view.read("metadata.json"))
    camera = meta["camera"]
    height, width = (int(v) for v in meta["metadata"]["resolution"])
    positions = np.asarray(camera["positions"], np.float64)
    quats = np.asarray(camera["quaternions"], np.float64)
    focal, sensor = float(camera["focal_length"]), float(camera["sensor_width"])
  except (KeyError, TypeError, ValueError) as error:  # JSON and UTF-8 errors are ValueErrors
    raise KubricError(f"{path}: bad metadata.json ({type(error).__name__}: {error})") from error
  if positions.ndim != 2 or positions.shape[1] != 3 or quats.shape != (len(positions), 4):
    raise KubricError(
      f"{path}: camera positions {list(positions.shape)} / quaternions "
      f"{list(quats.shape)} must be [F, 3] / [F, 4]"
    )
  if not (np.isfinite(positions).all() and np.isfinite(quats).all()):
    raise KubricError(f"{path}: NaN/inf in the camera poses")
  try:
    intrinsics = intrinsics_from_metadata(focal, sensor, height, width)
  except KubricError as error:
    raise KubricError(f"{path}: metadata.json {error}") from None
  c2w = kubric_pose_to_opencv(positions, quats).astype(np.float32)
  return dataclasses.replace(view, c2w=c2w, intrinsics=intrinsics, height=height, width=width)


def read_kubric_view(
  tar_path: str | os.PathLike,
  frames: Sequence[int] | None = None,
  *,
  load_images: bool = True,
  load_depth: bool = False,
) -> dict:
  """Reads frames of one camera's tar.

  Args:
    tar_path: `.../output_{view:03d}.tar`.
    frames: frame indices to read (default all `camera.positions`).

  Returns:
    dict with `c2w` [F, 4, 4] float32 (OpenCV), `intrinsics` [F, 4] float32 (pixels),
    `frames` int [F], `num_frames` (in the file), `height`, `width`; `images` uint8 [F, H, W, 3]
    when `load_images`; `depths` float32 [F, H, W] (z-depth) when `load_depth`.
  """
  view = parse_kubric_view(tar_path)
  frames = np.arange(view.num_frames) if frames is None else np.asarray(frames, np.int64)
  if frames.size and (frames.min() < 0 or frames.max() >= view.num_frames):
    raise KubricError(
      f"{view.path}: frames {frames.tolist()} outside the {view.num_frames} in the file"
    )
  shape = (view.height, view.width)
  result = {
    "c2w": view.c2w[frames],
    "intrinsics": np.tile(view.intrinsics, (len(frames), 1)),
    "frames": frames,
    "num_frames": view.num_frames,
    "height": view.height,
    "width": view.width,
  }
  if load_images:
    images = [_decode(view, f"rgba_{f:05d}.png", shape) for f in frames]
    result["images"] = np.stack(images) if images else np.zeros((0, *shape, 3), np.uint8)
  if load_depth:
    depths = [_decode(view, f"depth_{f:05d}.tiff", shape) for f in frames]
    result["depths"] = np.stack(depths) if depths else np.zeros((0, *shape), np.float32)
  return result


def _decode(view: KubricView, name: str, shape: tuple[int, int]) -> np.ndarray:
  """Member `name` as uint8 [H, W, 3] RGB (PNG, alpha dropped as official) or float32 [H, W]
  depth (TIFF, read with PIL as official); its size must be the metadata's resolution."""
  try:
    with Image.open(io.BytesIO(view.read(name))) as image:
      pixels = (
        np.asarray(image.convert("RGB")) if name.endswith(".png") else np.asarray(image, np.float32)
      )
  except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as error:
    raise KubricError(f"{view.path}: corrupt {name} ({error})") from error
  pixels = pixels[..., 0] if name.endswith(".tiff") and pixels.ndim == 3 else pixels
  if pixels.shape[:2] != shape:
    raise KubricError(
      f"{view.path}: {name} is {list(pixels.shape[:2])}, metadata.json resolution "
      f"is {list(shape)} (the intrinsics would be wrong)"
    )
  return pixels


def sample_dynamic_indices(
  rng: np.random.Generator,
  num_frames: int,
  num_cameras: int,
  num_context: int,
  min_gap: int = 3,
  max_gap: int = 23,
  interp_target: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
  """Official `_get_indices_dynamic`, with the same draws from `rng` in the same order.

  Returns:
    frames [num_context + 1] (increasing context frames spanning the gap, then the target frame,
    anywhere in the span when `interp_target`, else one of the context frames) and
    cameras [num_context] (distinct cameras; repeated in a shuffled cycle when there are fewer).
  """
  if num_frames < num_context:
    raise NotEnoughFramesError(f"{num_frames} frames are fewer than {num_context} context views")
  gap = int(rng.integers(min_gap, max_gap + 1))
  gap = max(min(num_frames - 1, gap), num_context - 1)
  start = int(rng.integers(0, num_frames - gap))
  between = np.sort(rng.permutation(np.arange(start + 1, start + gap))[: num_context - 2])
  frames = np.array([start, *between, start + gap])
  target = rng.permutation(np.arange(start, start + gap + 1))[:1]
  if not interp_target:
    target = rng.permutation(frames)[:1]
  frames = np.concatenate([frames, target])
  if num_context > num_cameras:
    views = rng.permutation(np.arange(num_context) % num_cameras)
  else:
    views = rng.permutation(np.arange(num_cameras))[:num_context]
  return frames, views


def pointmap_scale(
  depths: np.ndarray,
  c2w: np.ndarray,
  intrinsics: np.ndarray,
  trim: tuple[float, float] = (0.0, 1.0),
) -> float:
  """Mean distance from the origin of the points the depth maps see (official "pointmap").

  Unprojects every pixel with depth > 1e-8 at integer pixel coordinates (as official, no +0.5),
  optionally keeps only distances between the `trim` quantiles, and returns the mean (1.0 when
  no pixel has depth).

  depths: [V, H, W] z-depth, c2w: [V, 4, 4] (already normalised), intrinsics: [V, 4] pixels.
  """
  distances = []
  for depth, pose, (fx, fy, cx, cy) in zip(depths, np.asarray(c2w, np.float64), intrinsics):
    rows, cols = np.nonzero(depth > 1e-8)
    z = depth[rows, cols].astype(np.float64)
    points = np.stack([(cols - cx) / fx * z, (rows - cy) / fy * z, z], -1)
    distances.append(np.linalg.norm(points @ pose[:3, :3].T + pose[:3, 3], axis=-1))
  distances = np.concatenate(distances) if distances else np.zeros(0)
  if distances.size == 0:
    return 1.0
  lo, hi = trim
  if (lo > 0.0 or hi < 1.0) and distances.size > 1:
    kept = distances[
      (distances >= np.quantile(distances, lo)) & (distances <= np.quantile(distances, hi))
    ]
    distances = kept if kept.size else distances
  return float(max(distances.mean(), 1e-6))


# ----------------------------------------------------------------------------------------------
# Scene records for the input pipeline (`tokengs_jax.data.pipeline.InputPipeline`)


class _TarFrames:
  """Lazy length-(C*F) sequence of one per-frame member's bytes, camera-major: item c * F + f
  is camera c, frame f. `member` is a format string of the frame, e.g. "rgba_{:05d}.png".

  The pipeline decodes only the items it picks.
  """

  def __init__(self, views: Sequence[KubricView], num_frames: int, member: str):
    self.views, self.num_frames, self.member = tuple(views), num_frames, member

  def __len__(self) -> int:
    return len(self.views) * self.num_frames

  def __getitem__(self, index: int) -> bytes:
    if not 0 <= index < len(self):
      raise IndexError(f"{self.views[0].path}: view {index} of {len(self)}")
    camera, frame = divmod(int(index), self.num_frames)
    return self.views[camera].read(self.member.format(frame))


class KubricSceneSource:
  """Random-access source of Kubric scene records in the pipeline's record contract.

  A scene's C cameras x F frames are flattened camera-major into C*F "frames": `c2w [C*F, 4, 4]`
  (OpenCV), `intrinsics [C*F, 4]`, lazy PNG `images`, lazy TIFF `depths` (the pipeline's
  "pointmap" scale reads the context views' ones), and `times [C*F]` = the frame index (the
  pipeline min-max normalises times per example, as official), plus `num_cameras`,
  `num_frames` for `kubric_view_selector`.

  Each scene's tars are parsed once per process (metadata and member offsets, cached for the
  last 64 scenes); a sample then reads only its views' members. A malformed scene raises
  `KubricError` on access (the pipeline's `skip_bad` counts and skips it).

  Args:
    root, subsets: list the scenes with `list_kubric_scenes(root, subsets)`...
    scenes: ...or use exactly these scene directories (e.g. a train/held-out split of a listing).
  """

  def __init__(
    self,
    root: str | os.PathLike | None = None,
    subsets: Sequence[str] = DEFAULT_SUBSETS,
    *,
    scenes: Sequence[str | os.PathLike] | None = None,
  ):
    if (root is None) == (scenes is None):
      raise ValueError("give either root (with subsets) or scenes")
    self.scenes = (
      [pathlib.Path(s) for s in scenes] if scenes is not None else list_kubric_scenes(root, subsets)
    )
    self._cache: collections.OrderedDict = collections.OrderedDict()

  def __len__(self) -> int:
    return len(self.scenes)

  @property
  def keys(self) -> list[str]:
    """The scene keys (directory names), in item order."""
    return [scene.name for scene in self.scenes]

  def __getitem__(self, index: int) -> dict:
    scene_dir = self.scenes[index]
    key = (os.getpid(), scene_dir)
    if key not in self._cache:
      self._cache[key] = self._read_scene(scene_dir)
      while len(self._cache) > 64:
        self._cache.popitem(last=False)
    self._cache.move_to_end(key)
    return dict(self._cache[key])

  def __getstate__(self):  # workers build their own cache
    return {**self.__dict__, "_cache": collections.OrderedDict()}

  @staticmethod
  def _read_scene(scene_dir: pathlib.Path) -> dict:
    count = len(list(scene_dir.glob("output_*.tar")))
    if not count:
      raise KubricError(f"{scene_dir}: no output_*.tar camera files")
    views = [parse_kubric_view(scene_dir / f"output_{c:03d}.tar") for c in range(count)]
    first = views[0]
    if any(
      (v.num_frames, v.height, v.width) != (first.num_frames, first.height, first.width)
      for v in views
    ):
      raise KubricError(f"{scene_dir}: cameras differ in frame count or resolution")
    return {
      "key": scene_dir.name,
      "source": str(scene_dir),
      "c2w": np.concatenate([v.c2w for v in views]),
      "intrinsics": np.tile(
        np.stack([v.intrinsics for v in views])[:, None], (1, first.num_frames, 1)
      ).reshape(-1, 4),
      "height": first.height,
      "width": first.width,
      "images": _TarFrames(views, first.num_frames, "rgba_{:05d}.png"),
      "depths": _TarFrames(views, first.num_frames, "depth_{:05d}.tiff"),
      "times": np.tile(np.arange(first.num_frames, dtype=np.float64), len(views)),
      "num_cameras": len(views),
      "num_frames": first.num_frames,
    }


def kubric_view_selector(
  num_context: int,
  num_targets: int,
  min_gap: int = 3,
  max_gap: int = 23,
  interp_target: bool = True,
):
  """A pipeline `select_views(record, rng, step)` doing the official dynamic sampling on the
  flattened records of `KubricSceneSource`: context v = (camera v, frame v), target v =
  (camera v, target frame), returned as flat indices camera * F + frame."""
  if not 0 < num_targets <= num_context:
    raise ValueError(f"need 0 < targets ({num_targets}) <= context views ({num_context})")

  def select(record: dict, rng: np.random.Generator, step: int) -> tuple[np.ndarray, np.ndarray]:
    del step  # the official dynamic sampler has no warm-up
    num_frames = record["num_frames"]
    frames, cameras = sample_dynamic_indices(
      rng, num_frames, record["num_cameras"], num_context, min_gap, max_gap, interp_target
    )
    context = cameras * num_frames + frames[:num_context]
    target = cameras[:num_targets] * num_frames + frames[-1]
    return context, target

  return select
