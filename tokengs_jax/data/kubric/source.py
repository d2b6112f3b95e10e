"""Kubric scenes as scene records for the input pipeline (`tokengs_jax.data.pipeline`).

`list_kubric_scenes` finds the scene directories `<root>/<subset>/<scene>`; `KubricSceneSource`
turns each into a record whose C cameras x F frames are flattened camera-major, with lazy PNG/TIFF
members read only for the views a sample picks.
"""

from __future__ import annotations

import collections
import logging
import os
import pathlib
from typing import Sequence

import numpy as np

from tokengs_jax.data.kubric.camera_tar import (
  KubricError,
  KubricView,
  decode_member,
  parse_kubric_view,
)

DEFAULT_SUBSETS = ("v0", "v1", "v2")
OFFICIAL_NUM_CAMERAS = 9  # the official `Kubric` default and released Kubric-4D rig


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


class _TarFrames:
  """Lazy length-(C*F) sequence of one per-frame member, decoded, camera-major: item c * F + f is
  camera c, frame f. `member` is a format string of the frame, e.g. "rgba_{:05d}.png".

  The pipeline reads only the items it picks. They are decoded here (images uint8 [H, W, 3], their
  alpha uint8 [H, W] with `alpha`, depth maps float32 [H, W], segmentations int32 [H, W], each of
  the metadata's resolution), not by the pipeline, so that a bad frame's `KubricError` names its
  tar and member rather than a flattened index.
  """

  def __init__(
    self, views: Sequence[KubricView], num_frames: int, member: str, *, alpha: bool = False
  ):
    self.views, self.num_frames, self.member = tuple(views), num_frames, member
    self.alpha = alpha  # the member's alpha channel (`decode_member(alpha=True)`)

  def __len__(self) -> int:
    return len(self.views) * self.num_frames

  def present(self, index: int) -> bool:
    """Whether item `index`'s member is in its tar (depth maps are optional)."""
    camera, frame = divmod(int(index), self.num_frames)
    return self.member.format(frame) in self.views[camera].members

  def __getitem__(self, index: int) -> np.ndarray:
    if not 0 <= index < len(self):
      raise IndexError(
        f"{pathlib.Path(self.views[0].path).parent}: item {index} of {len(self.views)} cameras "
        f"x {self.num_frames} frames"
      )
    camera, frame = divmod(int(index), self.num_frames)
    view = self.views[camera]
    shape = (view.height, view.width)
    return decode_member(view, self.member.format(frame), shape, alpha=self.alpha)


class KubricSceneSource:
  """Random-access source of Kubric scene records in the pipeline's record contract.

  A scene's C cameras x F frames are flattened camera-major into C*F "frames": `c2w [C*F, 4, 4]`
  (OpenCV), `intrinsics [C*F, 4]`, lazily decoded `images` (uint8 [H, W, 3]), `alphas` (uint8
  [H, W], the same PNGs' alpha channel: the foreground masks; decoded only if read), `depths`
  (float32 [H, W], the stored distance along each pixel's ray; the pipeline's "pointmap" scale
  reads the context views' ones) and `segmentations` (int32 [H, W] object instance numbers, 0
  the background; `.present(i)` says whether the tar has them), and `times [C*F]` = the frame
  index (the pipeline min-max normalises times per example, as official), plus `num_cameras`,
  `num_frames` for `kubric_view_selector`. When every camera's metadata lists the same object
  `instances`, the record also has `object_poses [K, F, 4, 4]` (object-to-world at every frame,
  in the cameras' world; instance k is segmentation number k + 1); the evaluation's motion
  truth (`evaluation.evaluation_fields`). Cameras that list different instances (e.g. only
  those each one sees) leave it out, with a warning: their numbers need not agree.

  Each scene's tars are parsed once per process (metadata and member offsets, cached for the
  last 64 scenes); a sample then reads only its views' members. A malformed scene raises
  `KubricError` on access (the pipeline's `skip_bad` counts and skips it), in particular one
  without all of `output_000.tar` ... `output_{num_cameras - 1:03d}.tar`, or whose tars lack a
  frame their metadata lists (`parse_kubric_view`).

  Args:
    root, subsets: list the scenes with `list_kubric_scenes(root, subsets)`...
    scenes: ...or use exactly these scene directories (e.g. a train/held-out split of a listing).
    num_cameras: cameras every scene must have; cameras 0 .. num_cameras - 1 are read and any
      further tars ignored (official `Kubric(num_cameras=9)`: the released rig). None: every
      `output_*.tar` of the scene, which must be numbered 0 .. C - 1 without a gap (a missing
      last tar then goes unnoticed: for generated rigs of a known size, give that size).
  """

  def __init__(
    self,
    root: str | os.PathLike | None = None,
    subsets: Sequence[str] = DEFAULT_SUBSETS,
    *,
    scenes: Sequence[str | os.PathLike] | None = None,
    num_cameras: int | None = OFFICIAL_NUM_CAMERAS,
  ):
    if (root is None) == (scenes is None):
      raise ValueError("give either root (with subsets) or scenes")
    if num_cameras is not None and num_cameras < 1:
      raise ValueError(f"num_cameras must be positive or None, got {num_cameras}")
    self.num_cameras = num_cameras
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
      self._cache[key] = _read_scene(scene_dir, self.num_cameras)
      while len(self._cache) > 64:
        self._cache.popitem(last=False)
    self._cache.move_to_end(key)
    return dict(self._cache[key])

  def __getstate__(self):  # workers build their own cache
    return {**self.__dict__, "_cache": collections.OrderedDict()}


