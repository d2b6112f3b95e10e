"""experiments.cli: `[command] [preset] [--field value ...]` parsed into typed settings, and
presets that reproduce official ones resolving to the official values (issue 26)."""

import dataclasses
import inspect

import pytest

from experiments import cli, data, dl3dv, re10k, tasks
from tokengs_jax import model
from tokengs_jax.data.kubric import kubric_view_selector


def _official_steps(options) -> int:
  """Optimiser steps of an official preset: epochs x iterations per epoch / accumulation."""
  return options.num_epochs * options.max_iters_per_epoch // options.gradient_accumulation_steps


def test_parse_defaults_to_run_with_default_preset():
  command, experiment = cli.parse([], re10k.PRESETS, "synthetic-tiny", "prog")
  assert command == "run"
  assert experiment == re10k.PRESETS["synthetic-tiny"]
  command, experiment = cli.parse(["--train.steps", "9"], re10k.PRESETS, "synthetic-tiny", "prog")
  assert command == "run" and experiment.train.steps == 9
  assert experiment.model == re10k.PRESETS["synthetic-tiny"].model


@pytest.mark.parametrize("command", [[], ["eval"]])
def test_parse_takes_negated_booleans_with_the_preset_omitted(command):
  # tyro alone refused `--x.no-y` where the default preset was left out
  flags = [
    "--train.no-cross-view-renders",
    "--eval.no-pixel-baseline",
    "--model.no-own-view-colours",
  ]
  parsed, experiment = cli.parse(command + flags, re10k.PRESETS, "synthetic-tiny", "prog")
  assert parsed == (command or ["run"])[0]
  assert re10k.PRESETS["synthetic-tiny"].train.cross_view_renders
  assert not experiment.train.cross_view_renders
  assert not experiment.eval.pixel_baseline and not experiment.model.own_view_colours


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


def test_dl3dv_base_preset_is_the_official_train_dl3dv_base(official):
  options = official.config_defaults["train_dl3dv_base"]
  command, experiment = cli.parse(["train", "paper-base"], dl3dv.PRESETS, "synthetic-4view", "p")
  assert command == "train" and experiment == dl3dv.PRESETS["paper-base"]
  # the whole architecture, image size and input views as the official Options read them
  assert experiment.model == model.config_from_official(dataclasses.asdict(options))
  assert (experiment.model.enc_depth, experiment.model.dec_depth) == (3, 12)
  assert (experiment.model.num_gs_tokens, experiment.image_size) == (1024, (256, 256))
  t = experiment.train
  assert t.steps == _official_steps(options) == 150_000
  assert t.warmup_steps == options.pct_start_steps == 2000
  assert t.learning_rate == options.lr == 4e-4
  assert experiment.num_context_views == options.num_input_views == 4
  assert t.num_target_views == options.num_views - options.num_input_views == 4
  assert t.batch_size == options.batch_size * 8  # global: 8 per GPU x 8 GPUs
  assert t.grad_accum_steps == options.gradient_accumulation_steps
  loss = tasks.Task().loss_config(experiment)
  assert (loss.rgb_loss, loss.lambda_rgb, loss.lambda_ssim, loss.lambda_lpips) == (
    options.rgb_loss_type,
    options.lambda_rgb,
    options.lambda_ssim,
    options.lambda_lpips,
  )
  assert loss.lambda_opacity == options.lambda_opacity and not t.use_input_supervision
  # DL3DV data: `dl3dv_scaled_0.15`, first_cam, the data at the model's size
  ((mode, _),) = options.data_mode
  example = data.example_config(experiment, training=True)
  assert experiment.dataset == "dl3dv" and mode == f"dl3dv_scaled_{example.translation_scale}"
  assert example.normalization == options.camera_normalization_method
  assert example.scale_method == options.camera_scale_method
  assert example.image_shape == tuple(options.img_size)
  assert (example.sampler.num_context_views, example.sampler.num_target_views) == (4, 4)


def test_kubric_static_preset_is_the_official_finetune_dl3dv_kubric_static(official):
  from experiments import kubric
  from experiments.kubric_data import kubric_example_config, kubric_views
  from experiments.kubric_task import KubricTask

  options = official.config_defaults["finetune_dl3dv_kubric_static"]
  command, experiment = cli.parse(["finetune", "paper-static"], kubric.PRESETS, "paper", "p")
  assert command == "finetune" and experiment == kubric.PRESETS["paper-static"]
  assert experiment.model == model.config_from_official(dataclasses.asdict(options))
  assert not experiment.model.time_embedding and experiment.model.num_dynamic_gs_tokens == 0
  t = experiment.train
  assert t.steps == _official_steps(options) == 50_000
  assert (t.warmup_steps, t.learning_rate) == (options.pct_start_steps, options.lr)
  assert t.num_target_views == options.num_views - options.num_input_views == 4
  assert t.batch_size == options.batch_size * 8
  loss = KubricTask().loss_config(experiment)
  assert (loss.rgb_loss, loss.lambda_rgb, loss.lambda_ssim, loss.lambda_lpips) == (
    options.rgb_loss_type,
    options.lambda_rgb,
    options.lambda_ssim,
    options.lambda_lpips,
  )
  assert (loss.lambda_vis, loss.lambda_dyn_aux) == (
    options.lambda_visibility,
    options.lambda_dyn_aux,
  )
  assert not t.use_input_supervision and loss.lambda_opacity == options.lambda_opacity
  ((mode, _),) = options.data_mode
  example = kubric_example_config(experiment, training=True)
  assert mode == f"kubric_scaled_{example.translation_scale}"
  assert (example.normalization, example.scale_method) == (
    options.camera_normalization_method,
    options.camera_scale_method,
  )
  assert example.image_shape == tuple(options.img_size)
  # targets at an in-between time: `kubric_views` leaves the selector's default on
  assert options.use_interp_target
  assert inspect.signature(kubric_view_selector).parameters["interp_target"].default is True
  assert callable(kubric_views(experiment, t.num_target_views))


