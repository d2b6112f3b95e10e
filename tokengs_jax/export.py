"""Outputs a person looks at: PLY for 3DGS viewers, PNG grids, depth colouring, MP4 fly-throughs.

Everything here is host-side numpy (it runs after the jitted work, on fetched arrays).
"""

from __future__ import annotations

import pathlib
from typing import Sequence

import numpy as np
from PIL import Image

# Zeroth-order real spherical harmonic; 3DGS viewers decode colour = 0.5 + SH_C0 * f_dc.
SH_C0 = 0.28209479177387814
_PLY_FIELDS = (
  ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
  + [f"scale_{i}" for i in range(3)]
  + [f"rot_{i}" for i in range(4)]
)
# The official `save_ply` leaves out the Gaussians below this opacity (the results folders' PLYs).
OFFICIAL_MIN_OPACITY = 0.005


def _logit(p: np.ndarray, eps: float = 1e-6) -> np.ndarray:
  p = np.clip(p, eps, 1.0 - eps)
  return np.log(p) - np.log1p(-p)


def write_ply(
  path,
  means,
  opacities,
  scales,
  quats,
  colors,
  min_opacity: float = 0.0,
  cameras: dict | None = None,
) -> pathlib.Path:
  """Writes Gaussians in the binary PLY layout of the reference 3DGS code (and its viewers).

  Viewers store pre-activation values, so opacity goes out as a logit, scales as logs, colour as
  the SH DC coefficient, and quaternions (wxyz) normalised.

  means: [N, 3], opacities: [N], scales: [N, 3] (linear), quats: [N, 4] wxyz, colors: [N, 3] in [0, 1].
  min_opacity: the Gaussians of opacity below it are left out, those of exactly it kept (the
    official `save_ply` drops opacity < `OFFICIAL_MIN_OPACITY`); 0 keeps every one. A NaN
    opacity is never left out: it is refused with the other non-finite values.
  cameras: None (default) keeps what no camera sees; else also leaves out the Gaussians that no
    given camera can draw, by the renderer's own culling rule (`splatting.compaction.drawable`,
    conservative: nothing a render of these cameras shows is dropped). A dict with
    "world_to_camera" [V, 4, 4], "intrinsics" [V, 4] (pixels), "height", "width" and optionally
    "near", "far" (the renderer's defaults otherwise).
  """
  means, scales, quats, colors = (np.asarray(a, np.float32) for a in (means, scales, quats, colors))
  opacities = np.asarray(opacities, np.float32).reshape(-1, 1)
  kept = ~(opacities[:, 0] < np.float32(min_opacity))
  if cameras is not None:  # a non-finite Gaussian stays, to be refused below, not dropped
    fields = np.concatenate([means, opacities, scales, quats, colors], axis=-1)
    finite = np.all(np.isfinite(fields), axis=-1)
    kept &= _seen(means, opacities[:, 0], scales, quats, colors, cameras) | ~finite
  means, opacities, scales, quats, colors = (
    a[kept] for a in (means, opacities, scales, quats, colors)
  )
  norm = np.linalg.norm(quats, axis=-1, keepdims=True)
  quats = np.where(norm > 0, quats / np.maximum(norm, 1e-12), np.array([1, 0, 0, 0], np.float32))
  table = np.concatenate(
    [
      means,
      np.zeros_like(means),
      (colors - 0.5) / SH_C0,
      _logit(opacities),
      np.log(np.maximum(scales, 1e-12)),
      quats,
    ],
    axis=-1,
  ).astype("<f4")
  if not np.all(np.isfinite(table)):
    raise ValueError(f"refusing to write non-finite Gaussians to {path}")
  header = (
    "\n".join(
      ["ply", "format binary_little_endian 1.0", f"element vertex {len(table)}"]
      + [f"property float {name}" for name in _PLY_FIELDS]
      + ["end_header"]
    )
    + "\n"
  )
  path = pathlib.Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  with open(path, "wb") as f:
    f.write(header.encode("ascii"))
    f.write(table.tobytes())
  return path


