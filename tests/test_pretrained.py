"""The shipped weights (experiments/pretrained/): intact, and exactly what the default loads.

The command that trained them (`python -m experiments.re10k run pretrain`) runs at a small scale,
and is shipped the same way, in `tests/test_experiments.py::test_entry_point_end_to_end`.
"""

import dataclasses
import json

import jax
import pytest

from experiments import re10k, weights
from experiments.config import PRETRAINED_SYNTHETIC
from tokengs_jax import model


@pytest.fixture(scope="module")
def provenance():
  return json.loads((PRETRAINED_SYNTHETIC / "provenance.json").read_text())


def test_shipped_files_match_their_recorded_digests(provenance):
  assert set(provenance["files"]) == {"params.msgpack", "pixel_aligned.msgpack"}
  for name, digest in provenance["files"].items():
    assert weights.sha256(PRETRAINED_SYNTHETIC / name) == digest, name


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


def test_shipped_weights_come_from_the_pretrain_preset(provenance):
  """Its recorded experiment is the `pretrain` preset's (apart from where it wrote), so the
  preset reproduces them; and its model is the one the default loads them into."""
  pretrain = re10k.PRESETS["pretrain"]
  expected = json.loads(json.dumps(dataclasses.asdict(pretrain)))
  differing = _recorded_fields_differing(provenance["experiment"], expected)
  assert sorted(differing) == ["output_dir", "synthetic_dir"]
  assert pretrain.model == re10k.PRESETS["synthetic-tiny"].model


def test_default_starts_from_the_shipped_weights_with_nothing_fresh():
  default = re10k.PRESETS["synthetic-tiny"]
  assert default.checkpoint == str(PRETRAINED_SYNTHETIC / "params.msgpack")
  loaded = weights.load_params(default.checkpoint)
  expected = jax.eval_shape(lambda: model.init_params(jax.random.key(0), default.model))
  assert jax.tree.structure(loaded) == jax.tree.structure(expected)
  for got, want in zip(jax.tree.leaves(loaded), jax.tree.leaves(expected), strict=True):
    assert got.shape == want.shape and got.dtype == want.dtype
