"""experiments.results: metrics.json / metrics.md, process-0 writes, grids, safe file names."""

import json
import re

import jax
import numpy as np
import pytest

from experiments import figures, results
from tokengs_jax import evaluation, export


def _evaluation(per_scene: dict[str, list[dict]]) -> evaluation.Evaluation:
  return evaluation.Evaluation(
    {name: evaluation.MethodScores(per_scene=rows) for name, rows in per_scene.items()}, kept=[]
  )


def test_write_metrics_means_over_scenes_markdown_and_checks(tmp_path):
  primary = _evaluation(
    {
      "mean_colour": [
        {"key": "a", "psnr": 8.0, "ssim": 0.1},
        {"key": "b", "psnr": 9.0, "ssim": 0.2},
      ],
      "nearest_view": [
        {"key": "a", "psnr": 16.0, "ssim": 0.5},
        {"key": "b", "psnr": 17.0, "ssim": 0.5},
      ],
      "trained": [{"key": "a", "psnr": 10.0, "ssim": 0.5}, {"key": "b", "psnr": 20.0, "ssim": 0.7}],
    }
  )
  other = _evaluation(
    {
      "nearest_view": [{"key": "c", "psnr": 12.0, "ssim": 0.3}],
      "trained": [{"key": "c", "psnr": 14.0, "ssim": 0.4}],
    }
  )
  payload = results.write_metrics(tmp_path, {"test": primary, "ood": other}, {"title": "t"})
  assert payload["test_sets"] == ["test", "ood"]
  assert payload["metrics"]["trained"]["mean"]["psnr"] == pytest.approx(15.0)
  written = json.loads((tmp_path / "metrics.json").read_text())
  assert written["metrics"]["mean_colour"]["mean"]["ssim"] == pytest.approx(0.15)
  assert written["other_test_sets"]["ood"]["metrics"]["trained"]["mean"]["psnr"] == 14.0
  assert written["checks"]["trained beats nearest_view"].startswith("False (PSNR margin -1.500")
  assert written["other_test_sets"]["ood"]["checks"]["trained beats nearest_view"].startswith(
    "True"
  )
  text = (tmp_path / "metrics.md").read_text()
  assert "| trained | 15.0000 | 0.6000 |" in text
  assert "trained beats mean_colour: True (PSNR margin +6.500 dB)" in text
  assert "## Test set `ood`" in text and "| trained | 14.0000 | 0.4000 |" in text


def test_write_metrics_survives_a_method_that_scored_no_scene(tmp_path):
  """An evaluation that matched nothing for a method says so instead of crashing."""
  scored = _evaluation({"trained": [], "nearest_view": [{"key": "a", "psnr": 9.0}]})
  payload = results.write_metrics(tmp_path, {"test": scored}, {"title": "t"})
  assert payload["metrics"]["trained"]["mean"] == {}
  assert payload["checks"] == {}
  assert "Scored no scene: trained." in (tmp_path / "metrics.md").read_text()
  assert "Scored no scene" in results.summary_text({"test": scored})


def test_only_process_zero_writes_results(tmp_path, monkeypatch):
  monkeypatch.setattr(jax, "process_index", lambda: 1)
  scored = _evaluation({"trained": [{"key": "a", "psnr": 9.0}]})
  payload = results.write_metrics(tmp_path / "out", {"test": scored}, {"title": "t"})
  assert payload["metrics"]["trained"]["mean"]["psnr"] == 9.0  # computed everywhere
  assert results.tensorboard_writer(tmp_path / "out") is None
  entry = {
    "key": "s",
    "batch": {
      "context_images": np.zeros((1, 2, 16, 16, 3)),
      "target_images": np.zeros((1, 1, 16, 16, 3)),
    },
    "trained": {"rgb": np.zeros((1, 16, 16, 3)), "depth": None, "alpha": None},
  }
  assert results.write_grids(tmp_path / "out" / "grids", [entry], ["trained"]) == []
  assert not (tmp_path / "out").exists()


def _kept_scene(rng, **methods) -> dict:
  """A kept scene (as `evaluation.evaluate` keeps one) of two 16x16 inputs and targets, with
  these methods' predictions."""
  images = {f"{kind}_images": rng.uniform(size=(1, 2, 16, 16, 3)) for kind in ("context", "target")}
  return {"key": "s", "batch": images, **methods}


def _rendered(rng) -> dict:
  """A method's renders of `_kept_scene`'s two targets: rgb, depth in [1, 3], alpha 1."""
  depth = rng.uniform(1.0, 3.0, size=(2, 16, 16, 1)).astype(np.float32)
  return {"rgb": rng.uniform(size=(2, 16, 16, 3)), "depth": depth, "alpha": np.ones_like(depth)}