def _seen(means, opacities, scales, quats, colors, cameras: dict) -> np.ndarray:
  """[N] bool: some camera of `cameras` (`write_ply`) may draw the Gaussian (jax, imported here
  so that the rest of this module stays numpy)."""
  from tokengs_jax.gaussians import Gaussians
  from tokengs_jax.splatting import compaction

  gaussians = Gaussians(means=means, opacities=opacities, scales=scales, quats=quats, colors=colors)
  limits = {k: cameras[k] for k in ("near", "far") if k in cameras}
  keep = compaction.drawable(
    gaussians,
    np.asarray(cameras["world_to_camera"], np.float32),
    np.asarray(cameras["intrinsics"], np.float32),
    height=int(cameras["height"]),
    width=int(cameras["width"]),
    **limits,
  )
  return np.asarray(keep)


# PLY scalar types -> numpy (both the spec's names and the sized aliases).
_PLY_TYPES = {
  "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
  "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
  "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_PLY_FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": None}


def _ply_header(path: pathlib.Path, data: bytes) -> tuple[str, int, list[tuple[str, str]], int]:
  """(format, vertex count, vertex properties as (name, numpy type), where the body starts) of a
  PLY whose only element is "vertex" with scalar properties; ValueError naming the file if not."""
  end = data.find(b"end_header")
  if not data.startswith(b"ply") or end < 0:
    raise ValueError(f"{path}: not a PLY file (no 'ply' magic or no 'end_header')")
  try:
    lines = data[:end].decode("ascii").splitlines()
  except UnicodeDecodeError:
    raise ValueError(f"{path}: PLY header is not ASCII") from None
  fmt, count, properties, elements = None, None, [], []
  for line in lines[1:]:
    words = line.split()
    if not words or words[0] in ("comment", "obj_info"):
      continue
    if words[0] == "format" and len(words) == 3 and words[1] in _PLY_FORMATS:
      fmt = words[1]
    elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
      elements.append(words[1])
      count = int(words[2]) if words[1] == "vertex" else count
    elif words[0] == "property" and len(words) == 3 and words[1] in _PLY_TYPES:
      if elements == ["vertex"]:
        properties.append((words[2], _PLY_TYPES[words[1]]))
    else:
      raise ValueError(f"{path}: unsupported PLY header line {line!r}")
  if fmt is None or elements != ["vertex"] or count is None:
    raise ValueError(f"{path}: needs a format line and exactly one element, 'vertex'")
  newline = data.find(b"\n", end)
  return fmt, count, properties, (len(data) if newline < 0 else newline + 1)


def read_ply(path) -> dict[str, np.ndarray]:
  """Reads a 3DGS PLY (as `write_ply` writes, or another writer's: any property order, types,
  endianness or ASCII) back into activated values, as float32.

  Returns dict with means [N,3], opacities [N], scales [N,3], quats [N,4], colors [N,3].
  Raises ValueError naming the file for a header it cannot honour, missing properties, or a body
  of the wrong length.
  """
  path = pathlib.Path(path)
  data = path.read_bytes()
  fmt, count, properties, start = _ply_header(path, data)
  # normals (nx, ny, nz) are written as zeros by 3DGS tools and not read
  needed = [name for name in _PLY_FIELDS if name not in ("nx", "ny", "nz")]
  missing = [name for name in needed if name not in dict(properties)]
  if missing:
    raise ValueError(f"{path}: PLY lacks the Gaussian properties {missing}")
  order = _PLY_FORMATS[fmt]
  if order is None:
    rows = data[start:].decode("ascii", errors="replace").split("\n")[:count]
    try:
      table = np.array([[float(v) for v in row.split()] for row in rows], np.float64)
    except ValueError:
      raise ValueError(f"{path}: unreadable ASCII PLY body") from None
    if table.shape != (count, len(properties)):
      raise ValueError(f"{path}: ASCII body is not {count} rows of {len(properties)} values")
    col = {name: table[:, i] for i, (name, _) in enumerate(properties)}
  else:
    record = np.dtype([(name, order + kind) for name, kind in properties])
    if len(data) - start != count * record.itemsize:
      raise ValueError(f"{path}: body holds {len(data) - start} bytes, not {count} vertices")
    table = np.frombuffer(data, record, count, start)
    col = {name: table[name] for name, _ in properties}
  stack = lambda keys: np.stack([np.asarray(col[k], np.float32) for k in keys], axis=-1)
  return {
    "means": stack(["x", "y", "z"]),
    "opacities": 1.0 / (1.0 + np.exp(-np.asarray(col["opacity"], np.float32))),
    "scales": np.exp(stack([f"scale_{i}" for i in range(3)])),
    "quats": stack([f"rot_{i}" for i in range(4)]),
    "colors": 0.5 + SH_C0 * stack(["f_dc_0", "f_dc_1", "f_dc_2"]),
  }


