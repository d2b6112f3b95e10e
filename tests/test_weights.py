"""experiments.weights: the starting weights of a run."""

import dataclasses
import json
import pathlib

import numpy as np
import pytest
from scenes import official_fixture

from experiments import weights
from experiments.config import Experiment

# The tiny official fixture's weights as torch saves a state dict (tests/test_model_official.py).
OFFICIAL_TINY_PTH = pathlib.Path(__file__).parent / "data" / "official_tiny.pth"


def test_official_weights_seed_a_grown_model_for_finetuning_but_must_match_for_evaluation():
  config, params, _ = official_fixture()
  grown = config.replace(num_gs_tokens=6, num_dynamic_gs_tokens=2, time_embedding=True)
  experiment = dataclasses.replace(
    Experiment(), model=grown, official_checkpoint=str(OFFICIAL_TINY_PTH)
  )
  started = weights.initial_params(experiment, finetune=True)
  np.testing.assert_array_equal(started["gs_tokens"][:4], params["gs_tokens"])
  assert started["gs_tokens"].shape == (6, 32) and started["gs_tokens_dynamic"].shape == (2, 32)
  with pytest.raises(ValueError, match="gs_tokens_dynamic"):
    weights.initial_params(experiment, finetune=False)


def _finished_run(
  folder: pathlib.Path, command: str, checkpoint=None, **weights_files: bytes
) -> pathlib.Path:
  """A run folder as `ship` reads it: metrics.json (its experiment started from `checkpoint`)
  and the named weights files."""
  folder.mkdir()
  experiment = {} if checkpoint is None else {"checkpoint": str(checkpoint)}
  (folder / "metrics.json").write_text(
    json.dumps({"command": command, "commit": command + "-commit", "experiment": experiment})
  )
  for name, content in weights_files.items():
    (folder / f"{name}.msgpack").write_bytes(content)
  return folder


def test_shipping_a_run_keeps_the_baselines_it_did_not_retrain_with_their_record(tmp_path):
  shipped = tmp_path / "shipped"
  first = _finished_run(tmp_path / "first", "both", params=b"old", pixel_aligned=b"pixel")
  weights.ship(first, shipped)
  second = _finished_run(tmp_path / "second", "tokengs only", params=b"new")
  provenance = weights.ship(second, shipped)
  assert provenance == json.loads((shipped / "provenance.json").read_text())
  assert provenance["command"] == "tokengs only"
  assert provenance["files"] == {
    "params.msgpack": weights.sha256(shipped / "params.msgpack"),
    "pixel_aligned.msgpack": weights.sha256(first / "pixel_aligned.msgpack"),
  }
  assert (shipped / "params.msgpack").read_bytes() == b"new"
  carried = {"command": "both", "commit": "both-commit", "train_steps": None}
  assert provenance["carried_over"] == {
    "pixel_aligned.msgpack": {**carried, "sha256": provenance["files"]["pixel_aligned.msgpack"]}
  }
  # shipped again, the baseline still names the run that trained it
  third = _finished_run(tmp_path / "third", "again", params=b"newer")
  assert weights.ship(third, shipped)["carried_over"] == provenance["carried_over"]
  # a weights file that no record vouches for is refused, and nothing is written
  (shipped / "pixel_aligned.msgpack").write_bytes(b"edited")
  with pytest.raises(ValueError, match="pixel_aligned.msgpack is not the file"):
    weights.ship(second, shipped)
  assert (shipped / "params.msgpack").read_bytes() == b"newer"
  assert json.loads((shipped / "provenance.json").read_text())["command"] == "again"


def test_shipping_a_later_stage_records_the_weights_it_started_from(tmp_path):
  shipped = tmp_path / "shipped"
  first = weights.ship(_finished_run(tmp_path / "first", "stage 1", params=b"1"), shipped)
  assert "started_from" not in first
  # started from the shipped weights it overwrites: their record is kept whole
  second_run = _finished_run(
    tmp_path / "second", "stage 2", checkpoint=shipped / "params.msgpack", params=b"2"
  )
  second = weights.ship(second_run, shipped)
  assert second["started_from"] == first and (shipped / "params.msgpack").read_bytes() == b"2"
  # started from a run folder: that run's record, and so on down the chain
  third_run = _finished_run(
    tmp_path / "third", "stage 3", checkpoint=second_run / "params.msgpack", params=b"3"
  )
  third = weights.ship(third_run, tmp_path / "elsewhere")
  assert third["started_from"] == {
    **{field: second[field] for field in ("command", "commit", "experiment")},
    **{field: None for field in ("train_steps", "train_seconds", "total_seconds", "devices")},
    "files": {"params.msgpack": weights.sha256(second_run / "params.msgpack")},
  }
  # shipped weights their record does not vouch for, or weights that are gone, are refused
  (shipped / "params.msgpack").write_bytes(b"edited")
  with pytest.raises(ValueError, match="not the file its folder's record describes"):
    weights.ship(second_run, shipped)
  (second_run / "params.msgpack").unlink()
  with pytest.raises(ValueError, match="is gone"):
    weights.ship(third_run, tmp_path / "elsewhere")
