"""experiments.cli: `[command] [preset] [--field value ...]` parsed into typed settings."""

import pytest

from experiments import cli, re10k


def test_parse_defaults_to_run_with_default_preset():
  command, experiment = cli.parse([], re10k.PRESETS, "synthetic-tiny", "prog")
  assert command == "run"
  assert experiment == re10k.PRESETS["synthetic-tiny"]
  command, experiment = cli.parse(["--train.steps", "9"], re10k.PRESETS, "synthetic-tiny", "prog")
  assert command == "run" and experiment.train.steps == 9
  assert experiment.model == re10k.PRESETS["synthetic-tiny"].model


def test_parse_command_preset_and_typed_overrides():
  command, experiment = cli.parse(
    [
      "eval",
      "paper",
      "--data-dir",
      "/x",
      "--train.steps",
      "7",
      "--official-checkpoint",
      "w.safetensors",
      "--model.enc-depth",
      "1",
    ],
    re10k.PRESETS,
    "synthetic-tiny",
    "prog",
  )
  assert command == "eval"
  assert experiment.data_dir == "/x" and experiment.train.steps == 7
  assert experiment.official_checkpoint == "w.safetensors"
  paper = re10k.PRESETS["paper"]
  assert experiment.model == paper.model.replace(enc_depth=1)  # the preset's model, one field set
  assert experiment.image_size == (256, 256) and experiment.num_context_views == 2


def test_parse_rejects_unknown_preset():
  with pytest.raises(SystemExit):
    cli.parse(["run", "nope"], re10k.PRESETS, "synthetic-tiny", "prog")
