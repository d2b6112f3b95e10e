"""The shipped weights (experiments/pretrained/): intact, and exactly what the defaults load.

The commands that trained them (`python -m experiments.re10k run pretrain` then `run finetune`,
`python -m experiments.kubric run pretrain`) run at a small scale in `tests/test_re10k.py`
(`test_entry_point_end_to_end`, which also ships its output the same way) and
`tests/test_kubric_entry_point.py` (`test_kubric_entry_point_end_to_end`, which starts from static
weights as the Kubric one does).
"""

import dataclasses
import json
import pathlib

import jax
import pytest

from experiments import kubric, re10k, weights
from experiments.config import PRETRAINED_KUBRIC, PRETRAINED_SYNTHETIC, PRETRAINED_SYNTHETIC_128
from tokengs_jax import model

TOKENGS_AND_PIXEL_ALIGNED = {"params.msgpack", "pixel_aligned.msgpack"}
# (presets, shipped folder, the files it holds, the presets that trained them in order) of each
# default's weights
SHIPPED = {
  "re10k": (
    re10k.PRESETS,
    PRETRAINED_SYNTHETIC,
    TOKENGS_AND_PIXEL_ALIGNED,
    ("pretrain", "finetune"),
  ),
  "kubric": (
    kubric.PRESETS,
    PRETRAINED_KUBRIC,
    {"params.msgpack", "static_only.msgpack"},
    ("pretrain",),
  ),
}
# shipped folder -> the files it holds, the Kubric default's static base included
FOLDERS = {folder: files for _, folder, files, _ in SHIPPED.values()} | {
  PRETRAINED_SYNTHETIC_128: TOKENGS_AND_PIXEL_ALIGNED
}
REPO = pathlib.Path(__file__).resolve().parent.parent
# recorded fields the trained weights do not depend on: where a run wrote, and how often it saved
NOT_WEIGHT_FIELDS = {"output_dir", "synthetic_dir", "train.checkpoint_every"}


def _provenance(folder: pathlib.Path) -> dict:
  return json.loads((folder / "provenance.json").read_text())


@pytest.fixture(scope="module", params=sorted(SHIPPED))
def shipped(request):
  presets, folder, files, stages = SHIPPED[request.param]
  return presets, folder, files, _provenance(folder), stages


@pytest.mark.parametrize("folder", sorted(FOLDERS), ids=lambda folder: folder.name)
def test_shipped_files_match_their_recorded_digests(folder):
  provenance = _provenance(folder)
  assert set(provenance["files"]) == FOLDERS[folder]
  for name, digest in provenance["files"].items():
    assert weights.sha256(folder / name) == digest, name
  for name, record in provenance.get("carried_over", {}).items():
    assert record["sha256"] == provenance["files"][name] and record["command"], name


def _recorded_fields_differing(recorded: dict, expected: dict, prefix: str = "") -> list[str]:
  """Fields of `recorded` whose value differs in `expected` (fields added to the settings since
  the weights were trained are absent from `recorded`, and not compared)."""
  differing = []
  for name, value in recorded.items():
    if isinstance(value, dict) and isinstance(expected.get(name), dict):
      differing += _recorded_fields_differing(value, expected[name], f"{prefix}{name}.")
    elif name not in expected or value != expected[name]:
      differing.append(prefix + name)
  return differing


def _in_repository(path: str | None) -> str | None:
  """A recorded path inside the checkout that wrote it, relative to that checkout's root; for
  shipped weights since moved, where they are now (their folder's provenance says `moved_from`)."""
  if path is None:
    return None
  parts = pathlib.PurePath(path).parts
  path = pathlib.PurePath(*parts[parts.index("experiments") :])
  for folder in FOLDERS:
    if _provenance(folder).get("moved_from") == str(path.parent):
      return str(folder.relative_to(REPO) / path.name)
  return str(path)


def _assert_recorded_as(provenance: dict, preset, *, checkpoint_by_path: bool = True) -> None:
  """The recorded experiment is `preset`, apart from NOT_WEIGHT_FIELDS and how it evaluated, which
  the weights do not depend on; a starting checkpoint in the repository is compared by its path
  there (unless `checkpoint_by_path` is False: a later stage, whose start is checked by its
  record instead), and a record older than a setting is upgraded as it is on loading."""
  recorded = dict(provenance["experiment"])
  # an older record reads as its class reads it (`config.from_fields`)
  recorded = getattr(type(preset), "upgrade_record", lambda fields: fields)(recorded)
  checkpoint = recorded.pop("checkpoint")
  if checkpoint_by_path:
    assert _in_repository(checkpoint) == _in_repository(preset.checkpoint)
  recorded.pop("eval")
  expected = json.loads(json.dumps(dataclasses.asdict(preset)))
  assert set(_recorded_fields_differing(recorded, expected)) <= NOT_WEIGHT_FIELDS


def test_shipped_weights_come_from_their_presets_stage_by_stage(shipped):
  """Each stage is recorded as its preset (`_assert_recorded_as`), the earlier stage under the
  later one's `started_from` (`experiments.weights.ship`), so the presets reproduce the weights;
  a later preset starts from the earlier one's output, and the last stage's model is the one the
  default loads them into."""
  presets, _, _, provenance, stages = shipped
  for earlier, later in zip(stages, stages[1:]):
    assert presets[later].checkpoint == f"{presets[earlier].output_dir}/params.msgpack"
  record = provenance
  for stage in reversed(stages[1:]):
    _assert_recorded_as(record, presets[stage], checkpoint_by_path=False)
    assert pathlib.PurePath(record["experiment"]["checkpoint"]).name == "params.msgpack"
    record = record["started_from"]
  first = presets[stages[0]]
  _assert_recorded_as(record, first)
  assert first.checkpoint is None or (REPO / _in_repository(first.checkpoint)).exists()
  assert presets[stages[-1]].model == presets["synthetic-tiny"].model


def test_the_kubric_static_base_is_the_re10k_recipe_at_its_128_tokens():
  pretrain = re10k.PRESETS["pretrain"]
  at_128 = dataclasses.replace(pretrain, model=pretrain.model.replace(num_gs_tokens=128))
  assert at_128.checkpoint is None
  _assert_recorded_as(_provenance(PRETRAINED_SYNTHETIC_128), at_128)
  kubric_pretrain = kubric.PRESETS["pretrain"]
  assert kubric_pretrain.checkpoint == str(PRETRAINED_SYNTHETIC_128 / "params.msgpack")
  static = kubric_pretrain.model.replace(
    num_input_views=2, num_dynamic_gs_tokens=0, time_embedding=False
  )
  assert static == at_128.model


def test_default_starts_from_the_shipped_weights_with_nothing_fresh(shipped):
  presets, folder, files, _, _ = shipped
  default = presets["synthetic-tiny"]
  assert default.checkpoint == str(folder / "params.msgpack")
  configs = {"params.msgpack": default.model}
  if "static_only.msgpack" in files:  # the Kubric static-only model of the same budget
    tokens = default.model.num_gs_tokens + default.model.num_dynamic_gs_tokens
    configs["static_only.msgpack"] = default.model.replace(
      num_gs_tokens=tokens, num_dynamic_gs_tokens=0
    )
  for name, config in configs.items():
    loaded = weights.load_params(folder / name)
    expected = jax.eval_shape(lambda c=config: model.init_params(jax.random.key(0), c))
    assert jax.tree.structure(loaded) == jax.tree.structure(expected), name
    for got, want in zip(jax.tree.leaves(loaded), jax.tree.leaves(expected), strict=True):
      assert got.shape == want.shape and got.dtype == want.dtype, name
