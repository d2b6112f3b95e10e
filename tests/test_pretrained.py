"""The shipped weights (experiments/pretrained/): intact, and exactly what the defaults load.

The commands that trained them (`python -m experiments.re10k run pretrain`, `python -m
experiments.kubric run pretrain`) run at a small scale in `tests/test_re10k.py`
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
from experiments.config import PRETRAINED_KUBRIC, PRETRAINED_SYNTHETIC
from tokengs_jax import model

# (presets, shipped folder, the files it holds)
SHIPPED = {
  "re10k": (re10k.PRESETS, PRETRAINED_SYNTHETIC, {"params.msgpack", "pixel_aligned.msgpack"}),
  "kubric": (kubric.PRESETS, PRETRAINED_KUBRIC, {"params.msgpack", "static_only.msgpack"}),
}
REPO = pathlib.Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module", params=sorted(SHIPPED))
def shipped(request):
  presets, folder, files = SHIPPED[request.param]
  provenance = json.loads((folder / "provenance.json").read_text())
  return presets, folder, files, provenance


def test_shipped_files_match_their_recorded_digests(shipped):
  _, folder, files, provenance = shipped
  assert set(provenance["files"]) == files
  for name, digest in provenance["files"].items():
    assert weights.sha256(folder / name) == digest, name


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
  """A recorded path inside the checkout that wrote it, relative to that checkout's root."""
  if path is None:
    return None
  parts = pathlib.PurePath(path).parts
  return str(pathlib.PurePath(*parts[parts.index("experiments") :]))


def test_shipped_weights_come_from_the_pretrain_preset(shipped):
  """Its recorded experiment is the `pretrain` preset's (apart from where it wrote and how it
  evaluated, which the weights do not depend on; a starting checkpoint in the repository is
  compared by its path there, and a record older than a setting is upgraded as it is on loading),
  so the preset reproduces them; and its model is the one the default loads them into."""
  presets, _, _, provenance = shipped
  pretrain = presets["pretrain"]
  recorded = dict(provenance["experiment"])
  # an older record reads as its class reads it (`config.from_fields`)
  recorded = getattr(type(pretrain), "upgrade_record", lambda fields: fields)(recorded)
  assert _in_repository(recorded.pop("checkpoint")) == _in_repository(pretrain.checkpoint)
  expected = json.loads(json.dumps(dataclasses.asdict(pretrain)))
  recorded.pop("eval")
  differing = _recorded_fields_differing(recorded, expected)
  assert sorted(differing) == ["output_dir", "synthetic_dir"]
  assert pretrain.model == presets["synthetic-tiny"].model
  assert pretrain.checkpoint is None or (REPO / _in_repository(pretrain.checkpoint)).exists()


def test_default_starts_from_the_shipped_weights_with_nothing_fresh(shipped):
  presets, folder, files, _ = shipped
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
