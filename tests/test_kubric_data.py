"""experiments/kubric_data.py: the synthetic subsets (published whole, stamped, rewritten when
their settings change) and the scene sources."""

import dataclasses
import json
import shutil

import pytest

from experiments import kubric_data
from small_experiments import tiny_kubric as _tiny_kubric


def test_kubric_synthetic_subsets_are_published_whole_stamped_and_rewritten_when_changed(
  tmp_path, monkeypatch
):
  """Each subset goes through `data.ensure_generated_set`: reused under the same settings,
  written anew under others, never left half-written, and refused when it records none."""
  experiment = _tiny_kubric(tmp_path)
  root = kubric_data.data_root(experiment)
  assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]  # no staging folder left
  assert sorted(p.name for p in root.iterdir()) == ["test", "v0"]
  stamp = json.loads((root / "v0" / "generator.json").read_text())
  assert stamp["generator"] == "generate_kubric_like" and stamp["seed"] == experiment.seed
  for subset in ("v0", "test"):
    (root / subset / "kept").touch()
  kubric_data.data_root(experiment)  # the same settings: both subsets reused
  assert (root / "v0" / "kept").exists() and (root / "test" / "kept").exists()

  reseeded = dataclasses.replace(experiment, seed=experiment.seed + 1)
  kubric_data.data_root(reseeded)  # another seed: both subsets written anew, nothing left aside
  assert not (root / "v0" / "kept").exists() and not (root / "test" / "kept").exists()
  assert json.loads((root / "v0" / "generator.json").read_text())["seed"] == reseeded.seed
  assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]
  assert sorted(p.name for p in root.iterdir()) == ["test", "v0"]
  more = dataclasses.replace(
    reseeded, synthetic=dataclasses.replace(reseeded.synthetic, num_train=2)
  )
  assert len(kubric_data.scene_sources(more)[0]) == 2

  def interrupted(staging, subset, **arguments):
    (staging / subset / "scene_000000").mkdir(parents=True)
    raise RuntimeError("interrupted")

  shutil.rmtree(root / "v0")  # missing: the next call writes it
  monkeypatch.setattr(kubric_data, "generate_kubric_like", interrupted)
  with pytest.raises(RuntimeError, match="interrupted"):
    kubric_data.data_root(more)
  assert not (root / "v0").exists()  # the half-written subset was never published
  monkeypatch.undo()
  assert len(kubric_data.scene_sources(more)[0]) == 2
  assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]

  (root / "v0" / "generator.json").unlink()  # a subset from before the settings were recorded
  with pytest.raises(ValueError, match="not recorded.*another --synthetic-dir"):
    kubric_data.data_root(more)
  assert (root / "v0" / "scene_000000").exists()  # refused, not deleted
