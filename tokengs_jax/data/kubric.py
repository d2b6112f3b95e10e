"""Kubric-4D (multi-view dynamic) reader, as the official TokenGS `Kubric` dataset + provider.

Layout: `<root>/<subset>/<scene>/output_{view:03d}.tar` (subsets v0, v1, v2; 9 cameras x 24
frames), each tar holding `./metadata.json`, `./rgba_{frame:05d}.png` and (optional)
`./depth_{frame:05d}.tiff` (float32 z-depth). From the metadata, as official:

- intrinsics: fx = focal_length * W / sensor_width, fy = focal_length * H / sensor_width,
  (cx, cy) = (W / 2, H / 2), with `H, W = metadata.resolution` (the same for every frame);
- frame f's camera-to-world: rotation of the wxyz (Hamilton) quaternion `camera.quaternions[f]`,
  translation `camera.positions[f]`, in Blender/OpenGL axes (+y up, looking down -z); OpenCV
  is obtained by negating the y and z columns.

An example (official `_get_indices_dynamic` + `_curate_batch_dynamic` + `_preprocess`): pick
`num_context` cameras and `num_context` increasing frames spanning a random gap, plus one target
frame; context view v is camera v at frame v, target view v is camera v at the target frame.
Times are the frame indices min-max normalised over the example. Cameras are normalised
(`mean_cam` by default) and scaled by `base_scale / mean distance of the context views' depth
points from the origin` ("pointmap").
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
import pathlib
import tarfile
from typing import Literal, Sequence

import numpy as np
from PIL import Image

from tokengs_jax.data import transforms

__all__ = [
  "KubricConfig",
  "KubricError",
  "KubricSceneSource",
  "KubricSource",
  "intrinsics_from_metadata",
  "kubric_view_selector",
  "kubric_pose_to_opencv",
  "list_kubric_scenes",
  "make_kubric_example",
  "normalize_times",
  "opencv_to_kubric_pose",
  "pointmap_scale",
  "quat_wxyz_to_rotation",
  "read_kubric_view",
  "rotation_to_quat_wxyz",
  "sample_dynamic_indices",
]

DEFAULT_SUBSETS = ("v0", "v1", "v2")
# Blender/OpenGL camera axes (x right, y up, looking down -z) -> OpenCV (x right, y down, +z).
_GL_TO_CV = np.diag([1.0, -1.0, -1.0])


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
  """
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


def _member(tar: tarfile.TarFile, name: str, path: str) -> bytes:
  for candidate in (f"./{name}", name):  # released tars prefix './'; accept both
    try:
      handle = tar.extractfile(candidate)
    except KeyError:
      continue
    if handle is not None:
      return handle.read()
  raise KubricError(f"{path}: member '{name}' is missing")


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
  path = str(tar_path)
  try:
    tar = tarfile.open(path, "r")
  except (tarfile.TarError, OSError) as error:
    raise KubricError(f"{path}: not a readable tar ({error})") from error
  with tar:
    try:
      meta = json.loads(_member(tar, "metadata.json", path))
      camera = meta["camera"]
      height, width = (int(v) for v in meta["metadata"]["resolution"])
      positions = np.asarray(camera["positions"], np.float64)
      quats = np.asarray(camera["quaternions"], np.float64)
      focal, sensor = float(camera["focal_length"]), float(camera["sensor_width"])
    except (KeyError, TypeError, ValueError) as error:
      raise KubricError(f"{path}: bad metadata.json ({type(error).__name__}: {error})") from error
    if positions.ndim != 2 or positions.shape[1] != 3 or quats.shape != (len(positions), 4):
      raise KubricError(
        f"{path}: camera positions {list(positions.shape)} / quaternions "
        f"{list(quats.shape)} must be [F, 3] / [F, 4]"
      )
    if not (np.isfinite(positions).all() and np.isfinite(quats).all()):
      raise KubricError(f"{path}: NaN/inf in the camera poses")
    num_frames = len(positions)
    frames = np.arange(num_frames) if frames is None else np.asarray(frames, np.int64)
    if frames.size and (frames.min() < 0 or frames.max() >= num_frames):
      raise KubricError(f"{path}: frames {frames.tolist()} outside the {num_frames} in the file")
    result = {
      "c2w": kubric_pose_to_opencv(positions[frames], quats[frames]).astype(np.float32),
      "intrinsics": np.tile(
        intrinsics_from_metadata(focal, sensor, height, width), (len(frames), 1)
      ),
      "frames": frames,
      "num_frames": num_frames,
      "height": height,
      "width": width,
    }
    if load_images:
      result["images"] = (
        np.stack([_decode_rgb(_member(tar, f"rgba_{f:05d}.png", path), path, f) for f in frames])
        if frames.size
        else np.zeros((0, height, width, 3), np.uint8)
      )
    if load_depth:
      result["depths"] = (
        np.stack(
          [_decode_depth(_member(tar, f"depth_{f:05d}.tiff", path), path, f) for f in frames]
        )
        if frames.size
        else np.zeros((0, height, width), np.float32)
      )
  return result


