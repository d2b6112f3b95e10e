"""experiments.dynamic_videos: the official Kubric videos (`render_kubric_dyn.py`) of the shipped
time-conditioned Kubric model on a small generated scene, and the Kubric evaluation writing them
(`KubricTask.extra_visuals`)."""

import dataclasses
import json

import numpy as np
import pytest

from experiments import dynamic_videos, weights
from experiments.config import PRETRAINED_KUBRIC
from experiments.kubric_data import kubric_example_config, scene_sources
from experiments.kubric_task import KubricTask
from small_experiments import tiny_kubric
from tokengs_jax import export

OFFICIAL_NAMES = [
  "01_gt_input",
  "02_gt_trajectory",
  "03_fixed_cam",
  "04_fixed_cam_dyn_only",
  "05_fixed_cam_static_only",
  "06_input_cams_hstack",
  "07_input_cams_hstack_dyn",
  "08_input_cams_hstack_static",
]


def test_video_views_are_the_official_ones():
  # official: input v is camera (g + v + 1) % C at frame round(v (F - 1) / (V - 1)); camera g
  # at every frame is shown (g = 0, F = 24, 9 cameras, 4 inputs)
  context, target = dynamic_videos.video_views(9, 24, 4)
  assert context.tolist() == [[1, 0], [2, 8], [3, 15], [4, 23]]
  assert target.tolist() == [[0, f] for f in range(24)]
  context, _ = dynamic_videos.video_views(4, 12, 4)  # the synthetic rig: camera 0 is an input
  assert context.tolist() == [[1, 0], [2, 4], [3, 7], [0, 11]]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
  """The shipped Kubric weights (128 static + 32 dynamic tokens: a random tiny model's Gaussians
  are not seen from the cameras) and the Kubric default (its 4-camera rig, 32x32) on one
  generated test scene of 6 frames; the video batch of its first 3 frames."""
  tmp_path = tmp_path_factory.mktemp("videos")
  experiment = tiny_kubric(tmp_path)
  synthetic = dataclasses.replace(experiment.synthetic, frames=6)  # the evaluation's views: 5
  experiment = dataclasses.replace(experiment, num_cameras=4, synthetic=synthetic)
  experiment = dataclasses.replace(experiment, model=experiment.model.replace(image_size=(32, 32)))
  task = KubricTask()
  _, test = scene_sources(experiment)
  params = weights.load_params(PRETRAINED_KUBRIC / "params.msgpack")
  config = kubric_example_config(experiment, training=False)
  batch = dynamic_videos.video_example(test[0], config, experiment.num_context_views, 3)
  return task, experiment, params, batch


def test_the_static_tokens_stand_still_and_the_full_render_changes_only_where_the_dynamic_are(
  scene,
):
  task, experiment, params, batch = scene
  assert batch["target_times"][0].tolist() == pytest.approx([0, 0.5, 1])  # 3 of the 4 frames
  c2w = np.repeat(batch["target_c2w"][0, :1], 3, 0)  # the fixed camera (03, 04, 05)
  intrinsics = np.repeat(batch["target_intrinsics"][0, :1], 3, 0)
  parts = dynamic_videos.render_path(
    params,
    experiment.model,
    task.objective(experiment),
    batch,
    c2w,
    intrinsics,
    np.float32([0, 0.5, 1]),
  )
  assert set(parts) == {"full", "dynamic", "static"}
  full, dynamic, static = (parts[name] for name in ("full", "dynamic", "static"))
  np.testing.assert_array_equal(np.diff(static.rgb, axis=0), 0)  # no time in the static tokens
  changed = np.abs(np.diff(full.rgb, axis=0)).max(axis=(0, -1))  # [H, W]
  assert changed.max() > 1e-3  # the dynamic Gaussians move: the fixed camera's frames differ
  # where no dynamic Gaussian is drawn at any time, the full render is the static tokens' alone
  absent = dynamic.alpha.max(axis=(0, -1)) < 1e-4
  assert 0 < absent.sum() < absent.size
  np.testing.assert_allclose(full.rgb[:, absent], static.rgb[:, absent], atol=1e-3)
  assert changed[absent].max() < 1e-3
  assert np.abs(full.rgb - static.rgb)[:, ~absent].max() > 0
  assert np.abs(full.rgb - dynamic.rgb).max() > 1e-2


