"""One Kubric camera's tar: its metadata (poses, intrinsics, in the official conventions) and frames.

`parse_kubric_view` reads a tar's index and `metadata.json` once into a `KubricView` (cameras and
each member's byte range) and refuses a tar that lacks any frame the metadata lists;
`read_kubric_view` decodes frames (PNG RGB, TIFF depth) checked against the metadata's
resolution. Every failure is a `KubricError` naming the file and, for a frame, the member
(`.../output_002.tar member ./rgba_00007.png`).

Depth: `depth_{frame:05d}.tiff` holds, as in real Kubric (its `z_to_depth`), the distance from the
camera centre to the surface along each pixel's ray, not the planar camera z
(`z_to_ray_depth`, `ray_depth_to_z`, `unproject_ray_depth` convert).

Motion truth (optional; the official loader reads neither): `segmentation_{frame:05d}.png`, an
8-bit palette PNG of object instance numbers (0 the background, k + 1 the metadata's instance k),
and the metadata's `instances[k]["positions"]` [F, 3] / `["quaternions"]` [F, 4] (wxyz), each
object's pose (object-to-world, in the cameras' world) at every frame, as Kubric writes them.
"""

from __future__ import annotations

import dataclasses
import json
import os
import tarfile
from typing import Sequence

import numpy as np

from tokengs_jax.data.chunks import ChunkError, check_regular_file
from tokengs_jax.data.chunks.images import check_frame_bytes, decode_image

# Blender/OpenGL camera axes (x right, y up, looking down -z) -> OpenCV (x right, y down, +z).
_GL_TO_CV = np.diag([1.0, -1.0, -1.0])
_MAX_METADATA_BYTES = 64 << 20


class KubricError(ValueError):
  """A Kubric scene is malformed; the message names the file."""


def check_finite_depth(depth: np.ndarray, where: str) -> None:
  """`KubricError` naming `where` unless every depth value is finite.

  Refused rather than masked: the official "pointmap" scale keeps an inf value (depth > 1e-8),
  which makes the scale and so every camera position NaN, and drops a NaN one, so that a NaN-only
  map silently gives the scale 1.0. The depth maps this reads (Kubric's renders, the synthetic
  writers') hold finite distances, so a non-finite one marks a damaged file.
  """
  non_finite = np.count_nonzero(~np.isfinite(depth))
  if non_finite:
    raise KubricError(f"{where}: {non_finite} of {np.size(depth)} depth values are NaN or inf")


def quat_wxyz_to_rotation(quats: np.ndarray) -> np.ndarray:
  """Quaternions (w, x, y, z), Hamilton convention -> rotation matrices.

  Each quaternion is normalised first (the official loader uses them as stored, so a stored
  length off 1 scales and shears its rotation; docs/deviations.md); one of length ~0 or not
  finite is refused (ValueError). quats: [..., 4] -> [..., 3, 3] float64.
  """
  quats = np.asarray(quats, np.float64)
  length = np.linalg.norm(quats, axis=-1, keepdims=True)
  if not np.all(np.isfinite(length) & (length > 1e-8)):
    raise ValueError("quaternion of zero or non-finite length")
  w, x, y, z = np.moveaxis(quats / length, -1, 0)
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


def pose_matrices(positions: np.ndarray, quats: np.ndarray) -> np.ndarray:
  """Kubric poses (position, wxyz rotation to the world) -> rigid 4x4 object-to-world matrices.

  positions: [..., 3], quats: [..., 4] -> [..., 4, 4] float64.
  """
  positions = np.asarray(positions, np.float64)
  poses = np.zeros(positions.shape[:-1] + (4, 4))
  poses[..., :3, :3] = quat_wxyz_to_rotation(quats)
  poses[..., :3, 3] = positions
  poses[..., 3, 3] = 1.0
  return poses