def _camera_tars(scene_dir: pathlib.Path, num_cameras: int | None) -> list[pathlib.Path]:
  """The scene's camera tars `output_000.tar` ... in camera order; `KubricError` naming the scene
  and the first missing tar unless all `num_cameras` (None: as many as there are) are there."""
  numbers = set()
  for path in scene_dir.glob("output_*.tar"):
    number = path.name.removeprefix("output_").removesuffix(".tar")
    if number.isdigit():
      numbers.add(int(number))
  if not numbers:
    raise KubricError(f"{scene_dir}: no output_*.tar camera files")
  count = max(numbers) + 1 if num_cameras is None else num_cameras
  missing = [c for c in range(count) if c not in numbers]
  if missing:
    expected = "numbered without gaps" if num_cameras is None else f"num_cameras={num_cameras}"
    raise KubricError(
      f"{scene_dir}: camera tar {scene_dir / f'output_{missing[0]:03d}.tar'} is missing "
      f"({len(missing)} of the {count} cameras absent; expected {expected})"
    )
  return [scene_dir / f"output_{c:03d}.tar" for c in range(count)]


def _shared_object_poses(scene_dir: pathlib.Path, views: Sequence[KubricView]):
  """The object poses [K, F, 4, 4] every camera's metadata lists; None when the first lists none
  or the cameras disagree (then with a warning)."""
  poses = views[0].object_poses
  if poses is None:
    return None
  for view in views[1:]:
    if view.object_poses is None or not (
      view.object_poses.shape == poses.shape and np.allclose(view.object_poses, poses, atol=1e-6)
    ):
      logging.getLogger("tokengs_jax.data").warning(
        "%s: %s lists other object instances than %s; the scene has no object motion truth",
        scene_dir,
        pathlib.Path(view.path).name,
        pathlib.Path(views[0].path).name,
      )
      return None
  return poses


def _read_scene(scene_dir: pathlib.Path, num_cameras: int | None) -> dict:
  views = [parse_kubric_view(path) for path in _camera_tars(scene_dir, num_cameras)]
  first = views[0]
  if any(
    (v.num_frames, v.height, v.width) != (first.num_frames, first.height, first.width)
    for v in views
  ):
    raise KubricError(f"{scene_dir}: cameras differ in frame count or resolution")
  object_poses = _shared_object_poses(scene_dir, views)
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
    "alphas": _TarFrames(views, first.num_frames, "rgba_{:05d}.png", alpha=True),
    "depths": _TarFrames(views, first.num_frames, "depth_{:05d}.tiff"),
    "segmentations": _TarFrames(views, first.num_frames, "segmentation_{:05d}.png"),
    "times": np.tile(np.arange(first.num_frames, dtype=np.float64), len(views)),
    "num_cameras": len(views),
    "num_frames": first.num_frames,
    **({} if object_poses is None else {"object_poses": object_poses}),
  }