def test_the_official_videos_their_frames_sizes_and_order(scene):
  task, experiment, params, batch = scene
  config = experiment.model
  videos = dynamic_videos.render_videos(params, config, task.objective(experiment), batch)
  assert list(videos) == OFFICIAL_NAMES
  for name, frames in videos.items():  # 32x32 views upscaled to 256; the strips: the 4 inputs
    width = 256 * (config.num_input_views if "hstack" in name else 1)
    assert frames.shape == (3, 256, width, 3) and frames.dtype == np.uint8, name
  # the data moves, and so do the dynamic tokens' Gaussians; the static ones' stand still
  for name in ("01_gt_input", "04_fixed_cam_dyn_only", "07_input_cams_hstack_dyn"):
    assert np.abs(np.diff(videos[name].astype(int), axis=0)).max() > 0, name
  for name in ("05_fixed_cam_static_only", "08_input_cams_hstack_static"):
    assert np.abs(np.diff(videos[name].astype(int), axis=0)).max() == 0, name
  # the trajectory starts at the fixed camera's pose and time, then follows the camera
  np.testing.assert_array_equal(videos["02_gt_trajectory"][0], videos["03_fixed_cam"][0])
  # the shown camera's frames as the data pipeline reads them, upscaled 8x
  gt = export.to_uint8(batch["target_images"][0])
  np.testing.assert_array_equal(videos["01_gt_input"][:, ::8, ::8], gt)
  # a strip's views are different input cameras
  strip = videos["06_input_cams_hstack"].astype(int)
  assert np.abs(strip[:, :, :256] - strip[:, :, 256:512]).max() > 0


@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")  # imageio's reader forks its ffmpeg
def test_the_kubric_evaluation_writes_the_videos_only_with_video_frames(
  scene, tmp_path, monkeypatch
):
  import imageio.v2 as imageio

  from experiments import dynamic_pictures

  task, experiment, params, _ = scene
  # the evaluation's other dynamic pictures are dynamic_pictures' (not these tests')
  monkeypatch.setattr(dynamic_pictures, "write_pictures", lambda *args: {})
  monkeypatch.setattr(dynamic_pictures, "scene_flow_report", lambda *args: {})
  config = experiment.model
  for frames, media_scenes in ((0, 1), (2, 1), (2, 0)):  # 0: every scene, each in its folder
    out = tmp_path / f"{frames}_{media_scenes}"
    run = dataclasses.replace(
      experiment,
      output_dir=str(out),
      eval=dataclasses.replace(experiment.eval, video_frames=frames, media_scenes=media_scenes),
    )
    examples = task.evaluation_scenes(run)
    visuals = task.extra_visuals(run, config, params, examples, None, 0)
    if frames == 0:
      assert "videos" not in visuals and not (out / "videos").exists()
      continue
    assert visuals["videos"]["failures"] == []
    json.dumps(visuals["videos"])  # metrics.json's
    key = examples[0][0]
    folder = out / "videos" / (key if media_scenes == 0 else "")
    written = visuals["videos"]["scenes"][key]
    assert written == [str((folder / f"{n}.mp4").relative_to(out)) for n in OFFICIAL_NAMES]
    for name in OFFICIAL_NAMES if media_scenes == 1 else ():
      reader = imageio.get_reader(out / "videos" / f"{name}.mp4")
      read = [frame for frame in reader]
      assert reader.get_meta_data()["fps"] == 8
      width = 256 * (config.num_input_views if "hstack" in name else 1)
      assert [frame.shape for frame in read] == [(256, width, 3)] * 2, name
