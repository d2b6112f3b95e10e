"""DL3DV in the official TokenGS layout, on small scenes written here (zip, directory, benchmark)."""

import io
import json
import zipfile

import numpy as np
import pytest
from PIL import Image

from tokengs_jax.data import (
  BadExampleError,
  BoundedSamplerConfig,
  DL3DVError,
  DL3DVSceneSource,
  ExampleConfig,
  InputPipeline,
  MissingIndexEntryError,
  list_dl3dv_scenes,
  make_example,
  nerfstudio_to_opencv_c2w,
  opencv_to_nerfstudio_c2w,
)
from tokengs_jax.data.dl3dv import (
  data_folder_format,
  dl3dv_held_out_root,
  dl3dv_split,
  dl3dv_training_source,
)
from tokengs_jax.data.pipeline import _frame

CAPTURE = (72, 128)  # (h, w) the transforms.json intrinsics refer to
STORED = (36, 64)  # (H, W) of the images in images_4/
RAW_INTRINSICS = (90.0, 80.0, 60.0, 40.0)  # fl_x, fl_y, cx, cy (off-centre principal point)
POINT_NS = np.array([0.3, -0.2, -4.0])  # a world point in the nerfstudio world
FRAMES = 6


def _gl_look_at(position, target):
  """OpenGL camera-to-world (x right, y up, looking down -z) at `position` looking at `target`."""
  back = position - target
  back = back / np.linalg.norm(back)
  right = np.cross([0.0, 1.0, 0.0], back)
  right = right / np.linalg.norm(right)
  pose = np.eye(4)
  pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, np.cross(back, right), back, position
  return pose


def _gl_poses():
  return np.stack(
    [
      _gl_look_at(np.array([0.2 * f - 0.5, 0.1 * f, 0.3]), POINT_NS + [0.1, 0.05, 0.0])
      for f in range(FRAMES)
    ]
  )


def _project_gl(pose, point, intrinsics):
  """Pixel of a world point in an OpenGL camera (z < 0 in front, y up = rows decreasing)."""
  fx, fy, cx, cy = intrinsics
  x, y, z = (np.linalg.inv(pose) @ np.append(point, 1.0))[:3]
  return np.array([cx + fx * x / -z, cy - fy * y / -z])


def _project_cv(c2w, point, intrinsics):
  fx, fy, cx, cy = intrinsics
  x, y, z = (np.linalg.inv(c2w) @ np.append(point, 1.0))[:3]
  return np.array([cx + fx * x / z, cy + fy * y / z])


def _stored_intrinsics():
  sy, sx = STORED[0] / CAPTURE[0], STORED[1] / CAPTURE[1]
  fx, fy, cx, cy = RAW_INTRINSICS
  return np.array([fx * sx, fy * sy, cx * sx, cy * sy])


def _blob_image(center, shape=STORED):
  """uint8 [H, W, 3]: a Gaussian blob (sigma 1.5 px) centred at pixel coordinates `center`."""
  rows, cols = np.mgrid[: shape[0], : shape[1]] + 0.5
  blob = np.exp(-((cols - center[0]) ** 2 + (rows - center[1]) ** 2) / (2 * 1.5**2))
  return np.repeat((blob * 255).round().astype(np.uint8)[..., None], 3, -1)


def _centroid(image):
  weight = image[..., 0].astype(np.float64)
  rows, cols = np.mgrid[: image.shape[0], : image.shape[1]] + 0.5
  return np.array([(weight * cols).sum(), (weight * rows).sum()]) / weight.sum()


def _scene_files(poses=None, names=None):
  """{relative path: bytes} of one scene: transforms.json + images_4/*.png with the point's blob."""
  poses = _gl_poses() if poses is None else poses
  names = names or [f"frame_{f + 1:05d}.png" for f in range(FRAMES)]
  fx, fy, cx, cy = RAW_INTRINSICS
  transforms = {
    "w": CAPTURE[1],
    "h": CAPTURE[0],
    "fl_x": fx,
    "fl_y": fy,
    "cx": cx,
    "cy": cy,
    "k1": 0.0,
    "camera_model": "OPENCV",
    "frames": [
      {"file_path": f"images/{name}", "transform_matrix": pose.tolist()}
      for name, pose in zip(names, poses)
    ],
  }
  files = {"transforms.json": json.dumps(transforms).encode()}
  for name, pose in zip(names, poses):
    buffer = io.BytesIO()
    Image.fromarray(_blob_image(_project_gl(pose, POINT_NS, _stored_intrinsics()))).save(
      buffer, "PNG"
    )
    files[f"images_4/{name}"] = buffer.getvalue()
  return files


