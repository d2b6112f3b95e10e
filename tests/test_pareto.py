"""benchmarks/pareto.py (issue 27): the run-time / error report, in its smallest form."""

import pathlib
import sys

import numpy as np
from PIL import Image

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent / "benchmarks"))

import pareto  # noqa: E402


def test_points_cover_every_choice_of_the_issue():
  """Every choice issue 27 names is a point, built the way the experiments build it (the methods
  are built only when measured: nothing runs here)."""
  from experiments import re10k, tasks, weights

  experiment = re10k.PRESETS["synthetic-tiny"]
  params = weights.load_params(experiment.checkpoint)
  found = pareto.points(tasks.Task(), experiment, params)
  assert [p.name for p in found] == [
    "feed-forward",
    *(f"token tuning {n}" for n in (5, 10, 25, 50, 100)),
    "Gaussian tuning 50",
    "joint tuning 50",
    *(f"{k} tokens" for k in (32, 64, 128, 256)),
    "bf16 matmuls",
    "bf16, token tuning 50",
    "skips",
    "skips, token tuning 50",
  ]
  assert set(pareto.QUICK_POINTS) <= {p.name for p in found}
  assert experiment.model.num_gs_tokens not in pareto.TOKEN_COUNTS  # that point is feed-forward


def test_one_gallery_two_points_write_the_table_and_the_chart(tmp_path):
  """One gallery, feed-forward with and without the skips: both rows (and the copy's) in the
  table, the same scores (the skips are exact), the chart written."""
  rows = pareto.main(
    ["--scenes", "1", "--points", "feed-forward", "skips", "--out", str(tmp_path / "docs"),
     "--synthetic-dir", str(tmp_path / "data")]
  )  # fmt: skip
  assert [r["method"] for r in rows] == ["feed-forward", "skips", pareto.COPY]
  ff, skips, _ = rows
  assert ff["psnr"] == skips["psnr"] and ff["lpips"] == skips["lpips"]
  assert all(np.isfinite(r[k]) for r in rows for k in ("psnr", "lpips", "seconds", "compile_s"))
  assert ff["seconds"] == ff["predict_s"] + ff["render_s"]  # one scene: the medians add up
  table = (tmp_path / "docs" / "pareto.md").read_text()
  for name in ("| feed-forward |", "| skips |", f"| {pareto.COPY} |", "Load average"):
    assert name in table
  assert "python benchmarks/pareto.py --scenes 1" in table
  from experiments import re10k

  default = re10k.PRESETS["synthetic-tiny"]
  assert f"the trained {default.model.num_gs_tokens}-token table" in table
  assert f"(lr {default.eval.tuning_learning_rate:g} tokens," in table
  image = np.asarray(Image.open(tmp_path / "docs" / "pareto.png"))
  assert image.shape == (pareto.PANEL[1] + 28, 2 * pareto.PANEL[0], 3)
  assert (image < 128).any()  # something is drawn
