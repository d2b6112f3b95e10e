"""tokengs_jax/data/mixing.py: several scene sources as one (the official `data_mode`): each
part's scenes `repeat` times per epoch, its own example settings, a deterministic and sharded
order through `InputPipeline`, and the `NAME:REPEAT:FOLDER` entries with their refusals."""

import collections
import dataclasses

import numpy as np
import pytest

from chunk_scenes import chunk_scene, write_chunk_set
from tokengs_jax.data import (
  DATASET_PRESETS,
  BoundedSamplerConfig,
  ExampleConfig,
  InputPipeline,
  NoUsableExamplesError,
  mixing,
)

SAMPLER = BoundedSamplerConfig(2, 2, 2, 4, 0, 0, 2, 4)
CONFIG = ExampleConfig((8, 12), SAMPLER, 0.25, random_flip=False)


def _records(prefix, count, frames=6):
  return [
    chunk_scene(f"{prefix}{i}", frames=frames, height=8, width=12, seed=i) for i in range(count)
  ]


def _mix(repeats=(1, 3), scales=(0.25, 1.0), sizes=(3, 2)):
  return mixing.MixedSource(
    [
      mixing.MixPart(
        _records(name, size), repeat, dataclasses.replace(CONFIG, translation_scale=s), name
      )
      for name, size, repeat, s in zip("ab", sizes, repeats, scales)
    ]
  )


def _epoch(source, **kwargs):
  """Every example of one epoch of `source`, in order: (part, scene in part, example)."""
  kwargs = {
    "batch_size": 1,
    "seed": 0,
    "num_epochs": 1,
    "shard_index": 0,
    "shard_count": 1,
  } | kwargs
  pipeline = InputPipeline(source, CONFIG, drop_remainder=False, **kwargs)
  examples = []
  for batch in pipeline:
    for i, index in enumerate(batch["scene_index"]):
      examples.append((*source.locate(int(index)), {k: v[i] for k, v in batch.items()}))
  return examples


def test_an_epoch_holds_each_parts_scenes_exactly_repeat_times_in_a_mixed_order():
  source = _mix(repeats=(1, 3))
  assert len(source) == 3 * 1 + 2 * 3
  assert source.counts() == {"a": 3, "b": 6}
  # the official `sample_list * num_repeat`: part b's block is its scenes over and over
  assert [source.locate(i) for i in range(len(source))] == [(0, 0), (0, 1), (0, 2)] + [
    (1, s) for s in (0, 1, 0, 1, 0, 1)
  ]
  epoch = _epoch(source)
  seen = collections.Counter((part, scene) for part, scene, _ in epoch)
  assert seen == {(0, 0): 1, (0, 1): 1, (0, 2): 1, (1, 0): 3, (1, 1): 3}
  parts = [part for part, _, _ in epoch]
  assert parts != sorted(parts)  # shuffled across the parts: a batch can mix datasets
  assert source[3]["key"] == source[5]["key"] == "b0"


def test_each_part_builds_its_examples_with_its_own_settings():
  """Two parts of the same scenes, translation scales 0.25 and 1.0: the same example (fixed views,
  no flip) has 4x the camera translations from the second part; other scenes are not touched."""
  scenes = _records("s", 2)
  deterministic = dataclasses.replace(CONFIG, deterministic=True)
  source = mixing.MixedSource(
    [
      mixing.MixPart(scenes, 1, dataclasses.replace(deterministic, translation_scale=s), str(s))
      for s in (0.25, 1.0)
    ]
  )
  by_scene = collections.defaultdict(dict)
  for part, scene, example in _epoch(source):
    by_scene[scene][part] = example
  for examples in by_scene.values():
    small, large = examples[0], examples[1]
    for key in ("context_c2w", "target_c2w"):
      np.testing.assert_allclose(large[key][..., :3, 3], 4 * small[key][..., :3, 3], rtol=1e-5)
      np.testing.assert_allclose(large[key][..., :3, :3], small[key][..., :3, :3])
      assert np.abs(small[key][..., :3, 3]).max() > 0
    np.testing.assert_array_equal(large["target_images"], small["target_images"])
  # a part without a config takes the pipeline's
  plain = mixing.MixedSource([mixing.MixPart(scenes, 2)])
  assert plain.example_config(3, CONFIG) is CONFIG


def test_the_order_is_fixed_by_the_seed_and_shards_split_it():
  source = _mix()
  order = [(p, s) for p, s, _ in _epoch(source)]
  again = _epoch(source)
  assert [(p, s) for p, s, _ in again] == order
  first = _epoch(source)[0][2]
  np.testing.assert_array_equal(again[0][2]["context_c2w"], first["context_c2w"])
  assert [(p, s) for p, s, _ in _epoch(source, seed=1)] != order
  shards = [_epoch(source, shard_index=i, shard_count=2) for i in range(2)]
  indices = [int(e["scene_index"]) for shard in shards for _, _, e in shard]
  assert sorted(indices) == list(range(len(source)))  # disjoint, and together the whole mix