def to_uint8(image) -> np.ndarray:
  """[..., 3] floats in [0, 1] -> uint8 (non-finite values become 0); uint8 as it is."""
  image = np.asarray(image)
  if image.dtype == np.uint8:
    return image
  image = np.nan_to_num(image.astype(np.float32), nan=0.0, posinf=1.0, neginf=0.0)
  return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def _valid_depth(depth, alpha) -> np.ndarray:
  valid = np.isfinite(depth) & (depth > 0)
  if alpha is not None:
    valid &= np.asarray(alpha).reshape(depth.shape) >= 0.5
  return valid


def inverse_depth_range(depths, alphas=None) -> tuple[float, float] | None:
  """Robust (2nd, 98th percentile) range of 1 / depth over rendered pixels (alpha >= 0.5) of
  one or more depth maps, as `colorize_depth` maps it; None when nothing was rendered."""
  alphas = [None] * len(depths) if alphas is None else alphas
  values = []
  for depth, alpha in zip(depths, alphas):
    depth = np.asarray(depth, np.float32).reshape(np.shape(depth)[:2])
    values.append(1.0 / depth[_valid_depth(depth, alpha)])
  values = np.concatenate(values) if values else np.zeros(0)
  if not values.size:
    return None
  lo, hi = np.percentile(values, [2, 98])
  return float(lo), float(hi)


def depth_ramp(t) -> np.ndarray:
  """The depth colour map: t [...] in [0, 1] (1 = near) -> [..., 3]; readable without matplotlib."""
  t = np.asarray(t, np.float32)
  return np.stack([t**1.5, np.sqrt(t) * 0.9, 0.6 * (1.0 - t) + 0.1], axis=-1)


def colorize_depth(
  depth, alpha=None, inverse_range: tuple[float, float] | None = None
) -> np.ndarray:
  """Depth [H, W] or [H, W, 1] -> [H, W, 3] in [0, 1], near = bright (`depth_ramp`).

  inverse_range: (lo, hi) of 1 / depth mapped to the ends of the ramp (several maps on one scale);
  default this map's `inverse_depth_range`. Pixels with alpha < 0.5 (nothing rendered) are black.
  """
  depth = np.asarray(depth, np.float32).reshape(np.shape(depth)[:2])
  valid = _valid_depth(depth, alpha)
  inverse_range = inverse_range or inverse_depth_range([depth], [alpha])
  if not valid.any() or inverse_range is None:
    return np.zeros(depth.shape + (3,), np.float32)
  lo, hi = inverse_range
  inv = np.where(valid, 1.0 / np.where(valid, depth, 1.0), 0.0)
  t = np.clip((inv - lo) / max(hi - lo, 1e-8), 0.0, 1.0)
  return np.where(valid[..., None], depth_ramp(t), 0.0)


def image_grid(rows: Sequence[Sequence[np.ndarray]], pad: int = 2) -> np.ndarray:
  """Tiles images ([H, W, 3] floats in [0, 1], any sizes) row by row on a white canvas -> uint8."""
  rows = [[to_uint8(img) for img in row] for row in rows if len(row)]
  heights = [max(img.shape[0] for img in row) for row in rows]
  width = max(sum(img.shape[1] for img in row) + pad * (len(row) + 1) for row in rows)
  canvas = np.full((sum(heights) + pad * (len(rows) + 1), width, 3), 255, np.uint8)
  y = pad
  for row, h in zip(rows, heights):
    x = pad
    for img in row:
      canvas[y : y + img.shape[0], x : x + img.shape[1]] = img
      x += img.shape[1] + pad
    y += h + pad
  return canvas


