"""experiments/data.py: synthetic sets (reused only under their settings, published whole),
evaluation scenes and indexes, novel targets, and training batches (depths, the split across
processes). Named `test_experiments_data` as `test_data_*` are the tests of `tokengs_jax.data`."""

import collections
import dataclasses
import json

import jax
import numpy as np
import pytest

from experiments import data, re10k, tasks
from small_experiments import small_smoke as _small_smoke
from small_experiments import tiny_kubric as _tiny_kubric


def _one_scene_smoke(tmp_path):
  """The smoke preset on one training and one test scene under `tmp_path / "data"`."""
  smoke = re10k.PRESETS["smoke"]
  return dataclasses.replace(
    smoke,
    synthetic_dir=str(tmp_path / "data"),
    synthetic=dataclasses.replace(smoke.synthetic, num_train=1, num_test=1, workers=1),
  )


def test_evaluation_scenes_read_a_list_format_index(tmp_path):
  """A Long-LRM list index (official DL3DV eval form): its context list, every frame a target."""
  experiment = _one_scene_smoke(tmp_path)
  data.ensure_synthetic(experiment)
  key = data.evaluation_scenes(experiment)[0][0]
  index = tmp_path / "index.json"
  index.write_text(json.dumps([{"scene_name": key, "fold_8_kmeans_2_input": [1, 7]}]))
  ((got_key, batch),) = data.evaluation_scenes(
    dataclasses.replace(experiment, eval_index=str(index))
  )
  assert got_key == key
  frames = experiment.synthetic.frames
  assert batch["context_images"].shape[1] == 2 and batch["target_images"].shape[1] == frames
  for view, frame in enumerate([1, 7]):  # the listed inputs are frames 1 and 7 of the targets
    np.testing.assert_array_equal(
      batch["context_images"][0, view], batch["target_images"][0, frame]
    )
  # the batch names its frames (the nearest-view baseline reads them)
  np.testing.assert_array_equal(batch["context_frames"], [[1, 7]])
  np.testing.assert_array_equal(batch["target_frames"], [np.arange(frames)])
  with pytest.raises(ValueError, match="fold_8_kmeans_3_input"):
    data.evaluation_scenes(dataclasses.replace(experiment, eval_index=str(index)).with_views(3))


def test_a_synthetic_set_written_with_other_settings_is_not_reused(tmp_path):
  experiment = _one_scene_smoke(tmp_path)
  root = data.ensure_synthetic(experiment)
  assert data.ensure_synthetic(experiment) == root  # same settings: reused
  other_walk = dataclasses.replace(
    experiment.synthetic, walk=dataclasses.replace(experiment.synthetic.walk, pitch=(0.0, 0.0))
  )
  for changed in (
    dataclasses.replace(experiment, synthetic=other_walk),
    dataclasses.replace(experiment, seed=1),
  ):
    with pytest.raises(ValueError, match="other settings.*another --synthetic-dir"):
      data.ensure_synthetic(changed)
  (root / "generator.json").unlink()  # a set from before the settings were recorded
  with pytest.raises(ValueError, match="not recorded"):
    data.ensure_synthetic(experiment)


def test_an_index_matching_no_scene_fails_before_any_work_and_lists_unknown_keys(tmp_path):
  experiment = _one_scene_smoke(tmp_path)
  data.ensure_synthetic(experiment)
  key = data.evaluation_scenes(experiment)[0][0]
  index = tmp_path / "index.json"
  index.write_text(json.dumps({"nope": {"context": [0, 4], "target": [2]}}))
  with pytest.raises(ValueError, match=f"none of its 1 scenes is in the data.*'nope'.*'{key}'"):
    data.check_evaluation_data(dataclasses.replace(experiment, eval_index=str(index)))
  index.write_text(
    json.dumps(
      {"nope": {"context": [0, 4], "target": [2]}, key: {"context": [0, 4], "target": [2]}}
    )
  )
  partial = dataclasses.replace(experiment, eval_index=str(index))
  assert data.check_evaluation_data(partial) == {
    "requested": 2,
    "evaluated": 1,
    "missing": ["nope"],
  }
  assert [k for k, _ in data.evaluation_scenes(partial)] == [key]
  index.write_text(json.dumps({key: {"context": [0, 4], "target": [99]}}))
  with pytest.raises(ValueError, match="frame 99"):
    data.check_evaluation_data(dataclasses.replace(experiment, eval_index=str(index)))


def test_novel_targets_are_inside_the_span_and_never_inputs():
  np.testing.assert_array_equal(data.novel_targets(np.array([0, 12]), 3), [1, 6, 11])
  targets = data.novel_targets(np.array([0, 5, 11, 16]), 4)
  assert not set(targets.tolist()) & {0, 5, 11, 16} and targets.min() > 0 and targets.max() < 16
  with pytest.raises(ValueError, match="widen"):
    data.novel_targets(np.array([0, 2]), 2)