def _write_zip(path, key, files, prefix=""):
  path.parent.mkdir(parents=True, exist_ok=True)
  with zipfile.ZipFile(path, "w") as archive:
    for name, data in files.items():
      archive.writestr(f"{key}/{prefix}{name}", data)


def _write_dir(directory, files):
  for name, data in files.items():
    (directory / name).parent.mkdir(parents=True, exist_ok=True)
    (directory / name).write_bytes(data)


@pytest.fixture(scope="module")
def dl3dv_root(tmp_path_factory):
  """Training layout: <root>/1K/<key>.zip and <root>/2K/<key>/ (unpacked)."""
  root = tmp_path_factory.mktemp("dl3dv")
  files = _scene_files()
  _write_zip(root / "1K" / "aaaa.zip", "aaaa", files)
  _write_dir(root / "2K" / "bbbb", files)
  return root


def test_official_conversion_is_the_documented_row_and_column_operations():
  matrix = np.random.default_rng(0).normal(size=(4, 4))
  matrix[3] = [0, 0, 0, 1]  # an affine transform, as every transform_matrix is
  expected = matrix.copy()  # official load_cameras: negate row z, swap rows x/y, negate columns y/z
  expected[2, :] *= -1
  expected = expected[[1, 0, 2, 3]]
  expected[:3, 1:3] *= -1
  np.testing.assert_allclose(nerfstudio_to_opencv_c2w(matrix), expected)
  np.testing.assert_allclose(
    opencv_to_nerfstudio_c2w(nerfstudio_to_opencv_c2w(matrix)), matrix, atol=1e-12
  )
  rotation = nerfstudio_to_opencv_c2w(_gl_poses())[:, :3, :3]  # still rotations (det +1)
  np.testing.assert_allclose(np.linalg.det(rotation), 1.0, atol=1e-9)


@pytest.mark.parametrize("index", [0, 1])
def test_point_projects_to_the_same_pixel_before_and_after_conversion(dl3dv_root, index):
  source = DL3DVSceneSource(dl3dv_root)
  record = source[index]
  assert record["key"] == ["aaaa", "bbbb"][index]
  assert (record["height"], record["width"]) == STORED
  np.testing.assert_allclose(
    record["intrinsics"], np.tile(_stored_intrinsics(), (FRAMES, 1)), rtol=1e-6
  )
  # The point in the converted world, placed from frame 0's OpenGL view (so the test does not
  # assume the world change), must land where the OpenGL projection put it in every frame, and
  # where the image's blob is.
  gl = _gl_poses()
  in_camera0 = (np.linalg.inv(gl[0]) @ np.append(POINT_NS, 1.0))[:3] * [1, -1, -1]  # GL -> CV axes
  point = (record["c2w"][0].astype(np.float64) @ np.append(in_camera0, 1.0))[:3]
  for f in range(FRAMES):
    before = _project_gl(gl[f], POINT_NS, _stored_intrinsics())
    after = _project_cv(record["c2w"][f].astype(np.float64), point, record["intrinsics"][f])
    np.testing.assert_allclose(after, before, atol=1e-3)
    np.testing.assert_allclose(_centroid(_frame(record, f)), after, atol=0.3)


def test_pipeline_crop_keeps_the_point_on_its_blob(dl3dv_root):
  record = DL3DVSceneSource(dl3dv_root)[0]
  config = ExampleConfig(
    (24, 24), BoundedSamplerConfig(2, 2, 2, 5, 0, 0, 2, 5), 0.15, random_flip=False
  )
  views = (np.array([1, 4]), np.array([2, 5]))
  example = make_example(record, config, np.random.default_rng(0), views=views)
  gl = _gl_poses()
  in_camera1 = (
    (np.linalg.inv(gl[1]) @ np.append(POINT_NS, 1.0))[:3] * [1, -1, -1] * 0.15
  )  # first_cam
  for images, c2w, intrinsics in (
    ("context_images", "context_c2w", "context_intrinsics"),
    ("target_images", "target_c2w", "target_intrinsics"),
  ):
    for v in range(2):
      pixel = _project_cv(example[c2w][v].astype(np.float64), in_camera1, example[intrinsics][v])
      np.testing.assert_allclose(_centroid(example[images][v]), pixel, atol=0.35)


