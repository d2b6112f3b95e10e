"""The official loss options on the command line (issue 26): the SSIM / LPIPS variants as flags and
under the official preset names, the opacity regulariser, input-view supervision, and bad loss
settings refused at parse time."""

import dataclasses
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scenes import gaussians_in_front

from experiments import cli, dl3dv, re10k, tasks
from experiments.config import TrainSettings
from tokengs_jax import losses, splatting
from tokengs_jax.camera import invert_rigid
from tokengs_jax.objective import (
  ObjectiveConfig,
  static_model_loss,
  supervision_loss,
  time_conditioned_loss,
)


# official Options field -> TrainSettings field
LOSS_FIELDS = {
  "rgb_loss_type": "rgb_loss",
  "lambda_rgb": "lambda_rgb",
  "lambda_ssim": "lambda_ssim",
  "lambda_lpips": "lambda_lpips",
  "lambda_opacity": "lambda_opacity",
}

# official preset -> (dl3dv preset, the command that runs it)
OFFICIAL_PRESETS = {
  **{f"finetune_dl3dv_{n}view": (f"paper-{n}view", "finetune") for n in (2, 4, 6)},
  **{f"eval_dl3dv_{n}view": (f"paper-{n}view", "eval") for n in (2, 4, 6)},
  **{
    f"{stage}_dl3dv_latent_{n}view_{loss}": (f"paper-latent-{n}view-{loss}", command)
    for n in (2, 4, 6)
    for loss in ("ssim", "lpips")
    for stage, command in (("finetune", "finetune"), ("eval", "eval"))
  },
}


def test_default_loss_settings_are_the_official_defaults(official):
  defaults, train = official.Options(), TrainSettings()
  for official_name, name in LOSS_FIELDS.items():
    assert getattr(train, name) == getattr(defaults, official_name), name
  assert train.use_input_supervision is defaults.use_input_supervision is False
  experiment = re10k.PRESETS["synthetic-tiny"]
  assert tasks.Task().loss_config(experiment) == losses.LossConfig()  # unchanged default loss
  assert not tasks.Task().objective(experiment).use_input_supervision


@pytest.mark.parametrize("official_name", sorted(OFFICIAL_PRESETS))
def test_dl3dv_presets_resolve_to_the_official_loss(official, official_name):
  options = official.config_defaults[official_name]
  name, command = OFFICIAL_PRESETS[official_name]
  parsed, experiment = cli.parse([command, name], dl3dv.PRESETS, "synthetic-4view", "prog")
  assert parsed == command
  for official_field, field in LOSS_FIELDS.items():
    assert getattr(experiment.train, field) == getattr(options, official_field), field
  assert experiment.train.use_input_supervision == options.use_input_supervision
  loss_config = tasks.Task().loss_config(experiment)
  assert (loss_config.rgb_loss, loss_config.lambda_rgb) == (
    options.rgb_loss_type,
    options.lambda_rgb,
  )
  assert (loss_config.lambda_ssim, loss_config.lambda_lpips) == (
    options.lambda_ssim,
    options.lambda_lpips,
  )
  model = experiment.model
  assert model.num_input_views == options.num_input_views
  assert tuple(model.image_size) == tuple(options.img_size)
  assert model.num_gs_tokens == options.num_gs_tokens
  assert model.use_latent_bottleneck == options.use_latent_bottleneck
  if "latent" in official_name and command == "finetune":
    assert experiment.train.learning_rate == options.lr
    assert experiment.train.warmup_steps == options.pct_start_steps
    assert experiment.train.num_target_views == options.num_views - options.num_input_views
  if "latent" in official_name and command == "eval":  # scene-latent tuning at the official rate
    assert options.ttt_mode == "scene-latent-tuning" and experiment.eval.tuning_target == "latents"
    assert experiment.eval.tuning_learning_rate == options.ttt_lr


def test_loss_flags_reach_the_training_loss_and_objective():
  flags = {
    "ssim": ["--train.rgb-loss", "l1", "--train.lambda-rgb", "0.8", "--train.lambda-ssim", "0.2"],
    "lpips": ["--train.lambda-ssim", "0", "--train.lambda-lpips", "0.5"],
    "opacity": ["--train.lambda-opacity", "0.01", "--train.use-input-supervision"],
  }
  parsed = {
    name: cli.parse(argv, re10k.PRESETS, "synthetic-tiny", "prog")[1]
    for name, argv in flags.items()
  }
  task = tasks.Task()
  ssim = task.loss_config(parsed["ssim"])
  assert (ssim.rgb_loss, ssim.lambda_rgb, ssim.lambda_ssim) == ("l1", 0.8, 0.2)
  lpips = task.loss_config(parsed["lpips"])
  assert (lpips.rgb_loss, lpips.lambda_ssim, lpips.lambda_lpips) == ("l2", 0.0, 0.5)
  assert task.loss_config(parsed["opacity"]).lambda_opacity == 0.01
  assert task.objective(parsed["opacity"]).use_input_supervision
  assert task.tuning_loss_config(parsed["opacity"]).lambda_opacity == 0.01


