"""DL3DV-10K in the official TokenGS layout: one nerfstudio `transforms.json` + image folder per scene.

Layouts read (official `tokengs/data/static/dl3dv.py`, `registry.py`, `data/DATA.md`):
- training (DL3DV-ALL-960P): `<root>/<subset>/<scene>.zip` (subsets `1K` ... `11K`) holding
  `<scene>/transforms.json` and `<scene>/<image folder>/<name>`;
- benchmark (DL3DV-10K-Benchmark, official subset "140"): `<root>/<scene>.zip` holding
  `<scene>/gaussian_splat/transforms.json` and `<scene>/gaussian_splat/<image folder>/<name>`;
- the same trees unpacked: `<scene>/` directories in place of the zips.
The image folder is `images_4` (official resolution "960p") or `images` ("960p_images", the
registry's training setting). A frame's image is the base name of its `file_path`, looked up in
that folder, as official.

`transforms.json` (nerfstudio): `fl_x, fl_y, cx, cy` in pixels of the `w` x `h` capture, and
`frames[i].transform_matrix`, a camera-to-world in OpenGL camera axes (+y up, looking down -z) and
nerfstudio's world (COLMAP's with x and y swapped and z negated). Conversion, as official
`load_cameras`: undo the world change (rows: x <- y, y <- x, z <- -z; a proper rotation) and turn
the camera axes to OpenCV (negate the y and z columns). Intrinsics are rescaled from `w` x `h` to
the stored images, as official (which assumes 540 x 960; here the size of the scene's first
image, or `resolution` when given).

`DL3DVSceneSource` yields the data area's scene records (see `tokengs_jax.data.chunked`), so
`InputPipeline`, the evaluation indexes and everything after the source are shared with the chunk
format. A data folder splits into training and held-out scenes as the chunk format's does
(`dl3dv_split`, `dl3dv_training_source`): `<root>/train` and `<root>/test` where they exist (e.g.
links to DL3DV-ALL-960P and DL3DV-10K-Benchmark), else one folder whose held-out scenes an
evaluation index names; a held-out scene is never a training scene.
"""

from __future__ import annotations

import collections
import json
import os
import pathlib
from collections.abc import Iterable, Sequence

import numpy as np

from tokengs_jax.data.chunks import ChunkError, check_regular_file, read_member
from tokengs_jax.data.chunks.archive import _open_archive
from tokengs_jax.data.chunks.images import check_frame_bytes, image_size
from tokengs_jax.data.rejections import Rejections
from tokengs_jax.data.sampler import MissingIndexEntryError

__all__ = [
  "DL3DVError",
  "DL3DVSceneSource",
  "data_folder_format",
  "dl3dv_held_out_root",
  "dl3dv_split",
  "dl3dv_training_source",
  "has_dl3dv_scenes",
  "index_scene_keys",
  "list_dl3dv_scenes",
  "nerfstudio_to_opencv_c2w",
  "opencv_to_nerfstudio_c2w",
  "read_dl3dv_cameras",
]