def kubric_pose_to_opencv(positions: np.ndarray, quats: np.ndarray) -> np.ndarray:
  """Kubric camera poses -> OpenCV c2w.  positions: [F, 3], quats: [F, 4] wxyz -> [F, 4, 4]."""
  c2w = pose_matrices(positions, quats)
  c2w[..., :3, :3] = c2w[..., :3, :3] @ _GL_TO_CV
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
    object_poses: [K, F, 4, 4] float64 object-to-world pose of each of the metadata's `instances`
      at every frame; None when the metadata has no `instances`.
  """

  path: str
  c2w: np.ndarray
  intrinsics: np.ndarray
  height: int
  width: int
  members: dict
  object_poses: np.ndarray | None = None

  @property
  def num_frames(self) -> int:
    return len(self.c2w)

  def where(self, name: str) -> str:
    """How errors name member `name` (without "./"): `<tar> member ./<name>`."""
    return f"{self.path} member ./{name}"

  def read(self, name: str) -> bytes:
    """The bytes of member `name`; `KubricError` if it is missing or the tar is truncated."""
    if name not in self.members:
      raise KubricError(f"{self.where(name)} is missing")
    offset, size = self.members[name]
    try:
      with open(self.path, "rb") as handle:
        handle.seek(offset)
        data = handle.read(size)
    except OSError as error:
      raise KubricError(f"{self.where(name)}: cannot read ({error})") from error
    if len(data) != size:
      raise KubricError(f"{self.where(name)} is truncated ({len(data)} of {size} bytes)")
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
    num_frames = meta["metadata"].get("num_frames", len(positions))
  except (KeyError, TypeError, ValueError, AttributeError) as error:  # JSON errors: ValueErrors
    raise KubricError(f"{path}: bad metadata.json ({type(error).__name__}: {error})") from error
  if positions.ndim != 2 or positions.shape[1] != 3 or quats.shape != (len(positions), 4):
    raise KubricError(
      f"{path}: camera positions {list(positions.shape)} / quaternions "
      f"{list(quats.shape)} must be [F, 3] / [F, 4]"
    )
  if not isinstance(num_frames, int) or num_frames != len(positions):
    raise KubricError(
      f"{path}: metadata.json num_frames {num_frames!r} is not the {len(positions)} camera poses"
    )
  if not (np.isfinite(positions).all() and np.isfinite(quats).all()):
    raise KubricError(f"{path}: NaN/inf in the camera poses")
  try:
    intrinsics = intrinsics_from_metadata(focal, sensor, height, width)
  except KubricError as error:
    raise KubricError(f"{path}: metadata.json {error}") from None
  _check_every_frame_is_present(view, num_frames)
  c2w = kubric_pose_to_opencv(positions, quats).astype(np.float32)
  return dataclasses.replace(
    view,
    c2w=c2w,
    intrinsics=intrinsics,
    height=height,
    width=width,
    object_poses=_object_poses(meta, num_frames, path),
  )


def _object_poses(meta: dict, num_frames: int, path: str) -> np.ndarray | None:
  """The metadata's `instances` as object-to-world poses [K, F, 4, 4] (None without the key);
  `KubricError` unless every instance has finite `positions` [F, 3] and `quaternions` [F, 4]."""
  if "instances" not in meta:
    return None
  try:
    instances = [
      (np.asarray(i["positions"], np.float64), np.asarray(i["quaternions"], np.float64))
      for i in meta["instances"]
    ]
  except (KeyError, TypeError, ValueError) as error:  # ragged lists are ValueErrors
    raise KubricError(
      f"{path}: bad metadata.json instances ({type(error).__name__}: {error})"
    ) from error
  poses = []
  for k, (positions, quats) in enumerate(instances):
    if positions.shape != (num_frames, 3) or quats.shape != (num_frames, 4):
      raise KubricError(
        f"{path}: metadata.json instance {k} positions {list(positions.shape)} / quaternions "
        f"{list(quats.shape)} must be [{num_frames}, 3] / [{num_frames}, 4]"
      )
    if not (np.isfinite(positions).all() and np.isfinite(quats).all()):
      raise KubricError(f"{path}: metadata.json instance {k}: NaN/inf in its poses")
    poses.append(pose_matrices(positions, quats))
  return np.stack(poses) if poses else np.zeros((0, num_frames, 4, 4))


def _check_every_frame_is_present(view: KubricView, num_frames: int) -> None:
  """`KubricError` unless the tar holds an RGBA PNG for every frame the metadata lists, and a depth
  TIFF (a segmentation PNG) for every frame when it holds any (both are optional, a partial set
  is not).

  A tar cut exactly at a member boundary reads as a valid, shorter tar; without this check the
  scene would still give every example that avoids its missing frames.
  """
  optional = [
    pattern
    for pattern in ("depth_{:05d}.tiff", "segmentation_{:05d}.png")
    if any(name.startswith(pattern.split("{")[0]) for name in view.members)
  ]
  for pattern in ["rgba_{:05d}.png", *optional]:
    missing = [f for f in range(num_frames) if pattern.format(f) not in view.members]
    if missing:
      raise KubricError(
        f"{view.where(pattern.format(missing[0]))} is missing: metadata.json lists {num_frames} "
        f"frames and {len(missing)} of them are absent (a truncated tar?)"
      )


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
    when `load_images`; `depths` float32 [F, H, W] (distance along each pixel's ray, as stored)
    when `load_depth`.
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
    images = [decode_member(view, f"rgba_{f:05d}.png", shape) for f in frames]
    result["images"] = np.stack(images) if images else np.zeros((0, *shape, 3), np.uint8)
  if load_depth:
    depths = [decode_member(view, f"depth_{f:05d}.tiff", shape) for f in frames]
    result["depths"] = np.stack(depths) if depths else np.zeros((0, *shape), np.float32)
  return result


def decode_member(
  view: KubricView, name: str, shape: tuple[int, int], *, alpha: bool = False
) -> np.ndarray:
  """Member `name` as uint8 [H, W, 3] RGB (`rgba_*.png`, alpha dropped as official; with
  `alpha`, its alpha channel instead, uint8 [H, W]: the foreground mask), float32 [H, W] depth
  (`depth_*.tiff`, read with PIL as official) or int32 [H, W] instance numbers
  (`segmentation_*.png`, the palette indices), whose size must be `shape` (the metadata's
  resolution: the intrinsics are derived from it). Every failure is a `KubricError` naming tar
  and member."""
  segmentation = name.startswith("segmentation_")
  where = view.where(name)
  if name in view.members:  # a missing one is named by `view.read`
    check_frame_bytes(view.members[name][1], where=where, error=KubricError)
  mode = ("RGBA" if alpha else "RGB") if name.endswith(".png") and not segmentation else None
  pixels = decode_image(view.read(name), where=where, error=KubricError, mode=mode)
  if alpha:
    pixels = pixels[..., 3]
  if segmentation:
    pixels = pixels.astype(np.int32)
  elif name.endswith(".tiff"):
    pixels = pixels.astype(np.float32)
  if segmentation and pixels.ndim != 2:
    raise KubricError(
      f"{where}: a segmentation holds one instance number per pixel, found {list(pixels.shape)}"
    )
  pixels = pixels[..., 0] if name.endswith(".tiff") and pixels.ndim == 3 else pixels
  if pixels.shape[:2] != shape:
    raise KubricError(
      f"{where} is {list(pixels.shape[:2])}, metadata.json resolution "
      f"is {list(shape)} (the intrinsics would be wrong)"
    )
  if name.endswith(".tiff"):
    check_finite_depth(pixels, where)
  return pixels


def _pixel_rays(intrinsics: np.ndarray, height: int, width: int) -> np.ndarray:
  """Camera-space (OpenCV) rays through the pixel centres, with z = 1.  -> [H, W, 3] float64."""
  fx, fy, cx, cy = np.asarray(intrinsics, np.float64)
  rows, cols = np.mgrid[0:height, 0:width] + 0.5
  return np.stack([(cols - cx) / fx, (rows - cy) / fy, np.ones_like(cols)], -1)


def z_to_ray_depth(z: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
  """Planar camera z -> distance from the camera centre along each pixel-centre ray (what Kubric's
  `z_to_depth` stores in `depth_*.tiff`).  z: [..., H, W], intrinsics: [4] pixels -> float32."""
  z = np.asarray(z)
  rays = _pixel_rays(intrinsics, *z.shape[-2:])
  return (z * np.linalg.norm(rays, axis=-1)).astype(np.float32)


def ray_depth_to_z(depth: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
  """Inverse of `z_to_ray_depth`.  depth: [..., H, W], intrinsics: [4] pixels -> float32."""
  depth = np.asarray(depth)
  rays = _pixel_rays(intrinsics, *depth.shape[-2:])
  return (depth / np.linalg.norm(rays, axis=-1)).astype(np.float32)


def unproject_ray_depth(depth: np.ndarray, c2w: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
  """World points a Kubric depth map sees: camera centre + depth x unit ray through the pixel
  centre (pixels with depth 0 saw nothing and map to the centre).

  depth: [H, W] ray distance, c2w: [4, 4] OpenCV, intrinsics: [4] pixels -> [H, W, 3] float64.
  """
  rays = _pixel_rays(intrinsics, *np.shape(depth))
  rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
  pose = np.asarray(c2w, np.float64)
  return (np.asarray(depth, np.float64)[..., None] * rays) @ pose[:3, :3].T + pose[:3, 3]
