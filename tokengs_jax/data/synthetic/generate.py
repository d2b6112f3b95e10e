"""Writers of synthetic datasets in the real on-disk formats, so the real loaders read them.

- `generate_re10k_like`: static rooms + RE10K-like walks -> pixelSplat chunks
  `{train,test}/NNNNNN.torch` (JPEG frames, normalised intrinsics, w2c rows) + `index.json`.
- The held-out static test families (galleries, the frozen courtyards): `held_out`.
- `generate_kubric_like`: dynamic scenes seen by a 9-camera rig -> the Kubric-4D layout
  `<root>/<subset>/<scene>/output_{view:03d}.tar`, each tar holding `metadata.json`,
  `rgba_{frame:05d}.png`, `depth_{frame:05d}.tiff` (float32 distance along each pixel's ray,
  as Kubric's) and `segmentation_{frame:05d}.png` (palette PNG of object instance numbers, 0 the
  background, as Kubric's), the metadata listing every object's pose at every frame
  (`instances[k]["positions"]`, `["quaternions"]`, as Kubric's): the generator's motion truth.

Every scene is a pure function of (seed, split, index): `np.random.default_rng([seed, split_id,
index])`. That makes generation deterministic, lets scenes be generated in any order or in
parallel, and lets a test regenerate a single scene to compare with what was written.
"""

from __future__ import annotations

import colorsys
import concurrent.futures
import dataclasses
import functools
import io
import json
import os
import pathlib
import tarfile
from typing import Sequence

import numpy as np
import tifffile
from PIL import Image

from tokengs_jax.data import chunks, kubric
from tokengs_jax.data.synthetic import cameras, scenes, varied
from tokengs_jax.data.synthetic.raytrace import render

_SPLIT_IDS = {"train": 0, "test": 1}
RE10K_FPS = 30  # RE10K timestamps are microseconds of the source video


@dataclasses.dataclass(frozen=True)
class Re10kLikeConfig:
  """Options of `generate_re10k_like` beyond the sizes."""

  fov_x_degrees: tuple[float, float] = (55.0, 75.0)  # sampled per scene (all frames share it)
  supersample: int = 2  # sub-pixel samples per axis (anti-aliasing, as downscaled video has)
  jpeg_quality: int = 95
  scenes_per_chunk: int = 16
  room: scenes.RoomConfig | varied.VariedRoomConfig = scenes.RoomConfig()  # the scene family


def scene_rng(seed: int, split: str, index: int) -> np.random.Generator:
  """The generator from which scene `index` of `split` is drawn."""
  return np.random.default_rng([seed, _SPLIT_IDS[split], index])


def scene_key(seed: int, split: str, index: int) -> str:
  return f"synthetic{seed}_{split}_{index:06d}"