DEFAULT_IMAGE_FOLDER = "images_4"
_BENCHMARK_PREFIX = "gaussian_splat"
# nerfstudio world -> COLMAP world (official `load_cameras` row operations): x <- y, y <- x, z <- -z.
_WORLD_NERFSTUDIO_TO_COLMAP = np.array(
  [[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)
# OpenGL camera axes (x right, y up, -z forward) -> OpenCV (x right, y down, z forward).
_CAMERA_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


class DL3DVError(ValueError):
  """A DL3DV scene is malformed; the message names the file and scene."""


def nerfstudio_to_opencv_c2w(transform_matrix: np.ndarray) -> np.ndarray:
  """DL3DV `transform_matrix` (nerfstudio world, OpenGL camera) -> OpenCV c2w, as official.

  transform_matrix: [..., 4, 4] -> [..., 4, 4] float64.
  """
  return _WORLD_NERFSTUDIO_TO_COLMAP @ np.asarray(transform_matrix, np.float64) @ _CAMERA_GL_TO_CV


def opencv_to_nerfstudio_c2w(c2w: np.ndarray) -> np.ndarray:
  """Inverse of `nerfstudio_to_opencv_c2w` (for writing test scenes); both factors are orthogonal.

  c2w: [..., 4, 4] -> [..., 4, 4] float64.
  """
  return _WORLD_NERFSTUDIO_TO_COLMAP.T @ np.asarray(c2w, np.float64) @ _CAMERA_GL_TO_CV


class _SceneFiles:
  """Reads files of one scene, whether it is a zip or a directory (picklable: holds paths only)."""

  def __init__(self, path: pathlib.Path):
    self.path = path
    self.key = path.stem if path.suffix == ".zip" else path.name
    nested = (
      f"{_BENCHMARK_PREFIX}/transforms.json"  # the benchmark nests the scene one level deeper
    )
    if path.suffix == ".zip":
      is_nested = f"{self.key}/{nested}" in _open_archive(str(path)).namelist()
    else:
      is_nested = (path / nested).is_file()
    self.prefix = _BENCHMARK_PREFIX + "/" if is_nested else ""

  def where(self, name: str) -> str:
    inner = f"{self.prefix}{name}"
    return (
      f"{self.path}:{self.key}/{inner}" if self.path.suffix == ".zip" else str(self.path / inner)
    )

  def read(self, name: str, *, is_frame: bool = False) -> bytes:
    """File `name` of the scene; an image (`is_frame`) is refused above `MAX_FRAME_BYTES` before
    it is read."""
    where = f"{self.where(name)} (scene '{self.key}')"
    try:
      if self.path.suffix == ".zip":
        archive, member = _open_archive(str(self.path)), f"{self.key}/{self.prefix}{name}"
        if member not in archive.NameToInfo:
          raise DL3DVError(f"{self.where(name)}: missing (scene '{self.key}')")
        if is_frame:
          check_frame_bytes(archive.NameToInfo[member].file_size, where=where)
        return read_member(archive, member, where=where)
      path = self.path / self.prefix / name
      if not path.exists():
        raise DL3DVError(f"{self.where(name)}: missing (scene '{self.key}')")
      check_regular_file(path)  # a FIFO or device would block or never end
      if is_frame:
        check_frame_bytes(path.stat().st_size, where=where)
      return path.read_bytes()
    except ChunkError as error:
      raise DL3DVError(str(error)) from error
    except OSError as error:
      raise DL3DVError(f"{self.where(name)}: cannot read ({error}; scene '{self.key}')") from error


class _SceneImages:
  """Lazy length-F sequence of one scene's encoded images (PNG/JPEG bytes), read on access."""

  def __init__(self, files: _SceneFiles, folder: str, names: Sequence[str]):
    self.files, self.folder, self.names = files, folder, tuple(names)

  def __len__(self) -> int:
    return len(self.names)

  def __getitem__(self, index: int) -> bytes:
    if not 0 <= index < len(self.names):
      raise IndexError(f"{self.files.path}: frame {index} of {len(self.names)}")
    return self.files.read(f"{self.folder}/{self.names[index]}", is_frame=True)


def _scene_files(path: pathlib.Path) -> _SceneFiles:
  try:
    return _SceneFiles(path)
  except (OSError, ChunkError) as error:
    raise DL3DVError(f"{path}: not a readable scene zip ({error})") from error


def read_dl3dv_cameras(
  transforms: dict, where: str
) -> tuple[np.ndarray, np.ndarray, tuple[float, float], list[str]]:
  """Cameras of a parsed `transforms.json`; `where` (file and scene) is named in errors.

  Returns:
    (c2w [F, 4, 4] float32 OpenCV, intrinsics [F, 4] float64 fx, fy, cx, cy in pixels of the
    capture, capture size (h, w), image file base names [F]).
  """
  try:
    fx, fy, cx, cy, width, height = (
      float(transforms[k]) for k in ("fl_x", "fl_y", "cx", "cy", "w", "h")
    )
  except KeyError as error:
    raise DL3DVError(f"{where}: no '{error.args[0]}' (needs fl_x, fl_y, cx, cy, w, h)") from error
  except (TypeError, ValueError) as error:
    raise DL3DVError(f"{where}: intrinsics are not numbers ({error})") from error
  frames = transforms.get("frames")
  if not isinstance(frames, list) or not frames:
    raise DL3DVError(f"{where}: 'frames' must be a non-empty list")
  matrices, names = [], []
  for number, frame in enumerate(frames):
    try:
      matrix = np.asarray(frame["transform_matrix"], np.float64)
      names.append(str(frame["file_path"]).split("/")[-1])  # base name, as official
    except (KeyError, TypeError, ValueError) as error:
      raise DL3DVError(
        f"{where}: frame {number} needs 'transform_matrix' and 'file_path' "
        f"({type(error).__name__}: {error})"
      ) from error
    if matrix.shape != (4, 4):
      raise DL3DVError(
        f"{where}: frame {number} transform_matrix is {list(matrix.shape)}, not [4, 4]"
      )
    matrices.append(matrix)
  matrices = np.stack(matrices)
  if not np.isfinite(matrices).all():
    bad = sorted({int(i) for i in np.nonzero(~np.isfinite(matrices))[0]})
    raise DL3DVError(f"{where}: NaN/inf in transform_matrix of frames {bad}")
  intrinsics = np.array([fx, fy, cx, cy])
  if not (np.isfinite(intrinsics).all() and fx > 0 and fy > 0 and width > 0 and height > 0):
    raise DL3DVError(f"{where}: bad intrinsics fl_x={fx}, fl_y={fy}, w={width}, h={height}")
  c2w = nerfstudio_to_opencv_c2w(matrices).astype(np.float32)
  return c2w, np.tile(intrinsics, (len(matrices), 1)), (height, width), names


def _is_scene_dir(path: pathlib.Path) -> bool:
  return (path / "transforms.json").is_file() or (
    path / _BENCHMARK_PREFIX / "transforms.json"
  ).is_file()


def _scenes_in(directory: pathlib.Path) -> tuple[list[pathlib.Path], list[pathlib.Path]]:
  """(scene zips/directories directly in `directory`, other subdirectories), each sorted."""
  scenes, others = [], []
  for entry in sorted(directory.iterdir()):
    if entry.suffix == ".zip" and entry.is_file() or entry.is_dir() and _is_scene_dir(entry):
      scenes.append(entry)
    elif entry.is_dir():
      others.append(entry)
  return scenes, others


def list_dl3dv_scenes(
  root: str | os.PathLike, subsets: Sequence[str] | None = None
) -> list[pathlib.Path]:
  """Scene zips / directories under `root`.

  subsets: read `<root>/<subset>` for each, in order (official training: `1K` ... `11K`);
    None: the scenes directly in `root` (the benchmark layout) followed by those one level down
    (every subset directory found). Missing subset directories are an error.
  """
  root = pathlib.Path(root)
  if not root.is_dir():
    raise DL3DVError(f"{root}: no such DL3DV directory")
  if subsets is not None:
    missing = [s for s in subsets if not (root / s).is_dir()]
    if missing:
      raise DL3DVError(f"{root}: subset directories {missing} not found")
    return [scene for s in subsets for scene in _scenes_in(root / s)[0]]
  scenes, others = _scenes_in(root)
  return scenes + [scene for directory in others for scene in _scenes_in(directory)[0]]


class DL3DVSceneSource:
  """Random-access source of DL3DV scenes in the official layout, as scene records.

  Only the scene list is built up front; `[i]` parses that scene's `transforms.json` (cached per
  process) and returns lazy images, so a sample reads just the frames it uses.

  Args:
    root: dataset root (see the module docstring for the layouts).
    subsets: subset directories to read (default: discover, see `list_dl3dv_scenes`).
    image_folder: `images_4` (official "960p") or `images` (official "960p_images").
    resolution: (H, W) the intrinsics are rescaled to; default: the size of the scene's first
      image (the official code assumes (540, 960)). The pipeline checks every frame it decodes
      against it, so a scene with mixed sizes is reported, not silently mis-calibrated.
    keys: only these scenes (e.g. an evaluation index's keys), in this order.
    skip_bad: drop, count and log (`rejections`) requested keys that are absent, instead of
      raising `MissingIndexEntryError`. Malformed scenes raise `DL3DVError` on access; the
      pipeline's `skip_bad` drops those.
  """

  def __init__(
    self,
    root: str | os.PathLike,
    *,
    subsets: Sequence[str] | None = None,
    image_folder: str = DEFAULT_IMAGE_FOLDER,
    resolution: tuple[int, int] | None = None,
    keys: Iterable[str] | None = None,
    skip_bad: bool = False,
  ):
    self.root = pathlib.Path(root)
    self.image_folder, self.resolution = image_folder, resolution
    self.rejections = Rejections(f"source {self.root}")
    scenes = list_dl3dv_scenes(self.root, subsets)
    by_key = {}
    for path in scenes:
      by_key.setdefault(path.stem if path.suffix == ".zip" else path.name, path)
    if keys is None:
      self.scenes = list(by_key.values())
    else:
      self.scenes = []
      for key in keys:
        if key in by_key:
          self.scenes.append(by_key[key])
          continue
        error = MissingIndexEntryError(f"{self.root}: scene '{key}' is not in the dataset")
        if not skip_bad:
          raise error
        self.rejections.add("missing_scene", str(error))
    self._cache: collections.OrderedDict = collections.OrderedDict()

  def __len__(self) -> int:
    return len(self.scenes)

  @property
  def keys(self) -> list[str]:
    """The scene keys (zip stem / directory name), in item order."""
    return [path.stem if path.suffix == ".zip" else path.name for path in self.scenes]

  def __getitem__(self, index: int) -> dict:
    path = self.scenes[index]
    key = (os.getpid(), path)
    if key not in self._cache:
      self._cache[key] = self._read_scene(path)
      while len(self._cache) > 64:
        self._cache.popitem(last=False)
    self._cache.move_to_end(key)
    return dict(self._cache[key])

  def frame_counts(self) -> dict[str, int]:
    """Scene key -> number of frames, reading each `transforms.json` (and one image header) but
    no pixel, so an evaluation index is checked against the data before any work. A scene that
    cannot be read is dropped from the source, counted and logged (`rejections`), as the chunk
    source's `skip_bad` drops a malformed scene when it is listed."""
    counts, kept = {}, []
    for index, path in enumerate(self.scenes):
      try:
        record = self[index]
      except DL3DVError as error:
        self.rejections.add("bad_scene", str(error))
        continue
      counts[record["key"]] = len(record["images"])
      kept.append(path)
    self.scenes = kept
    return counts

  def _read_scene(self, path: pathlib.Path) -> dict:
    files = _scene_files(path)
    where = f"{files.where('transforms.json')} (scene '{files.key}')"
    try:
      transforms = json.loads(files.read("transforms.json"))
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
      raise DL3DVError(f"{where}: not valid JSON ({error})") from error
    if not isinstance(transforms, dict):
      raise DL3DVError(f"{where}: expected a JSON object, found {type(transforms).__name__}")
    c2w, intrinsics, (raw_height, raw_width), names = read_dl3dv_cameras(transforms, where)
    images = _SceneImages(files, self.image_folder, names)
    height, width = self.resolution or self._image_size(images, files)
    # as official: every intrinsic scaled by the stored/capture size ratio of its axis
    scale = np.array([width / raw_width, height / raw_height] * 2)
    return {
      "key": files.key,
      "source": str(path),
      "c2w": c2w,
      "intrinsics": (intrinsics * scale).astype(np.float32),
      "height": int(height),
      "width": int(width),
      "images": images,
    }

  def _image_size(self, images: _SceneImages, files: _SceneFiles) -> tuple[int, int]:
    """(H, W) from the first image's header (no pixel is decoded)."""
    where = f"{files.where(f'{self.image_folder}/{images.names[0]}')} (scene '{files.key}')"
    return image_size(images[0], where=where, error=DL3DVError)

  def __getstate__(self):  # workers rebuild their own cache
    return {**self.__dict__, "_cache": collections.OrderedDict()}


def has_dl3dv_scenes(root: str | os.PathLike) -> bool:
  """Whether `root` holds DL3DV scenes (zips or unpacked) in a layout read here: directly, in
  subset folders (`1K/` ...), or under `train/` and `test/` (`dl3dv_split`)."""
  root = pathlib.Path(root)
  folders = [root, root / "train", root / "test"]
  return any(folder.is_dir() and list_dl3dv_scenes(folder) for folder in folders)


def data_folder_format(root: str | os.PathLike, *, where: str = "") -> str:
  """What a real-data folder holds: "chunks" (pixelSplat `train/`, `test/`: `*.torch` +
  `index.json`) or "zips" (DL3DV scenes as they ship, zipped or not: `has_dl3dv_scenes`).

  Raises DL3DVError (`where` prefixes the folder in the message) for a folder holding neither.
  """
  root = pathlib.Path(root)
  if not root.is_dir():
    raise DL3DVError(f"{where}{root}: no such folder")
  for stage in (root / "train", root / "test"):
    if (stage / "index.json").is_file() or next(stage.glob("*.torch"), None):
      return "chunks"
  if has_dl3dv_scenes(root):
    return "zips"
  raise DL3DVError(
    f"{where}{root}: holds neither pixelSplat chunks (train/ and test/ with *.torch and "
    "index.json) nor DL3DV scenes (<scene>.zip or <scene>/ with transforms.json: directly, in "
    "subset folders such as 1K/, or in train/ and test/)"
  )


def dl3dv_split(root: str | os.PathLike) -> tuple[pathlib.Path, pathlib.Path]:
  """(training root, held-out root) of a DL3DV data folder: `root/train` and `root/test` when
  either exists (the chunk format's split), else `root` for both (one folder of scenes: the
  evaluation index names the held-out ones, `dl3dv_training_source` leaves them out)."""
  root = pathlib.Path(root)
  if (root / "train").is_dir() or (root / "test").is_dir():
    return root / "train", root / "test"
  return root, root


def dl3dv_held_out_root(root: str | os.PathLike, *, indexed: bool) -> pathlib.Path:
  """`dl3dv_split`'s held-out root; DL3DVError where it is the whole folder and no evaluation
  index (`indexed`) names which of its scenes are held out."""
  train_root, test_root = dl3dv_split(root)
  if test_root == train_root and not indexed:
    raise DL3DVError(
      f"{root}: one folder of DL3DV scenes: name the held-out ones with an evaluation index "
      "(--eval-index; they are never trained on), or split them into train/ and test/"
    )
  return test_root


def index_scene_keys(path: str | os.PathLike) -> set[str]:
  """Every scene an evaluation index JSON names (null entries too; either format of
  `load_evaluation_index`), whatever its views."""
  raw = json.loads(pathlib.Path(path).read_text())
  if isinstance(raw, dict):
    return set(raw)
  return {e["scene_name"] for e in raw if isinstance(e, dict) and "scene_name" in e}


def dl3dv_training_source(
  root: str | os.PathLike, *, held_out_index: str | os.PathLike | None = None, **kwargs
) -> DL3DVSceneSource:
  """The training scenes of a DL3DV data folder (`dl3dv_split`), without any held-out scene.

  Held out: the scenes the evaluation index `held_out_index` names (`index_scene_keys`) and, in
  the split layout, every scene of `root/test` (DL3DV-ALL holds the benchmark's scenes too:
  DepthSplat's training set leaves them out). Only scene lists are read (no zip is opened).
  kwargs: `DL3DVSceneSource`'s.
  """
  train_root, test_root = dl3dv_split(root)
  excluded = index_scene_keys(held_out_index) if held_out_index else set()
  if test_root != train_root and test_root.is_dir():
    excluded.update(DL3DVSceneSource(test_root).keys)
  keys = [key for key in DL3DVSceneSource(train_root).keys if key not in excluded]
  if not keys:
    raise DL3DVError(
      f"{train_root}: no training scene left once the {len(excluded)} held-out ones are set aside"
    )
  return DL3DVSceneSource(train_root, keys=keys, **kwargs)