def save_png(path, image) -> pathlib.Path:
  """Writes a uint8 [H, W, 3] array (or floats in [0, 1]) as PNG."""
  path = pathlib.Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  Image.fromarray(to_uint8(image)).save(path)
  return path


def write_mp4(path, frames: Sequence[np.ndarray], fps: int = 24) -> pathlib.Path:
  """Encodes frames ([H, W, 3] floats in [0, 1] or uint8, all one size) as H.264 MP4 with the
  ffmpeg binary of the `imageio-ffmpeg` wheel.

  Sizes are padded to even numbers, which yuv420p requires. The encoder is started with
  `posix_spawn`, not a fork: a fork of a process running JAX's threads can deadlock (and JAX warns
  that it may). Raises RuntimeError with ffmpeg's message if it fails.
  """
  import subprocess
  import tempfile

  import imageio_ffmpeg

  path = pathlib.Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  frames = [to_uint8(frame) for frame in frames]
  if not frames:
    raise ValueError(f"{path}: no frames to encode")
  h, w = frames[0].shape[:2]
  command = [
    imageio_ffmpeg.get_ffmpeg_exe(),  # an absolute path, which posix_spawn needs
    "-loglevel", "error", "-y", "-f", "rawvideo", "-pix_fmt", "rgb24",
    "-s", f"{w + w % 2}x{h + h % 2}", "-r", str(fps), "-i", "-",
    "-an", "-vcodec", "libx264", "-pix_fmt", "yuv420p", str(path),
  ]  # fmt: skip
  with tempfile.TemporaryFile() as log:
    # close_fds=False and no cwd / preexec_fn: the conditions under which subprocess spawns
    encoder = subprocess.Popen(
      command, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=log, close_fds=False
    )
    with encoder.stdin:
      for frame in frames:
        if frame.shape[:2] != (h, w):
          encoder.kill()
          raise ValueError(f"{path}: frames of sizes {(h, w)} and {frame.shape[:2]}")
        even = np.pad(frame[..., :3], ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
        encoder.stdin.write(np.ascontiguousarray(even).tobytes())
    if encoder.wait() != 0:
      log.seek(0)
      message = log.read().decode(errors="replace").strip()
      raise RuntimeError(f"ffmpeg could not write {path}: {message}")
  return path


def _slerp_rotation(r0: np.ndarray, r1: np.ndarray, t: float) -> np.ndarray:
  """Geodesic interpolation between two rotation matrices (axis-angle of r0^T r1)."""
  rel = r0.T @ r1
  angle = np.arccos(np.clip((np.trace(rel) - 1.0) / 2.0, -1.0, 1.0))
  if angle < 1e-8:
    return r0
  axis = np.array([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]])
  axis = axis / max(np.linalg.norm(axis), 1e-12)
  k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
  a = t * angle
  return r0 @ (np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k)


def fly_through_poses(c2w: np.ndarray, num_frames: int) -> np.ndarray:
  """Camera path through the given keyframe poses, in order (piecewise slerp + lerp).

  c2w: [K, 4, 4] camera-to-world keyframes -> [num_frames, 4, 4].
  """
  c2w = np.asarray(c2w, np.float64)
  if len(c2w) == 1:
    return np.repeat(c2w, num_frames, axis=0)
  out = []
  for s in np.linspace(0.0, len(c2w) - 1.0, num_frames):
    i = min(int(s), len(c2w) - 2)
    t = s - i
    pose = np.eye(4)
    pose[:3, :3] = _slerp_rotation(c2w[i, :3, :3], c2w[i + 1, :3, :3], t)
    pose[:3, 3] = (1 - t) * c2w[i, :3, 3] + t * c2w[i + 1, :3, 3]
    out.append(pose)
  return np.stack(out).astype(np.float32)