def test_parts_that_cannot_share_a_batch_or_are_empty_are_refused():
  scenes = _records("s", 2)
  more_targets = dataclasses.replace(
    CONFIG, sampler=dataclasses.replace(SAMPLER, num_target_views=3)
  )
  with pytest.raises(ValueError, match="one shape"):
    mixing.MixedSource(
      [mixing.MixPart(scenes, 1, CONFIG, "a"), mixing.MixPart(scenes, 1, more_targets, "b")]
    )
  with pytest.raises(ValueError, match="at least one part"):
    mixing.MixedSource([])
  with pytest.raises(NoUsableExamplesError, match="part 1 .empty. has no scenes"):
    mixing.MixedSource([mixing.MixPart(scenes), mixing.MixPart([], 1, None, "empty")])
  for repeat in (0, -1, 1.5, True):
    with pytest.raises(ValueError, match="repeat must be an integer >= 1"):
      mixing.MixPart(scenes, repeat)
  with pytest.raises(IndexError):
    _mix()[len(_mix())]


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
  """Two chunk folders (`train/` + `test/`): 3 scenes and 2 scenes of 12 frames."""
  root = tmp_path_factory.mktemp("mix")
  made = {}
  for name, count in (("first", 3), ("second", 2)):
    scenes = [chunk_scene(f"{name}{i}", frames=12, seed=i) for i in range(count)]
    write_chunk_set(root / name / "train", scenes)
    write_chunk_set(root / name / "test", scenes[:1])
    made[name] = root / name
  return made


def test_entries_read_official_names_repeat_counts_and_folders(folders):
  entry = mixing.parse_data_mode(f"dl3dv_scaled_0.15:6:{folders['first']}")
  assert (entry.dataset, entry.translation_scale, entry.repeat) == ("dl3dv", 0.15, 6)
  assert (entry.folder, entry.format, entry.name) == (
    folders["first"],
    "chunks",
    "dl3dv_scaled_0.15",
  )
  default = mixing.parse_data_mode(f"re10k:1:{folders['second']}")
  assert default.translation_scale == 0.25 and default.name == "re10k_scaled_0.25"
  base = dataclasses.replace(DATASET_PRESETS["re10k"], image_shape=(16, 16), sampler=SAMPLER)
  config = entry.example_config(base)
  assert config.sampler.num_context_views == 2 and config.sampler.num_target_views == 2
  assert config.sampler.max_context_gap == DATASET_PRESETS["dl3dv"].sampler.max_context_gap
  assert config.translation_scale == 0.15 and config.image_shape == (16, 16)
  assert mixing.parse_dataset_name("re10k_scaled_2") == ("re10k", 2.0)


@pytest.mark.parametrize(
  "text, message",
  [
    ("re10k:1", "expected NAME:REPEAT:FOLDER"),
    ("re10k::{first}", "expected NAME:REPEAT:FOLDER"),
    ("scannet:1:{first}", "unknown dataset 'scannet'"),
    ("kubric_scaled_1.0:100:{first}", "Kubric is dynamic"),
    ("re10k_scaled_abc:1:{first}", "a number > 0"),
    ("re10k_scaled_0:1:{first}", "a number > 0"),
    ("re10k:0:{first}", "REPEAT must be an integer >= 1"),
    ("re10k:two:{first}", "REPEAT must be an integer >= 1"),
    ("re10k:1:{first}/missing", "no such folder"),
    ("re10k:1:{first}/train", "holds neither"),
  ],
)
def test_bad_entries_are_refused_naming_them(folders, text, message):
  text = text.format(first=folders["first"])
  with pytest.raises(ValueError, match=message) as error:
    mixing.parse_data_mode(text)
  assert "--data-mode" in str(error.value)


def test_a_chunk_folder_without_train_is_refused(folders, tmp_path):
  write_chunk_set(tmp_path / "test", [chunk_scene("t")])
  with pytest.raises(ValueError, match="no train/"):
    mixing.parse_data_mode(f"re10k:1:{tmp_path}")


def test_training_mix_reads_each_folders_train_split_with_its_settings(folders):
  base = dataclasses.replace(CONFIG, image_shape=(16, 16))
  source = mixing.training_mix(
    [
      f"re10k_scaled_0.5:1:{folders['first']}",
      mixing.parse_data_mode(f"dl3dv:2:{folders['second']}"),
    ],
    base,
  )
  assert source.counts() == {"re10k_scaled_0.5": 3, "dl3dv_scaled_0.15": 4}
  assert [source[i]["key"] for i in range(len(source))] == [
    "first0",
    "first1",
    "first2",
    "second0",
    "second1",
    "second0",
    "second1",
  ]
  assert source.example_config(0, base).translation_scale == 0.5
  assert source.example_config(6, base).translation_scale == 0.15
  assert not source.rejections
  wrapped = mixing.training_mix([f"re10k:1:{folders['first']}"], base, wrap=lambda s: [s[0]])
  assert len(wrapped) == 1