def render_re10k_like_scene(
  seed: int,
  split: str,
  index: int,
  height: int,
  width: int,
  frames: int,
  config: Re10kLikeConfig = Re10kLikeConfig(),
) -> dict:
  """One scene as `write_chunk` takes it: `key`, `url`, `timestamps [F]`, `c2w [F, 4, 4]`,
  `intrinsics [F, 4]` (pixels) and `images` uint8 [F, H, W, 3], plus `depths` [F, H, W] (not
  written to chunks; for checks)."""
  rng = scene_rng(seed, split, index)
  if isinstance(config.room, varied.VariedRoomConfig):
    scene, c2w = varied.sample_varied_room(rng, frames, config.room)
  else:
    scene, c2w = scenes.sample_room_scene(rng, frames, config.room)
  fov_x = np.deg2rad(rng.uniform(*config.fov_x_degrees))
  intrinsics = cameras.pinhole_intrinsics(height, width, fov_x)
  outputs = [render(scene, pose, intrinsics, height, width, config.supersample) for pose in c2w]
  images = np.stack([np.round(o.rgb * 255.0).astype(np.uint8) for o in outputs])
  return {
    "key": scene_key(seed, split, index),
    "url": "",
    "timestamps": np.arange(frames, dtype=np.int64) * (1_000_000 // RE10K_FPS),
    "c2w": c2w.astype(np.float32),
    "intrinsics": np.broadcast_to(intrinsics, (frames, 4)).astype(np.float32),
    "images": images,
    "depths": np.stack([o.depth for o in outputs]),
  }


def _write_chunk(path: str, indices: Sequence[int], render_scene, jpeg_quality: int) -> list[str]:
  """Renders scenes `indices` (`render_scene(index)` -> a scene as `write_chunk` takes it) into
  one chunk, with their true depths beside it.  -> their keys."""
  rendered = [render_scene(i) for i in indices]
  chunks.write_chunk(path, rendered, jpeg_quality=jpeg_quality)
  write_true_depths(path, rendered)
  return [scene["key"] for scene in rendered]


def write_chunked_split(
  directory: str | os.PathLike,
  count: int,
  render_scene,
  *,
  scenes_per_chunk: int,
  jpeg_quality: int,
  workers: int,
) -> dict:
  """Writes scenes 0..count-1 of a split as `<directory>/NNNNNN.torch` chunks of
  `scenes_per_chunk` scenes (+ `.depth.npz`) and `index.json` (scene key -> chunk file name, as
  pixelSplat's).

  render_scene: index -> scene (picklable: it runs in the worker processes).
  Returns the index.
  """
  directory = pathlib.Path(directory)
  directory.mkdir(parents=True, exist_ok=True)
  groups = [
    list(range(start, min(start + scenes_per_chunk, count)))
    for start in range(0, count, scenes_per_chunk)
  ]
  names = [f"{number:06d}.torch" for number in range(len(groups))]
  jobs = [
    (str(directory / name), group, render_scene, jpeg_quality) for name, group in zip(names, groups)
  ]
  keys = _run_jobs(_write_chunk, jobs, workers)
  index = {key: name for name, chunk_keys in zip(names, keys) for key in chunk_keys}
  (directory / "index.json").write_text(json.dumps(index, indent=1))
  return index


def true_depths_path(chunk_path: str | os.PathLike) -> pathlib.Path:
  """Where a chunk's true depth maps are kept: `NNNNNN.torch` -> `NNNNNN.depth.npz`."""
  chunk_path = pathlib.Path(chunk_path)
  return chunk_path.with_name(chunk_path.name.removesuffix(".torch") + ".depth.npz")


def write_true_depths(chunk_path: str | os.PathLike, rendered: Sequence[dict]) -> None:
  """Writes the planar z-depth maps of a chunk's scenes beside it (`true_depths_path`): `keys`
  [S] and `depths` float16 [S, F, H, W] (0 where a pixel saw nothing). The evaluation's geometry
  scores and the optional depth loss read them; the pixelSplat chunk format has no depth field."""
  np.savez(
    true_depths_path(chunk_path),
    keys=np.array([scene["key"] for scene in rendered]),
    depths=np.stack([scene["depths"] for scene in rendered]).astype(np.float16),
  )


def read_true_depths(chunk_path: str | os.PathLike, key: str) -> np.ndarray | None:
  """The true depth maps float32 [F, H, W] of scene `key` of a chunk, None where the chunk has
  none recorded (real data, training splits)."""
  path = true_depths_path(chunk_path)
  if not path.exists():
    return None
  keys, depths = _load_true_depths(str(path))
  positions = np.flatnonzero(keys == key)
  return depths[positions[0]].astype(np.float32) if len(positions) else None


@functools.lru_cache(maxsize=64)
def _load_true_depths(path: str) -> tuple[np.ndarray, np.ndarray]:
  """A chunk's depth file, read once per process (training reads it once per example)."""
  with np.load(path) as stored:
    return stored["keys"], stored["depths"]


def _run_jobs(function, jobs: list[tuple], workers: int) -> list:
  """Runs `function(*job)` for every job, in worker processes when `workers > 1`."""
  if workers <= 1:
    return [function(*job) for job in jobs]
  with concurrent.futures.ProcessPoolExecutor(workers) as pool:
    return list(pool.map(function, *zip(*jobs)))


def generate_re10k_like(
  root: str | os.PathLike,
  num_train: int,
  num_test: int,
  height: int = 64,
  width: int = 64,
  frames: int = 32,
  seed: int = 0,
  *,
  config: Re10kLikeConfig = Re10kLikeConfig(),
  workers: int = 1,
) -> dict:
  """Writes an RE10K-format dataset of synthetic rooms.

  Layout: `<root>/{train,test}/NNNNNN.torch` chunks of `config.scenes_per_chunk` scenes and, per
  split, `index.json` mapping each scene key to its chunk file name (as pixelSplat's).

  Returns:
    {split: {key: chunk file name}}, the contents of the index files.
  """
  sizes = dict(height=height, width=width, frames=frames, config=config)
  return {
    split: write_chunked_split(
      pathlib.Path(root) / split,
      count,
      functools.partial(render_re10k_like_scene, seed, split, **sizes),
      scenes_per_chunk=config.scenes_per_chunk,
      jpeg_quality=config.jpeg_quality,
      workers=workers,
    )
    for split, count in (("train", num_train), ("test", num_test))
  }


# ----------------------------------------------------------------------------------------------
# Kubric-like dynamic scenes


@dataclasses.dataclass(frozen=True)
class KubricLikeConfig:
  """Options of `generate_kubric_like` (defaults: Kubric's 35 mm lens on a 32 mm sensor)."""

  focal_length: float = 35.0
  sensor_width: float = 32.0
  supersample: int = 2
  camera_drift: float = 0.15  # radians each camera orbits over the sequence
  dynamic: scenes.DynamicConfig = scenes.DynamicConfig()


def render_kubric_like_scene(
  seed: int,
  index: int,
  height: int,
  width: int,
  frames: int,
  num_cameras: int,
  config: KubricLikeConfig = KubricLikeConfig(),
) -> dict:
  """Renders one dynamic scene from every camera at every frame.

  Returns:
    dict with `images` uint8 [C, F, H, W, 3], `depths` float32 [C, F, H, W] (distance from the
    camera centre along each pixel-centre ray, Kubric's convention; 0 where nothing was hit),
    `segmentations` uint8 [C, F, H, W] (object instance k + 1 per pixel, 0 the background),
    `c2w` [C, F, 4, 4] (OpenCV), `intrinsics` [4] (pixels, the values the Kubric reader derives
    from the metadata) and `metadata` [C] (the per-camera `metadata.json` dicts, with every
    object's poses).
  """
  rng = scene_rng(seed, "train", index)
  dynamic = scenes.sample_dynamic_scene(rng, config.dynamic)
  c2w = cameras.orbit_cameras(
    rng, num_cameras, frames, target=np.array([0.0, 0.5, 0.0]), drift=config.camera_drift
  )
  intrinsics = kubric.intrinsics_from_metadata(
    config.focal_length, config.sensor_width, height, width
  )
  images, depths, segmentations, metadata = render_kubric_views(
    dynamic.at,
    functools.partial(_object_poses, dynamic.at),
    c2w,
    np.broadcast_to(intrinsics, (num_cameras, 4)),
    np.full(num_cameras, config.focal_length),
    config.sensor_width,
    config.dynamic.frame_rate,
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


def _object_poses(scene_at, time: float) -> tuple[np.ndarray, np.ndarray]:
  """The poses of a scene whose every object is one rigid primitive with a rotation (as the
  Kubric-like scenes'): (rotations [K, 3, 3] object-to-world, positions [K, 3]) of
  `scene_at(time)`'s objects."""
  objects = scene_at(time).objects
  return (
    np.asarray([o.rotation for o in objects], np.float64).reshape(-1, 3, 3),
    np.asarray([o.center for o in objects], np.float64).reshape(-1, 3),
  )


def render_kubric_views(
  scene_at,
  poses_at,
  c2w,
  intrinsics,
  focal_lengths,
  sensor_width: float,
  frame_rate: float,
  height: int,
  width: int,
  supersample: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict]]:
  """A dynamic scene from every camera at every frame, in Kubric's conventions.

  Args:
    scene_at: time (seconds) -> the static `Scene` at that time.
    poses_at: time (seconds) -> (rotations [K, 3, 3] object-to-world, positions [K, 3]) of the
      scene's K object instances (`Scene.instances`) at that time.
    c2w: [C, F, 4, 4] OpenCV; intrinsics: [C, 4] pixels (as the Kubric reader derives them from
      `focal_lengths` [C] mm and `sensor_width` mm); frame_rate: frames per second.

  Returns:
    images uint8 [C, F, H, W, 3]; depths float32 [C, F, H, W], the distance along each
    pixel-centre ray (Kubric's `z_to_depth`; 0 where nothing was hit); segmentations uint8
    [C, F, H, W] (`Scene.segmentation` at the pixel centres); metadata [C], each camera's
    `metadata.json`, with `instances` [K] (each `positions` [F, 3] and wxyz `quaternions`
    [F, 4] of its object-to-world pose, as Kubric's object metadata).
  """
  num_cameras, frames = c2w.shape[:2]
  images = np.zeros((num_cameras, frames, height, width, 3), np.uint8)
  depths = np.zeros((num_cameras, frames, height, width), np.float32)
  segmentations = np.zeros((num_cameras, frames, height, width), np.uint8)
  object_rotations, object_positions = [], []
  for frame in range(frames):
    scene = scene_at(frame / frame_rate)
    for camera in range(num_cameras):
      output = render(scene, c2w[camera, frame], intrinsics[camera], height, width, supersample)
      images[camera, frame] = np.round(output.rgb * 255.0)
      # The tracer gives planar z; real Kubric's depth_*.tiff holds the ray distance.
      depths[camera, frame] = kubric.z_to_ray_depth(output.depth, intrinsics[camera])
      segmentations[camera, frame] = scene.segmentation(output.ids)
    rotation, position = poses_at(frame / frame_rate)
    object_rotations.append(rotation)
    object_positions.append(position)
  instances = [
    {"positions": p.tolist(), "quaternions": q.tolist()}
    for p, q in zip(
      np.stack(object_positions, 1),  # [K, F, 3]
      kubric.rotation_to_quat_wxyz(np.stack(object_rotations, 1)),  # [K, F, 4]
    )
  ]
  metadata = []
  for camera in range(num_cameras):
    positions, quaternions = kubric.opencv_to_kubric_pose(c2w[camera])
    metadata.append(
      {
        "metadata": {"resolution": [height, width], "num_frames": frames, "frame_rate": frame_rate},
        "camera": {
          "focal_length": float(focal_lengths[camera]),
          "sensor_width": sensor_width,
          "positions": positions.tolist(),
          "quaternions": quaternions.tolist(),
        },
        "instances": instances,
      }
    )
  return images, depths, segmentations, metadata


def _add_member(tar: tarfile.TarFile, name: str, data: bytes) -> None:
  info = tarfile.TarInfo(name)
  info.size = len(data)
  tar.addfile(info, io.BytesIO(data))


def _segmentation_png(segmentation: np.ndarray) -> bytes:
  """An instance segmentation [H, W] (values 0-255) as an 8-bit palette PNG, as Kubric's
  `write_palette_png` (the indices are the values; the palette only makes it viewable)."""
  count = int(segmentation.max()) + 1
  colours = [(0.0, 0.0, 0.0)] + [colorsys.hls_to_rgb(k / count, 0.5, 0.8) for k in range(1, count)]
  height, width = segmentation.shape
  image = Image.frombytes("P", (width, height), np.ascontiguousarray(segmentation, np.uint8))
  image.putpalette([round(255 * c) for colour in colours for c in colour])
  png = io.BytesIO()
  image.save(png, format="PNG")
  return png.getvalue()


def write_kubric_view(
  path: str | os.PathLike,
  metadata: dict,
  images: np.ndarray,
  depths: np.ndarray,
  segmentations: np.ndarray | None = None,
) -> None:
  """Writes one camera's tar: images uint8 [F, H, W, 3] as opaque RGBA PNGs, depths [F, H, W] as
  float32 TIFFs (written as given: Kubric's are ray distances, `kubric.z_to_ray_depth`) and, when
  given, segmentations [F, H, W] (instance numbers 0-255) as palette PNGs, member names prefixed
  with './' as in the released data."""
  if segmentations is not None and not 0 <= np.min(segmentations) <= np.max(segmentations) <= 255:
    raise ValueError("Kubric's 8-bit segmentation PNGs hold instance numbers 0-255")
  with tarfile.open(path, "w") as tar:
    _add_member(tar, "./metadata.json", json.dumps(metadata).encode())
    for frame, (image, depth) in enumerate(zip(images, depths)):
      alpha = np.full(image.shape[:2] + (1,), 255, np.uint8)
      png = io.BytesIO()
      Image.fromarray(np.concatenate([image, alpha], -1), "RGBA").save(png, format="PNG")
      _add_member(tar, f"./rgba_{frame:05d}.png", png.getvalue())
      tiff = io.BytesIO()
      tifffile.imwrite(tiff, depth.astype(np.float32))
      _add_member(tar, f"./depth_{frame:05d}.tiff", tiff.getvalue())
      if segmentations is not None:
        _add_member(tar, f"./segmentation_{frame:05d}.png", _segmentation_png(segmentations[frame]))


def _write_kubric_scene(
  directory: str,
  seed: int,
  index: int,
  height: int,
  width: int,
  frames: int,
  num_cameras: int,
  config: KubricLikeConfig,
) -> None:
  write_kubric_scene(
    directory, render_kubric_like_scene(seed, index, height, width, frames, num_cameras, config)
  )


def write_kubric_scene(directory: str | os.PathLike, scene: dict) -> None:
  """Writes a rendered dynamic scene (`render_kubric_like_scene`'s fields) as one tar per camera,
  `<directory>/output_{camera:03d}.tar`."""
  os.makedirs(directory, exist_ok=True)
  for camera, metadata in enumerate(scene["metadata"]):
    write_kubric_view(
      os.path.join(directory, f"output_{camera:03d}.tar"),
      metadata,
      scene["images"][camera],
      scene["depths"][camera],
      scene["segmentations"][camera],
    )


def generate_kubric_like(
  root: str | os.PathLike,
  num_scenes: int,
  height: int = 64,
  width: int = 64,
  frames: int = 24,
  num_cameras: int = 9,
  seed: int = 0,
  *,
  subset: str = "v0",
  config: KubricLikeConfig = KubricLikeConfig(),
  workers: int = 1,
) -> list[pathlib.Path]:
  """Writes `num_scenes` dynamic scenes as `<root>/<subset>/scene_NNNNNN/output_{view:03d}.tar`.

  Returns the scene directories.
  """
  directories = [pathlib.Path(root) / subset / f"scene_{index:06d}" for index in range(num_scenes)]
  jobs = [
    (str(d), seed, index, height, width, frames, num_cameras, config)
    for index, d in enumerate(directories)
  ]
  _run_jobs(_write_kubric_scene, jobs, workers)
  return directories