def test_scene_grid_is_readable_upscaled_labelled_with_a_depth_colour_bar():
  rng = np.random.default_rng(0)
  entry = _kept_scene(
    rng,
    nearest_view={"rgb": rng.uniform(size=(2, 16, 16, 3)), "depth": None, "alpha": None},
    trained=_rendered(rng),
  )
  depth = entry["trained"]["depth"]
  grid = results.scene_grid(entry, ["nearest_view", "trained"])
  # five rows (inputs, targets, two methods, depth) of 16-px views upscaled 8x to 128 px
  assert grid.dtype == np.uint8 and grid.shape[0] >= 5 * 128
  no_labels = figures.labelled_grid([("", [np.zeros((16, 16, 3))])])
  labels = figures.labelled_grid([("nearest_view", [np.zeros((16, 16, 3))])])
  assert labels.shape[1] > no_labels.shape[1]  # the label column holds the text
  assert (labels[:, :40] < 128).any()  # dark text left of the cells
  # the depth row carries a colour bar: the ramp from near (top, t = 1) to far (bottom, t = 0)
  rows = [("depth", [export.colorize_depth(depth[0])])]
  assert (
    figures.labelled_grid(rows, depth_range=(1.0, 3.0)).shape[1]
    > figures.labelled_grid(rows).shape[1]
  )
  bar = np.asarray(figures._colour_bar(128, (1.0, 3.0), figures._font()))
  np.testing.assert_array_equal(bar[0, 0], export.to_uint8(export.depth_ramp(1.0)))
  np.testing.assert_array_equal(bar[-1, 0], export.to_uint8(export.depth_ramp(0.0)))


def test_training_pictures_are_the_grid_and_histograms_of_the_first_set(tmp_path):
  """`write_training_pictures` (`train.log_image_every`): at each step, the scene's grid as
  `train/images` and histograms of its first Gaussian set (a dynamic model's [1, Vt] sets: the
  first target's time) without their non-finite values, read back from the event file."""
  import io

  from PIL import Image
  from tensorboard_events import summaries
  from tensorboardX import SummaryWriter

  from tokengs_jax.gaussians import Gaussians

  rng = np.random.default_rng(0)
  n = 12
  means = rng.normal(size=(1, 2, n, 3)).astype(np.float32)
  means[0, 0, 0, 0] = np.nan  # a broken Gaussian: left out of the distances, not fatal
  scales = rng.uniform(0.01, 0.5, size=(1, 2, n, 3)).astype(np.float32)
  gaussians = Gaussians(
    means=means,
    opacities=rng.uniform(size=(1, 2, n)).astype(np.float32),
    scales=scales,
    quats=rng.normal(size=(1, 2, n, 4)).astype(np.float32),
    colors=rng.uniform(size=(1, 2, n, 3)).astype(np.float32),
  )
  entry = _kept_scene(rng, prediction={**_rendered(rng), "gaussians": gaussians})
  writer = SummaryWriter(str(tmp_path))
  for step in (3, 6):
    results.write_training_pictures(writer, entry, "prediction", step)
  writer.close()
  read = summaries(tmp_path)
  names = ("opacity", "log_scale", "distance")
  assert read.keys() == {"train/images"} | {f"gaussian/{name}" for name in names}
  assert all(sorted(steps) == [3, 6] for steps in read.values())
  image = read["train/images"][6].image
  decoded = np.asarray(Image.open(io.BytesIO(image.encoded_image_string)))
  np.testing.assert_array_equal(decoded, results.scene_grid(entry, ["prediction"]))
  distances = np.linalg.norm(means[0, 0, 1:], axis=-1)
  opacity, log_scale, distance = (read[f"gaussian/{name}"][3].histo for name in names)
  assert (opacity.num, log_scale.num, distance.num) == (n, 3 * n, n - 1)
  assert opacity.sum == pytest.approx(gaussians.opacities[0, 0].sum(), rel=1e-5)
  np.testing.assert_allclose(np.diff(opacity.bucket_limit), 0.02)  # fixed bins of [0, 1]
  assert log_scale.min == pytest.approx(np.log(scales[0, 0].min()), rel=1e-5)
  assert (distance.min, distance.max) == pytest.approx((distances.min(), distances.max()))


def test_names_from_data_become_safe_distinct_file_names_inside_their_folder(tmp_path):
  keys = ["scene-01.v2", "/abs/x", "../../x", "..", "", "a b", "a_b", ".hidden", "é" * 300]
  names = [results.safe_file_name(key) for key in keys]
  assert names[0] == "scene-01.v2"  # a plain key is its own name
  assert len(set(names)) == len(keys)  # "a b" and "a_b" too
  assert all(re.fullmatch(r"[A-Za-z0-9_+-][A-Za-z0-9._+-]{0,140}", name) for name in names)
  assert results.data_path(tmp_path / "grids", "../../x", ".png").parent == tmp_path / "grids"
  (tmp_path / "grids").mkdir()
  (tmp_path / "grids" / "s.png").symlink_to(tmp_path / "elsewhere.png")
  with pytest.raises(ValueError, match="outside"):
    results.data_path(tmp_path / "grids", "s", ".png")