def test_benchmark_layout_keys_and_subsets(tmp_path):
  files = _scene_files()
  _write_zip(tmp_path / "bench" / "cccc.zip", "cccc", files, prefix="gaussian_splat/")
  _write_dir(tmp_path / "bench" / "dddd" / "gaussian_splat", files)
  source = DL3DVSceneSource(tmp_path / "bench", keys=["dddd", "cccc"])
  assert [source[i]["key"] for i in range(2)] == ["dddd", "cccc"]
  assert len(source[1]["images"]) == FRAMES and _frame(source[1], 0).shape == STORED + (3,)
  with pytest.raises(MissingIndexEntryError, match="'eeee'"):
    DL3DVSceneSource(tmp_path / "bench", keys=["eeee"])
  skipping = DL3DVSceneSource(tmp_path / "bench", keys=["eeee", "cccc"], skip_bad=True)
  assert len(skipping) == 1 and skipping.rejections.counts["missing_scene"] == 1
  _write_zip(tmp_path / "train" / "1K" / "x.zip", "x", files)
  _write_zip(tmp_path / "train" / "2K" / "y.zip", "y", files)
  assert [p.stem for p in list_dl3dv_scenes(tmp_path / "train", ["2K"])] == ["y"]
  with pytest.raises(DL3DVError, match="3K"):
    list_dl3dv_scenes(tmp_path / "train", ["1K", "3K"])


def test_pipeline_batches_from_a_zip_dataset(dl3dv_root):
  config = ExampleConfig((16, 32), BoundedSamplerConfig(2, 3, 2, 5, 0, 0, 2, 5), 0.15)
  pipeline = InputPipeline(
    DL3DVSceneSource(dl3dv_root), config, batch_size=2, seed=0, shard_index=0, shard_count=1
  )
  batch = next(iter(pipeline))
  assert batch["context_images"].shape == (2, 2, 16, 32, 3)
  assert batch["target_c2w"].shape == (2, 3, 4, 4)
  np.testing.assert_allclose(
    batch["context_c2w"][:, 0], np.broadcast_to(np.eye(4), (2, 4, 4)), atol=1e-6
  )


def _bad_transforms(tmp_path, name, edit):
  files = _scene_files()
  transforms = json.loads(files["transforms.json"])
  edit(transforms)
  files["transforms.json"] = json.dumps(transforms).encode()
  _write_zip(tmp_path / name / "s.zip", "s", files)
  return DL3DVSceneSource(tmp_path / name)


@pytest.mark.parametrize(
  "name, edit, message",
  [
    ("no_fx", lambda t: t.pop("fl_x"), "no 'fl_x'"),
    (
      "shape",
      lambda t: t["frames"][2].update(transform_matrix=[[1, 0, 0], [0, 1, 0]]),
      "frame 2 .*\\[2, 3\\]",
    ),
    (
      "nan",
      lambda t: t["frames"][3]["transform_matrix"][0].__setitem__(3, float("nan")),
      "NaN/inf.*\\[3\\]",
    ),
    ("no_frames", lambda t: t.update(frames=[]), "non-empty"),
    ("no_path", lambda t: t["frames"][0].pop("file_path"), "frame 0 needs"),
  ],
)
def test_bad_transforms_name_file_and_scene(tmp_path, name, edit, message):
  source = _bad_transforms(tmp_path, name, edit)
  with pytest.raises(DL3DVError, match=message) as error:
    source[0]
  assert "s.zip:s/transforms.json" in str(error.value) and "scene 's'" in str(error.value)


def test_bad_files_name_file_and_scene(tmp_path):
  files = _scene_files()
  del files["transforms.json"]
  _write_zip(tmp_path / "a" / "s.zip", "s", files)
  with pytest.raises(DL3DVError, match="s.zip:s/transforms.json: missing \\(scene 's'\\)"):
    DL3DVSceneSource(tmp_path / "a")[0]

  files = _scene_files()
  files["transforms.json"] = b"{not json"
  _write_zip(tmp_path / "b" / "s.zip", "s", files)
  with pytest.raises(DL3DVError, match="not valid JSON"):
    DL3DVSceneSource(tmp_path / "b")[0]

  (tmp_path / "c").mkdir()
  (tmp_path / "c" / "s.zip").write_bytes(b"not a zip")
  with pytest.raises(DL3DVError, match="s.zip: not a readable scene zip"):
    DL3DVSceneSource(tmp_path / "c")[0]

  files = _scene_files()
  files["images_4/frame_00003.png"] = b"\x89PNG broken"
  del files["images_4/frame_00005.png"]
  _write_zip(tmp_path / "d" / "s.zip", "s", files)
  record = DL3DVSceneSource(tmp_path / "d")[0]
  config = ExampleConfig(STORED, BoundedSamplerConfig(2, 1, 1, 5, 0, 0, 1, 5), 0.15)
  with pytest.raises(BadExampleError, match="s.zip scene 's'.*frame 2.*corrupt image"):
    make_example(record, config, np.random.default_rng(0), views=(np.array([0, 2]), np.array([1])))
  with pytest.raises(BadExampleError, match="s.zip scene 's'.*images_4/frame_00005.png: missing"):
    make_example(record, config, np.random.default_rng(0), views=(np.array([0, 4]), np.array([1])))
  pipeline = InputPipeline(
    DL3DVSceneSource(tmp_path / "d"),
    config,
    batch_size=1,
    seed=0,
    shard_index=0,
    shard_count=1,
    num_epochs=1,
    skip_bad=True,
    evaluation_index={"s": ((0, 4), (1,))},
  )
  assert list(pipeline) == [] and pipeline.rejections.counts == {"DL3DVError": 1}