@pytest.mark.parametrize(
  "flag",
  [
    ["--lambda-motion", "1"],
    ["--dyn-aux-on-motion", "--lambda-motion", "1"],
    ["--dyn-aux-on-objects"],
    ["--eval.static-baseline"],
    ["--model.num-dynamic-gs-tokens", "8"],
  ],
)
def test_a_static_kubric_model_refuses_the_dynamic_only_settings(flag, capsys, monkeypatch):
  from experiments import kubric

  monkeypatch.setenv("COLUMNS", "400")  # tyro's error box on one line
  with pytest.raises((SystemExit, ValueError)) as error:
    cli.parse(["finetune", "paper-static", *flag], kubric.PRESETS, "paper", "p")
  said = str(error.value) + capsys.readouterr().err
  assert "static Kubric model" in said and flag[0] in said


def test_kubric_pointmap_trim_flags_reach_the_examples_and_bad_ones_are_refused(
  capsys, monkeypatch
):
  from experiments import kubric
  from experiments.kubric_data import kubric_example_config

  monkeypatch.setenv("COLUMNS", "400")  # tyro's error box on one line
  _, default = cli.parse(["run", "paper"], kubric.PRESETS, "paper", "p")
  for training in (True, False):  # official default: every depth point
    config = kubric_example_config(default, training=training)
    assert (config.pointmap_trim_lo, config.pointmap_trim_hi) == (0.0, 1.0)
  trim = ["--pointmap-trim-lo", "0.05", "--pointmap-trim-hi", "0.95"]
  for preset in kubric.PRESETS:
    _, experiment = cli.parse(["run", preset, *trim], kubric.PRESETS, "paper", "p")
    for training in (True, False):  # training and the evaluation's examples alike
      config = kubric_example_config(experiment, training=training)
      assert (config.pointmap_trim_lo, config.pointmap_trim_hi) == (0.05, 0.95), preset
  bad = ["--pointmap-trim-lo", "0.6", "--pointmap-trim-hi", "0.4"]
  with pytest.raises((SystemExit, ValueError)) as error:
    cli.parse(["run", "paper", *bad], kubric.PRESETS, "paper", "p")
  assert "pointmap_trim_lo" in str(error.value) + capsys.readouterr().err


# our static presets that reproduce official ones: official preset -> (entry point module, preset)
_STATIC_PRESETS_OF_OFFICIAL = {
  "train_dl3dv_base": "paper-base",
  **{f"finetune_dl3dv_{v}view": f"paper-{v}view" for v in (2, 4, 6)},
  **{f"eval_dl3dv_{v}view": f"paper-{v}view" for v in (2, 4, 6)},
  **{
    f"{stage}_dl3dv_latent_{v}view_{loss}": f"paper-latent-{v}view-{loss}"
    for stage in ("finetune", "eval")
    for v in (2, 4, 6)
    for loss in ("ssim", "lpips")
  },
}


@pytest.mark.parametrize("official_name", sorted(_STATIC_PRESETS_OF_OFFICIAL))
def test_static_presets_use_the_official_camera_normalisation(official, official_name):
  """Issue 26: each preset's camera frame and translation-scale mode are its official preset's,
  for training and evaluation alike."""
  options = official.config_defaults[official_name]
  experiment = dl3dv.PRESETS[_STATIC_PRESETS_OF_OFFICIAL[official_name]]
  for training in (True, False):
    example = data.example_config(experiment, training=training)
    assert example.normalization == options.camera_normalization_method
    assert example.scale_method == options.camera_scale_method
  assert (experiment.normalization == "mean_cam") == (
    options.camera_normalization_method == "mean_cam"
  )


@pytest.mark.parametrize("normalization", ["first_cam", "mean_cam"])
def test_normalization_flag_reaches_the_example_config(normalization):
  for presets, name in ((re10k.PRESETS, "synthetic-tiny"), (dl3dv.PRESETS, "paper-2view")):
    _, experiment = cli.parse(
      ["train", name, "--normalization", normalization], presets, name, "prog"
    )
    assert experiment.normalization == normalization
    for training in (True, False):
      assert data.example_config(experiment, training=training).normalization == normalization
  # unset: the dataset's default frame
  default = data.example_config(re10k.PRESETS["synthetic-tiny"], training=True)
  assert re10k.PRESETS["synthetic-tiny"].normalization is None
  assert default.normalization == "first_cam"