def test_default_evaluation_scores_no_input_view_as_a_target(tmp_path):
  """Without an index, every evaluated target is a frame that is not an input."""
  smoke = re10k.PRESETS["smoke"]
  experiment = dataclasses.replace(
    smoke,
    synthetic_dir=str(tmp_path / "data"),
    synthetic=dataclasses.replace(smoke.synthetic, num_train=1, num_test=2, workers=1),
  )
  data.ensure_synthetic(experiment)
  for _, batch in data.evaluation_scenes(experiment):
    context, target = batch["context_frames"][0], batch["target_frames"][0]
    assert len(target) == smoke.eval.num_target_views
    assert not set(target.tolist()) & set(context.tolist())
    assert context.min() < target.min() and target.max() < context.max()


def test_generated_sets_are_published_whole_and_the_first_copy_kept(tmp_path):
  """Processes racing to write the same synthetic set never leave a partial or mixed one."""
  root = tmp_path / "set"

  def writer(content):
    def write(staging):
      (staging / "test").mkdir(parents=True)
      (staging / "test" / "index.json").write_text(content)

    return write

  data._publish(root, ("test",), writer("first"))
  data._publish(root, ("test",), writer("second"))
  assert (root / "test" / "index.json").read_text() == "first"
  assert sorted(p.name for p in tmp_path.iterdir()) == ["set"]  # no staging folder left


@pytest.mark.parametrize("entry_point", ["re10k", "kubric"])
def test_a_batch_that_does_not_split_evenly_across_processes_is_rejected(
  tmp_path, monkeypatch, entry_point
):
  """Both entry points split the global batch with one check, before any data is written."""
  from experiments.kubric_task import KubricTask

  monkeypatch.setattr(jax, "process_count", lambda: 3)
  if entry_point == "kubric":
    task, experiment = KubricTask(), _tiny_kubric(tmp_path)
  else:
    task, experiment = tasks.Task(), _small_smoke(tmp_path)
  experiment = dataclasses.replace(
    experiment, train=dataclasses.replace(experiment.train, batch_size=4)
  )
  with pytest.raises(ValueError, match="batch_size 4 is not divisible by 3 processes"):
    task.training_batches(experiment)
  assert not (tmp_path / "data").exists()
  assert data.local_batch_size(6) == 2


def test_training_batches_carry_true_depths_for_the_depth_loss(tmp_path):
  smoke = re10k.PRESETS["smoke"]
  experiment = _small_smoke(tmp_path, lambda_depth=0.1)
  batch = next(iter(data.training_batches(experiment)))
  depths = batch["target_depths"]
  assert depths.shape == batch["target_images"].shape[:-1]
  # Scaled as the cameras (translation scale 0.25): closed rooms of a few metres.
  assert (depths > 0).all() and 0.05 < float(depths.mean()) < 2.0
  assert tasks.Task().loss_config(experiment).lambda_depth == 0.1
  plain = dataclasses.replace(experiment, train=smoke.train)
  assert "target_depths" not in next(iter(data.training_batches(plain)))


def test_a_data_mode_mix_trains_on_each_dataset_repeat_times_an_epoch(tmp_path):
  """`data_mode` (official): two RE10K-format chunk folders, the second as DL3DV repeated 3
  times, make the training source; an epoch holds every scene of each that many times, and a
  few smoke training steps run on the mix (evaluation data: `--data-dir`, the first folder)."""
  from chunk_scenes import chunk_scene, write_chunk_set
  from tokengs_jax.data import mixing

  for name in ("first", "second"):  # 30 frames: RE10K's sampler spans 25+ frames
    scenes = [chunk_scene(f"{name}{i}", frames=30, height=16, width=24, seed=i) for i in range(2)]
    write_chunk_set(tmp_path / name / "train", scenes)
    write_chunk_set(tmp_path / name / "test", scenes[:1])
  smoke = re10k.PRESETS["smoke"]
  experiment = dataclasses.replace(
    smoke,
    data_dir=str(tmp_path / "first"),
    output_dir=str(tmp_path / "out"),
    data_mode=(f"re10k:1:{tmp_path / 'first'}", f"dl3dv_scaled_0.5:3:{tmp_path / 'second'}"),
    train=dataclasses.replace(smoke.train, steps=2, batch_size=4, log_image_every=0),
  )
  pipeline = data.training_batches(experiment)
  source = pipeline.source
  assert isinstance(source, mixing.MixedSource)
  assert source.counts() == {"re10k_scaled_0.25": 2, "dl3dv_scaled_0.5": 6}
  assert [source.example_config(i, None).translation_scale for i in (0, 7)] == [0.25, 0.5]
  batches = iter(pipeline)
  epoch = [int(i) for _ in range(len(source) // 4) for i in next(batches)["scene_index"]]
  assert collections.Counter(source.locate(i) for i in epoch) == {
    (0, 0): 1,
    (0, 1): 1,
    (1, 0): 3,
    (1, 1): 3,
  }
  tasks.execute("train", experiment)
  history = json.loads((tmp_path / "out" / "train_history.json").read_text())
  losses = [entry["loss"] for entry in history if "loss" in entry]
  assert len(losses) == 2 and all(np.isfinite(losses))