def test_frames_of_another_size_than_the_resolution_are_reported(dl3dv_root):
  record = DL3DVSceneSource(dl3dv_root, resolution=(54, 96))[0]
  config = ExampleConfig((16, 16), BoundedSamplerConfig(2, 1, 1, 5, 0, 0, 1, 5), 0.15)
  with pytest.raises(BadExampleError, match="aaaa.zip scene 'aaaa'.*\\(36, 64\\).*\\(54, 96\\)"):
    make_example(record, config, np.random.default_rng(0), views=(np.array([0, 2]), np.array([1])))


def test_scenes_written_in_the_shipped_layout_read_back_as_rendered(tmp_path):
  """`scenes.write_dl3dv_scene` (the experiments' fixture): zip, directory and benchmark forms
  give back the rendered cameras (capture intrinsics rescaled to the stored images) and pixels."""
  from scenes import write_dl3dv_scene

  from tokengs_jax.data.synthetic.generate import render_re10k_like_scene

  scene = render_re10k_like_scene(0, "train", 0, 18, 32, 4)
  write_dl3dv_scene(tmp_path / "flat" / "z.zip", scene)
  write_dl3dv_scene(tmp_path / "flat" / "d", scene, capture_scale=3)
  write_dl3dv_scene(tmp_path / "flat" / "b.zip", scene, benchmark=True)
  source = DL3DVSceneSource(tmp_path / "flat")
  assert source.keys == ["b", "d", "z"] and source.frame_counts() == {"b": 4, "d": 4, "z": 4}
  for index in range(3):
    record = source[index]
    np.testing.assert_allclose(record["c2w"], scene["c2w"], atol=1e-6)
    np.testing.assert_allclose(record["intrinsics"], scene["intrinsics"], rtol=1e-6)
    np.testing.assert_array_equal(_frame(record, 2), scene["images"][2])


def test_a_data_folder_splits_into_training_and_held_out_scenes(tmp_path):
  files = _scene_files()
  for key in ("a", "b", "c"):
    _write_zip(tmp_path / "one" / f"{key}.zip", key, files)
  index = tmp_path / "index.json"
  index.write_text(json.dumps([{"scene_name": "b", "fold_8_kmeans_16_input": [0]}]))
  assert data_folder_format(tmp_path / "one") == "zips"
  assert dl3dv_split(tmp_path / "one") == (tmp_path / "one", tmp_path / "one")
  assert dl3dv_training_source(tmp_path / "one", held_out_index=index).keys == ["a", "c"]
  with pytest.raises(DL3DVError, match="name the held-out ones"):
    dl3dv_held_out_root(tmp_path / "one", indexed=False)
  assert dl3dv_held_out_root(tmp_path / "one", indexed=True) == tmp_path / "one"
  _write_zip(tmp_path / "split" / "train" / "1K" / "a.zip", "a", files)
  _write_zip(tmp_path / "split" / "train" / "2K" / "b.zip", "b", files)
  _write_dir(tmp_path / "split" / "test" / "b" / "gaussian_splat", files)  # also a training scene
  assert dl3dv_training_source(tmp_path / "split").keys == ["a"]
  with pytest.raises(DL3DVError, match="no training scene left once the 3 held-out"):
    dl3dv_training_source(tmp_path / "one", held_out_index=_index_of(tmp_path, "a", "b", "c"))
  (tmp_path / "chunks" / "test").mkdir(parents=True)
  (tmp_path / "chunks" / "test" / "index.json").write_text("{}")
  assert data_folder_format(tmp_path / "chunks") == "chunks"
  with pytest.raises(DL3DVError, match="neither pixelSplat chunks"):
    data_folder_format(tmp_path / "chunks" / "test")


def _index_of(tmp_path, *keys):
  path = tmp_path / "index_of.json"
  path.write_text(json.dumps({key: {"context": [0, 2], "target": [1]} for key in keys}))
  return path


def test_frame_counts_drop_an_unreadable_scene_and_count_it(tmp_path):
  files = _scene_files()
  _write_zip(tmp_path / "a.zip", "a", files)
  _write_zip(tmp_path / "b.zip", "b", {**files, "transforms.json": b"{broken"})
  source = DL3DVSceneSource(tmp_path, skip_bad=True)
  assert source.frame_counts() == {"a": FRAMES}
  assert source.keys == ["a"] and source.rejections.counts == {"bad_scene": 1}
