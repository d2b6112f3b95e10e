"""experiments/kubric_task.py: the Kubric presets' loss (the official release's, scaled to the run;
the common `--train.*` flags, `--train.lambda-mask`, `--lambda-flow`)."""

import dataclasses
import json
import re

import pytest

from experiments import cli, kubric


def test_kubric_loss_is_the_official_release_scaled_to_the_run():
  from experiments.kubric_task import KubricTask

  paper = kubric.PRESETS["paper"]
  config = KubricTask().loss_config(paper)
  assert (config.rgb_loss, config.lambda_rgb, config.lambda_ssim, config.lambda_vis) == (
    "l1",
    0.8,
    0.2,
    1.0,
  )
  # official release: 0.3 held for 5k steps, decayed to 0 over 10k (of 50k finetuning steps)
  assert (
    config.lambda_dyn_aux,
    config.dyn_aux_hold_steps,
    config.dyn_aux_decay_steps,
    config.dyn_aux_min,
  ) == (0.3, 5_000, 10_000, 0.0)
  assert (config.lambda_motion, config.dyn_aux_on_motion) == (0.0, False)
  tiny = kubric.PRESETS["pretrain"]  # what trained the default's shipped weights
  config = KubricTask().loss_config(tiny)
  # the default's deviations: moving pixels x5, the auxiliary term on them, held all run
  assert (config.lambda_motion, config.dyn_aux_on_motion) == (4.0, True)
  assert config.dyn_aux_hold_steps == tiny.train.steps
  assert config.dyn_aux_decay_steps == round(0.2 * tiny.train.steps)
  # token tuning's input views moved nowhere: the official auxiliary term
  assert not KubricTask().tuning_loss_config(tiny).dyn_aux_on_motion
  assert KubricTask().objective(tiny).decode_times == "first"
  mse = dataclasses.replace(tiny, train=dataclasses.replace(tiny.train, rgb_loss="l2"))
  assert KubricTask().loss_config(mse).rgb_loss == "l2"


def _refusal(capsys, parse, *argv) -> str:
  """What the command line says, on one line, as it refuses `argv` (tyro's boxed message)."""
  with pytest.raises(SystemExit):
    parse(*argv)
  return " ".join(re.sub("[\u2500-\u257f]", " ", capsys.readouterr().err).split())