@pytest.mark.parametrize(
  "flag, good, bad",
  [
    ("--train.lambda-opacity", "0.1", "-0.1"),
    ("--train.lambda-ssim", "0.2", "-0.2"),
    ("--train.lambda-rgb", "0.8", "nan"),
    ("--train.rgb-loss", "l1", "l3"),
  ],
)
def test_bad_loss_flags_fail_at_parse_time(flag, good, bad, capsys):
  cli.parse([flag, good], re10k.PRESETS, "synthetic-tiny", "prog")
  with pytest.raises((SystemExit, ValueError)) as error:
    cli.parse([flag, bad], re10k.PRESETS, "synthetic-tiny", "prog")
  said = (str(error.value) + capsys.readouterr().err).replace("-", "_")
  assert flag.removeprefix("--train.").replace("-", "_") in said


def test_bad_loss_settings_are_refused_on_construction():
  with pytest.raises(ValueError, match="lambda_opacity"):
    losses.LossConfig(lambda_opacity=-1.0)
  with pytest.raises(ValueError, match="lambda_lpips"):
    losses.LossConfig(lambda_lpips=float("inf"))
  with pytest.raises(ValueError, match="rgb_loss"):
    TrainSettings(rgb_loss="l3")
  with pytest.raises(ValueError, match="lambda_coverage"):
    dataclasses.replace(TrainSettings(), lambda_coverage=-2.0)


def test_opacity_loss_hand_values():
  opacities = jnp.array([[1.0, 0.5], [0.25, 1e-3]])
  expected = -np.mean(np.log(np.array([1.0, 0.5, 0.25, 1e-3]) + 1e-6))
  np.testing.assert_allclose(losses.opacity_loss(opacities), expected, rtol=1e-6)
  assert np.isfinite(jax.grad(losses.opacity_loss)(jnp.zeros(3))).all()  # eps keeps 0 finite


def _views(num_views, key=0):
  images = jax.random.uniform(jax.random.key(key), (1, num_views, 16, 16, 3))
  c2w = (
    jnp.tile(jnp.eye(4), (1, num_views, 1, 1))
    .at[:, :, 0, 3]
    .set(jnp.linspace(-0.1, 0.1, num_views))
  )
  intrinsics = jnp.tile(jnp.array([16.0, 16.0, 8.0, 8.0]), (1, num_views, 1))
  return images, c2w, intrinsics


def test_opacity_term_moves_the_supervision_loss_by_its_weight_and_raises_opacity():
  key = jax.random.split(jax.random.key(2), 2)
  gaussians = gaussians_in_front(*key, (1, 16), spread=0.5, opacity=0.3, scale=0.05)
  images, c2w, intrinsics = _views(2)
  args = (images, invert_rigid(c2w), intrinsics)
  render = splatting.RenderConfig()
  plain, plain_terms = supervision_loss(gaussians, *args, losses.LossConfig(), render)
  assert "opacity" not in plain_terms
  weighted = losses.LossConfig(lambda_opacity=0.5)
  loss, terms = supervision_loss(gaussians, *args, weighted, render)
  np.testing.assert_allclose(terms["opacity"], -np.log(0.3 + 1e-6), rtol=1e-5)
  np.testing.assert_allclose(loss, plain + 0.5 * terms["opacity"], rtol=1e-5)

  def opacity_term(opacities):
    g = dataclasses.replace(gaussians, opacities=opacities)
    return supervision_loss(g, *args, weighted, render)[1]["opacity"]

  assert float(jnp.max(jax.grad(opacity_term)(gaussians.opacities))) < 0  # pushes opacity up


