"""experiments/config.py: a recorded experiment read back (`config.from_fields`), and
`eval --from-run`, which builds on it (the rest of the command line: test_cli). Named
`test_experiments_<module>` as `test_config` would read as a `tokengs_jax` module's."""

import dataclasses
import json

import pytest

from experiments import cli, re10k


def test_recorded_settings_of_every_preset_read_back_as_they_were():
  """`config.from_fields` rebuilds an experiment from its metrics.json record (JSON lists back
  to tuples, nested settings, a Kubric experiment's own fields)."""
  from experiments import config, dl3dv, kubric

  for presets in (re10k.PRESETS, dl3dv.PRESETS, kubric.PRESETS):
    for preset in presets.values():
      recorded = json.loads(json.dumps(dataclasses.asdict(preset), default=str))
      assert config.from_fields(type(preset), recorded) == preset
  with pytest.raises(ValueError, match="no fields.*'frames'"):
    config.from_fields(config.Experiment, {"frames": 3})


def test_eval_from_run_takes_the_recorded_settings_and_flags_override_them(tmp_path):
  """`eval --from-run RUN_DIR`: the experiment the run recorded in its metrics.json, scoring its
  trained weights (`params.msgpack`, when it trained; else the weights it evaluated) into
  RUN_DIR/eval/; flags override it. Another command, or a folder without metrics.json, refuses."""
  smoke = re10k.PRESETS["smoke"]
  run = tmp_path / "run"
  recorded = dataclasses.replace(
    smoke,
    output_dir=str(run),
    official_checkpoint="w.safetensors",
    eval=dataclasses.replace(smoke.eval, num_scenes=1, media_scenes=3),
  )
  run.mkdir()
  payload = {"experiment": dataclasses.asdict(recorded)}
  (run / "metrics.json").write_text(json.dumps(payload, default=str))

  def parse(*argv):
    return cli.parse(list(argv), re10k.PRESETS, "synthetic-tiny", "prog")

  assert parse("eval", "--from-run", str(run)) == (
    "eval",
    dataclasses.replace(recorded, output_dir=str(run / "eval")),
  )
  (run / "params.msgpack").write_bytes(b"")
  command, experiment = parse(
    "eval", f"--from-run={run}", "--eval.num-scenes", "4", "--output-dir", str(tmp_path / "x")
  )
  assert experiment == dataclasses.replace(
    recorded,
    checkpoint=str(run / "params.msgpack"),
    official_checkpoint=None,
    output_dir=str(tmp_path / "x"),
    eval=dataclasses.replace(recorded.eval, num_scenes=4),
  )
  _, negated = parse("eval", "--from-run", str(run), "--eval.no-lpips")
  assert recorded.eval.lpips and not negated.eval.lpips
  with pytest.raises(SystemExit, match="eval --from-run"):
    parse("run", "--from-run", str(run))
  with pytest.raises(SystemExit, match="metrics.json"):
    parse("eval", "--from-run", str(tmp_path))
  from experiments import kubric

  kubric_run = {"experiment": dataclasses.asdict(kubric.PRESETS["synthetic-tiny"])}
  (run / "metrics.json").write_text(json.dumps(kubric_run, default=str))
  with pytest.raises(SystemExit, match="records no Experiment.*another entry point"):
    parse("eval", "--from-run", str(run))


def test_lambda_mask_reaches_the_loss_and_is_refused_on_data_without_masks(capsys):
  """`--train.lambda-mask` (official `lambda_mask`) is `TrainSettings.lambda_mask`, in the loss it
  builds; RE10K, DL3DV and the synthetic set carry no foreground masks, so their command lines
  refuse a positive weight before any work, naming it."""
  from experiments import config, dl3dv

  assert config.TrainSettings().loss_config().lambda_mask == 0.0  # off, as official
  assert config.TrainSettings(lambda_mask=0.5).loss_config().lambda_mask == 0.5
  for presets, default in ((re10k.PRESETS, "synthetic-tiny"), (dl3dv.PRESETS, "synthetic-4view")):
    assert cli.parse([], presets, default, "prog")[1].train.lambda_mask == 0.0
    with pytest.raises(SystemExit):
      cli.parse(["--train.lambda-mask", "0.5"], presets, default, "prog")
    assert "lambda_mask must be 0" in capsys.readouterr().err
  with pytest.raises(ValueError, match="no foreground masks"):
    dataclasses.replace(re10k.PRESETS["smoke"], train=config.TrainSettings(lambda_mask=0.1))


def test_data_mode_names_the_training_datasets_and_bad_entries_are_refused_at_parse(
  tmp_path, capsys
):
  """`--data-mode NAME:REPEAT:FOLDER ...` (official `data_mode`) on the static entry points: the
  entries as given; an unknown or Kubric dataset, a repeat below 1 or a missing folder stops the
  command line before any work, naming the entry; Kubric's own entry point refuses the flag."""
  from chunk_scenes import chunk_scene, write_chunk_set
  from experiments import dl3dv, kubric

  write_chunk_set(tmp_path / "re10k" / "train", [chunk_scene("a")])
  mix = (f"dl3dv_scaled_0.15:6:{tmp_path / 're10k'}", f"re10k_scaled_0.25:1:{tmp_path / 're10k'}")
  for presets, default in ((re10k.PRESETS, "smoke"), (dl3dv.PRESETS, "synthetic-4view")):
    assert cli.parse([], presets, default, "prog")[1].data_mode == ()
    assert cli.parse(["--data-mode", *mix], presets, default, "prog")[1].data_mode == mix
  bad = {
    f"scannet:1:{tmp_path / 're10k'}": "unknown dataset 'scannet'",
    f"kubric_scaled_1.0:100:{tmp_path / 're10k'}": "Kubric is dynamic",
    f"re10k:0:{tmp_path / 're10k'}": "REPEAT must be an integer >= 1",
    f"re10k:1:{tmp_path / 'absent'}": "no such folder",
  }
  for entry, message in bad.items():
    with pytest.raises(SystemExit):
      cli.parse(["smoke", "--data-mode", entry], re10k.PRESETS, "smoke", "prog")
    err = " ".join(capsys.readouterr().err.split())  # as one line, whatever the box's width
    assert message in err and "--data-mode" in err, err
  with pytest.raises(SystemExit):
    cli.parse(["--data-mode", mix[1]], kubric.PRESETS, "synthetic-tiny", "prog")
  assert "a Kubric run trains on its one dataset" in " ".join(capsys.readouterr().err.split())


def test_cross_view_renders_reach_the_objective_and_need_viewer_colours(capsys):
  """`--train.cross-view-renders` is `ObjectiveConfig.cross_view_renders` in the run's objective
  (training and token tuning); a model whose colours do not depend on the camera refuses it
  before any work."""
  from experiments import tasks

  parse = lambda *argv: cli.parse(list(argv), re10k.PRESETS, "synthetic-tiny", "prog")[1]
  assert tasks.Task().objective(parse()).cross_view_renders  # the default's, as its finetune's
  switched_off = parse("run", "synthetic-tiny", "--train.no-cross-view-renders")
  assert not tasks.Task().objective(switched_off).cross_view_renders
  assert not tasks.Task().objective(parse("run", "pretrain")).cross_view_renders
  flagged = parse("run", "pretrain", "--train.cross-view-renders")
  assert tasks.Task().objective(flagged).cross_view_renders
  with pytest.raises(SystemExit):
    parse("--train.cross-view-renders", "--model.input-colour-weights", "mean")
  assert "viewer weights" in capsys.readouterr().err