def test_kubric_presets_keep_their_loss_and_honour_the_common_train_flags(capsys):
  """The loss terms moved to `train` (issue 26): each preset's loss is the one it had (by hand:
  the official release's L1 x 0.8 + SSIM x 0.2 + visibility x 1 and the auxiliary term), the
  common `--train.*` loss flags now change Kubric's loss, and a record of a run from before the
  move reads back to the loss it trained with."""
  from experiments import config, kubric
  from experiments.kubric_task import KubricExperiment, KubricTask
  from tokengs_jax.losses import LossConfig

  release = dict(rgb_loss="l1", lambda_rgb=0.8, lambda_ssim=0.2, lambda_vis=1.0)
  pretrain = dict(release, lambda_dyn_aux=0.3, lambda_motion=4.0, dyn_aux_on_motion=True)
  expected = {
    "pretrain": LossConfig(**pretrain, dyn_aux_hold_steps=1200, dyn_aux_decay_steps=240),
    # 0 steps: nothing to hold, the decay's one-step floor
    "synthetic-tiny": LossConfig(**pretrain, dyn_aux_hold_steps=0, dyn_aux_decay_steps=1),
    "paper": LossConfig(
      **release, lambda_dyn_aux=0.3, dyn_aux_hold_steps=5_000, dyn_aux_decay_steps=10_000
    ),
  }
  for name, loss in expected.items():
    assert KubricTask().loss_config(kubric.PRESETS[name]) == loss, name
  assert KubricTask().loss_config(KubricExperiment()).lambda_rgb == 0.8  # the release's default

  def parse(*argv):
    return cli.parse(list(argv), kubric.PRESETS, "synthetic-tiny", "prog")[1]

  flags = ("--train.lambda-ssim", "0.5", "--train.rgb-loss", "l2", "--train.lambda-opacity", "0.1")
  loss = KubricTask().loss_config(parse("run", "paper", *flags))
  assert loss == dataclasses.replace(
    expected["paper"], lambda_ssim=0.5, rgb_loss="l2", lambda_opacity=0.1
  )
  tuned = parse("--train.use-input-supervision")
  assert KubricTask().objective(tuned).use_input_supervision
  # each supervised view decoded at its own time, the inputs at theirs (the flag reaches the loss)
  per_view = parse("--train.use-input-supervision", "--decode-times", "per_view")
  assert KubricTask().objective(per_view).decode_times == "per_view"
  assert "Unrecognized" in _refusal(capsys, parse, "--rgb-loss", "l2")  # the duplicate flag
  said = _refusal(capsys, parse, "--train.lambda-depth", "0.1")
  assert "lambda_depth must be 0 on Kubric" in said
  said = _refusal(capsys, parse, "--train.cross-view-renders")
  assert "cross_view_renders is for static models" in said
  assert "dyn_aux_on_motion needs lambda_motion" in _refusal(capsys, parse, "--lambda-motion", "0")

  old = json.loads(json.dumps(dataclasses.asdict(kubric.PRESETS["pretrain"]), default=str))
  old["rgb_loss"] = "l2"  # recorded top-level, and train's unused photometric weights
  old["train"].update(rgb_loss="l2", lambda_rgb=1.0, lambda_ssim=0.2, lambda_opacity=0.3)
  read = config.from_fields(KubricExperiment, old)
  assert KubricTask().loss_config(read) == dataclasses.replace(expected["pretrain"], rgb_loss="l2")


def _parse_kubric(*argv):
  return cli.parse(list(argv), kubric.PRESETS, "synthetic-tiny", "prog")[1]


@pytest.mark.parametrize(
  "preset, flag, field, example_field",
  [
    ("paper", "--train.lambda-mask", "lambda_mask", "target_masks"),
    ("pretrain", "--lambda-flow", "lambda_flow", "target_flows"),
  ],
)
def test_per_pixel_loss_flags_reach_the_kubric_loss_and_only_then_the_examples_carry_their_truth(
  capsys, preset, flag, field, example_field
):
  """`--train.lambda-mask` (official `lambda_mask`) and `--lambda-flow` (the scene-flow term)
  weigh Kubric's training loss; only then do the training examples carry the targets' masks /
  flows (evaluation's never; token tuning scores neither, as official for the mask); with input
  supervision (the inputs carry neither) or negative: refused."""
  from experiments.kubric_data import kubric_example_config
  from experiments.kubric_task import KubricTask

  plain = _parse_kubric("run", preset)
  assert getattr(KubricTask().loss_config(plain), field) == 0.0
  assert not getattr(kubric_example_config(plain, training=True), example_field)
  weighted = _parse_kubric("run", preset, flag, "0.5")
  assert KubricTask().loss_config(weighted) == dataclasses.replace(
    KubricTask().loss_config(plain), **{field: 0.5}
  )
  assert getattr(kubric_example_config(weighted, training=True), example_field)
  assert not getattr(kubric_example_config(weighted, training=False), example_field)
  assert getattr(KubricTask().tuning_loss_config(weighted), field) == 0.0
  said = _refusal(capsys, _parse_kubric, flag, "0.5", "--train.use-input-supervision")
  assert field in said and "use_input_supervision" in said
  assert f"{field}=-1.0" in _refusal(capsys, _parse_kubric, flag, "-1")


def test_lambda_flow_needs_a_model_with_dynamic_tokens(capsys):
  said = _refusal(capsys, _parse_kubric, "run", "paper-static", "--lambda-flow", "1")
  assert "--lambda-flow" in said