def _decode_rgb(data: bytes, path: str, frame: int) -> np.ndarray:
  try:
    with Image.open(io.BytesIO(data)) as image:
      return np.asarray(image.convert("RGB"))  # alpha dropped, as official
  except (OSError, SyntaxError, ValueError) as error:
    raise KubricError(f"{path}: corrupt rgba_{frame:05d}.png ({error})") from error


def _decode_depth(data: bytes, path: str, frame: int) -> np.ndarray:
  try:
    with Image.open(io.BytesIO(data)) as image:
      depth = np.asarray(image, np.float32)
  except (OSError, SyntaxError, ValueError) as error:
    raise KubricError(f"{path}: corrupt depth_{frame:05d}.tiff ({error})") from error
  return depth[..., 0] if depth.ndim == 3 else depth


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
    raise ValueError(f"{num_frames} frames are fewer than {num_context} context views")
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


def normalize_times(frames: np.ndarray) -> np.ndarray:
  """Official time normalisation: (t - min) / (max - min) over the example.  [V] -> [V] float32."""
  frames = np.asarray(frames, np.float64)
  span = frames.max() - frames.min()
  if span <= 0:
    raise ValueError(f"times of an example must not all be equal, got {frames.tolist()}")
  return ((frames - frames.min()) / span).astype(np.float32)


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


@dataclasses.dataclass(frozen=True)
class KubricConfig:
  """Kubric example options; defaults are official `finetune_dl3dv_kubric_dyn` + registry."""

  root: str = "data/kubric"
  subsets: tuple[str, ...] = DEFAULT_SUBSETS
  num_context: int = 4
  num_views: int = 8  # context + targets; targets <= context (official assertion)
  image_shape: tuple[int, int] = (256, 256)
  min_gap: int = 3
  max_gap: int = 23
  interp_target: bool = True
  normalization: Literal["first_cam", "mean_cam"] = "mean_cam"
  scale_method: Literal["constant", "distance", "bound", "pointmap"] = "pointmap"
  base_scale: float = 1.0
  pointmap_trim: tuple[float, float] = (0.0, 1.0)
  random_flip: bool = True  # only applied when an example is made with training=True

  def __post_init__(self):
    num_targets = self.num_views - self.num_context
    if not (0 < num_targets <= self.num_context):
      raise ValueError(f"need 0 < targets ({num_targets}) <= context views ({self.num_context})")


def make_kubric_example(
  scene_dir: str | os.PathLike,
  rng: np.random.Generator,
  config: KubricConfig = KubricConfig(),
  *,
  training: bool = True,
  scene_index: int = 0,
) -> dict:
  """One example from a scene directory, drawing every random choice from `rng`.

  Returns:
    dict of numpy arrays: `context_images` [Vc, H, W, 3] float32 in [0, 1], `context_c2w`
    [Vc, 4, 4], `context_intrinsics` [Vc, 4] (pixels), `context_times` [Vc], the same four
    `target_*` with Vt = num_views - num_context, and `scene_index` int64 [].
  """
  scene_dir = pathlib.Path(scene_dir)
  views = sorted(scene_dir.glob("output_*.tar"))
  if not views:
    raise KubricError(f"{scene_dir}: no output_*.tar camera files")
  first = read_kubric_view(views[0], frames=[], load_images=False)
  frames, cameras = sample_dynamic_indices(
    rng,
    first["num_frames"],
    len(views),
    config.num_context,
    config.min_gap,
    config.max_gap,
    config.interp_target,
  )
  num_context, num_targets = config.num_context, config.num_views - config.num_context
  # (camera, frame) of every view: context v = (camera v, frame v); target v = (camera v, target)
  picks = [(cameras[v], frames[v]) for v in range(num_context)]
  picks += [(cameras[v], frames[-1]) for v in range(num_targets)]
  want_depth = config.scale_method == "pointmap"
  read = [
    read_kubric_view(
      scene_dir / f"output_{cam:03d}.tar", [frame], load_depth=want_depth and v < num_context
    )
    for v, (cam, frame) in enumerate(picks)
  ]
  images = np.concatenate([r["images"] for r in read])
  c2w = np.concatenate([r["c2w"] for r in read])
  raw_intrinsics = np.concatenate([r["intrinsics"] for r in read])
  times = normalize_times(np.array([frame for _, frame in picks]))

  images, intrinsics = transforms.resize_and_center_crop(images, raw_intrinsics, config.image_shape)
  c2w = transforms.normalize_cameras(c2w, num_context, config.normalization)
  if config.scale_method == "pointmap":
    # official: on the full-resolution depth and intrinsics, with the normalised cameras
    depths = np.concatenate([r["depths"] for r in read[:num_context]])
    scale = config.base_scale / pointmap_scale(
      depths, c2w[:num_context], raw_intrinsics[:num_context], config.pointmap_trim
    )
  else:
    scale = transforms.translation_scale(c2w, num_context, config.base_scale, config.scale_method)
  if training and config.random_flip and rng.uniform() < 0.5:
    images, c2w, intrinsics = transforms.flip_horizontal(images, c2w, intrinsics)
  c2w = np.array(c2w, np.float32)
  c2w[:, :3, 3] *= scale
  images = images.astype(np.float32) / 255.0
  context, target = slice(0, num_context), slice(num_context, None)
  return {
    "context_images": images[context],
    "context_c2w": c2w[context],
    "context_intrinsics": intrinsics[context],
    "context_times": times[context],
    "target_images": images[target],
    "target_c2w": c2w[target],
    "target_intrinsics": intrinsics[target],
    "target_times": times[target],
    "scene_index": np.int64(scene_index),
  }