def test_opacity_term_reaches_the_time_conditioned_loss():
  key = jax.random.split(jax.random.key(3), 2)
  gaussians = gaussians_in_front(*key, (1, 16), spread=0.5, opacity=0.6, scale=0.05)
  images, c2w, intrinsics = _views(2)

  def gaussians_at(times, world_to_camera):
    del world_to_camera
    return jax.tree.map(
      lambda x: jnp.broadcast_to(x[:, None], (1, times.shape[1], *x.shape[1:])), gaussians
    )

  def loss_with(config):
    return time_conditioned_loss(
      gaussians_at,
      jnp.zeros((1, 2)),
      images,
      invert_rigid(c2w),
      intrinsics,
      config,
      splatting.RenderConfig(),
    )

  plain, _ = loss_with(losses.LossConfig())
  loss, terms = loss_with(losses.LossConfig(lambda_opacity=2.0))
  np.testing.assert_allclose(terms["opacity"], -np.log(0.6 + 1e-6), rtol=1e-5)
  np.testing.assert_allclose(loss, plain + 2.0 * terms["opacity"], rtol=1e-5)


def test_input_supervision_scores_the_input_views_too():
  """With `use_input_supervision` the supervision views are the targets and the inputs (official
  `images_all`); without it, the targets alone. Same Gaussians (a stand-in `reconstruct`)."""
  key = jax.random.split(jax.random.key(4), 2)
  gaussians = gaussians_in_front(*key, (1, 32), spread=0.5, opacity=0.8, scale=0.1)
  images, c2w, intrinsics = _views(5, key=5)
  batch = {
    "context_images": images[:, :2],
    "context_c2w": c2w[:, :2],
    "context_intrinsics": intrinsics[:, :2],
    "target_images": images[:, 2:],
    "target_c2w": c2w[:, 2:],
    "target_intrinsics": intrinsics[:, 2:],
  }
  settings = dict(
    model_config=types.SimpleNamespace(viewer_dependent=False),
    loss_config=losses.LossConfig(),
    render_config=splatting.RenderConfig(),
    reconstruct=lambda *args, **kwargs: gaussians,
  )

  def expected(views):
    return supervision_loss(
      gaussians,
      images[:, views],
      invert_rigid(c2w[:, views]),
      intrinsics[:, views],
      settings["loss_config"],
      settings["render_config"],
      context_images=batch["context_images"],
    )[0]

  targets_only, _ = static_model_loss(None, batch, objective=ObjectiveConfig(), **settings)
  np.testing.assert_allclose(targets_only, expected([2, 3, 4]), rtol=1e-5)
  every_view, _ = static_model_loss(
    None, batch, objective=ObjectiveConfig(use_input_supervision=True), **settings
  )
  np.testing.assert_allclose(every_view, expected([2, 3, 4, 0, 1]), rtol=1e-5)
  assert abs(float(every_view) - float(targets_only)) > 1e-4


def test_input_supervision_keeps_target_times_first_and_marks_input_depths_unknown():
  from tokengs_jax.objective import supervised_views

  batch = {
    "context_images": jnp.zeros((1, 2, 4, 4, 3)),
    "context_c2w": jnp.zeros((1, 2, 4, 4)),
    "context_intrinsics": jnp.zeros((1, 2, 4)),
    "context_times": jnp.array([[0.1, 0.2]]),
    "target_images": jnp.ones((1, 3, 4, 4, 3)),
    "target_c2w": jnp.ones((1, 3, 4, 4)),
    "target_intrinsics": jnp.ones((1, 3, 4)),
    "target_times": jnp.array([[0.5, 0.5, 0.5]]),
    "target_depths": jnp.full((1, 3, 4, 4), 2.0),
  }
  assert supervised_views(batch, ObjectiveConfig()) is batch
  views = supervised_views(batch, ObjectiveConfig(use_input_supervision=True))
  np.testing.assert_allclose(views["target_times"], [[0.5, 0.5, 0.5, 0.1, 0.2]])
  assert views["target_images"].shape == (1, 5, 4, 4, 3)
  np.testing.assert_array_equal(views["target_depths"][0, :, 0, 0], [2.0, 2.0, 2.0, 0.0, 0.0])
  # with the cross-view renders (`ObjectiveConfig.cross_view_renders`) the inputs come twice
  views = supervised_views(
    batch, ObjectiveConfig(use_input_supervision=True, cross_view_renders=True)
  )
  np.testing.assert_allclose(views["target_times"], [[0.5, 0.5, 0.5, 0.1, 0.2, 0.1, 0.2]])
  np.testing.assert_array_equal(views["target_depths"][0, :, 0, 0], [2.0] * 3 + [0.0] * 4)
  np.testing.assert_array_equal(views["context_images"], batch["context_images"])