class KubricSource:
  """Random-access source of Kubric examples (`len`, `[index]`), usable as a grain data source.

  Example `i` draws its random choices from `np.random.default_rng([seed, epoch, i])`: the same
  example for the same (seed, epoch, i) in any worker or process, new choices each epoch.
  """

  def __init__(
    self,
    config: KubricConfig = KubricConfig(),
    *,
    seed: int = 0,
    epoch: int = 0,
    training: bool = True,
  ):
    self.config = config
    self.scenes = list_kubric_scenes(config.root, config.subsets)
    self.seed, self.epoch, self.training = seed, epoch, training

  def __len__(self) -> int:
    return len(self.scenes)

  def __getitem__(self, index: int) -> dict:
    rng = np.random.default_rng([self.seed, self.epoch, int(index)])
    return make_kubric_example(
      self.scenes[index], rng, self.config, training=self.training, scene_index=int(index)
    )

  def __repr__(self) -> str:
    return f"KubricSource({self.config.root!r}, scenes={len(self)}, epoch={self.epoch})"


# ----------------------------------------------------------------------------------------------
# Scene records for the generic input pipeline (`tokengs_jax.data.pipeline.InputPipeline`)


class _TarFrames:
  """Lazy length-(C*F) sequence of one per-frame tar member's bytes, camera-major: item c * F + f
  is camera c, frame f. `member` is a format string of the frame, e.g. "rgba_{:05d}.png".

  The pipeline decodes only the items it picks (PIL reads the PNGs, tifffile the depth TIFFs).
  """

  def __init__(self, scene_dir: pathlib.Path, num_cameras: int, num_frames: int, member: str):
    self.scene_dir, self.num_cameras, self.num_frames = scene_dir, num_cameras, num_frames
    self.member = member

  def __len__(self) -> int:
    return self.num_cameras * self.num_frames

  def __getitem__(self, index: int) -> bytes:
    if not 0 <= index < len(self):
      raise IndexError(f"{self.scene_dir}: view {index} of {len(self)}")
    camera, frame = divmod(int(index), self.num_frames)
    path = str(self.scene_dir / f"output_{camera:03d}.tar")
    with tarfile.open(path, "r") as tar:
      return _member(tar, self.member.format(frame), path)


class KubricSceneSource:
  """Random-access source of Kubric scene records in the pipeline's record contract.

  A scene's C cameras x F frames are flattened camera-major into C*F "frames": `c2w [C*F, 4, 4]`
  (OpenCV), `intrinsics [C*F, 4]`, lazy PNG `images`, and `times [C*F]` = the frame index (the
  pipeline min-max normalises times per example, as official), plus `num_cameras`, `num_frames`
  for `kubric_view_selector`. Only metadata is read up front; pixels are read per sample.

  `depths` (lazy TIFF bytes, same indexing) feed the pipeline's depth-based "pointmap" camera
  scale, which the official Kubric preset uses (`DATASET_PRESETS["kubric"]`).
  """

  def __init__(self, root: str | os.PathLike, subsets: Sequence[str] = DEFAULT_SUBSETS):
    self.scenes = list_kubric_scenes(root, subsets)

  def __len__(self) -> int:
    return len(self.scenes)

  def __getitem__(self, index: int) -> dict:
    scene_dir = self.scenes[index]
    views = sorted(scene_dir.glob("output_*.tar"))
    if not views:
      raise KubricError(f"{scene_dir}: no output_*.tar camera files")
    read = [
      read_kubric_view(scene_dir / f"output_{c:03d}.tar", load_images=False)
      for c in range(len(views))
    ]
    num_frames = read[0]["num_frames"]
    if any(
      r["num_frames"] != num_frames
      or (r["height"], r["width"]) != (read[0]["height"], read[0]["width"])
      for r in read
    ):
      raise KubricError(f"{scene_dir}: cameras differ in frame count or resolution")
    return {
      "key": scene_dir.name,
      "source": str(scene_dir),
      "c2w": np.concatenate([r["c2w"] for r in read]),
      "intrinsics": np.concatenate([r["intrinsics"] for r in read]),
      "height": read[0]["height"],
      "width": read[0]["width"],
      "images": _TarFrames(scene_dir, len(read), num_frames, "rgba_{:05d}.png"),
      "depths": _TarFrames(scene_dir, len(read), num_frames, "depth_{:05d}.tiff"),
      "times": np.tile(np.arange(num_frames, dtype=np.float64), len(read)),
      "num_cameras": len(read),
      "num_frames": num_frames,
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
