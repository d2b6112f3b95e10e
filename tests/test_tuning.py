"""Test-time tuning on the tiny preset (every real-model case compiles the renderer: slow)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tokengs_jax.gaussians import Gaussians
from tokengs_jax.splatting import RenderConfig, larger_budget
from tokengs_jax.tuning import (
  TuningConfig,
  _adam_scan,
  _constrained,
  _offset,
  _tune_once,
  _unconstrained,
  tune,
)

HEIGHT = WIDTH = 32


def scene(num_views=2, seed=0):
  rng = np.random.default_rng(seed)
  images = rng.random((1, num_views, HEIGHT, WIDTH, 3)).astype(np.float32)
  c2w = np.tile(np.eye(4, dtype=np.float32), (1, num_views, 1, 1))
  c2w[0, :, 0, 3] = np.linspace(-0.1, 0.1, num_views)
  intrinsics = np.tile(np.array([32, 32, 16, 16], np.float32), (1, num_views, 1))
  return images, c2w, intrinsics


def test_gaussian_offsets_round_trip():
  key = jax.random.PRNGKey(0)
  g = Gaussians(
    means=jax.random.normal(key, (5, 3)),
    opacities=jnp.linspace(0.1, 0.9, 5),
    scales=jnp.linspace(0.01, 0.07, 15).reshape(5, 3),
    quats=jax.random.normal(key, (5, 4)),
    colors=jnp.linspace(0.05, 0.95, 15).reshape(5, 3),
  )

  def assert_close(a, b):
    jax.tree.map(lambda x, y: np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6), a, b)

  assert_close(_offset(g, jax.tree.map(jnp.zeros_like, g)), g)
  shifted = _offset(g, jax.tree.map(jnp.ones_like, g))
  assert np.all((shifted.opacities > 0) & (shifted.opacities < 1)) and np.all(shifted.scales > 0)
  assert_close(_constrained(_unconstrained(g)), g)


@pytest.mark.parametrize("schedule", ["constant", "cosine"])
def test_the_schedule_sets_each_steps_rate(schedule):
  """On a linear loss each Adam step moves by its rate (the normalised gradient is 1): the
  official constant rate, or a cosine from the rate at the first step to 0 after the last,
  half of it at the middle step, for each tuned variable with its own rate."""
  steps = 50
  rates = {"tokens": 1e-2, "offsets": 3e-2}
  variables = {name: jnp.zeros(()) for name in rates}
  tuning = TuningConfig(steps=steps, schedule=schedule)

  def loss_and_aux(v):
    return v["tokens"] + v["offsets"], v

  _, _, trajectory = _adam_scan(loss_and_aux, variables, rates, tuning)
  for name, rate in rates.items():
    moves = -np.diff(np.asarray(trajectory[name]))  # the moves of steps 0 .. steps - 2
    if schedule == "constant":
      np.testing.assert_allclose(moves, rate, rtol=1e-4)
    else:
      np.testing.assert_allclose(moves[[0, steps // 2]], [rate, rate / 2], rtol=1e-3)
      assert np.all(np.diff(moves) < 0) and moves[-1] < rate * 5e-3
  # no steps: nothing to schedule (the feed-forward result)
  unmoved, no_losses, _ = _adam_scan(
    loss_and_aux, variables, rates, TuningConfig(steps=0, schedule=schedule)
  )
  assert no_losses.shape == (0,) and unmoved == variables
  for unknown in (TuningConfig(steps=steps, schedule="linear"), TuningConfig(steps=0, schedule="")):
    with pytest.raises(ValueError, match="unknown tuning schedule"):
      _adam_scan(loss_and_aux, variables, rates, unknown)


@pytest.mark.slow
def test_token_tuning_lowers_loss_and_keeps_params(tiny):
  config, params = tiny
  before = jax.tree.map(np.array, params)
  # three input views (context extension: the preset was trained with two); same Gaussian count
  result = tune(
    params,
    *scene(num_views=3),
    model_config=config,
    tuning=TuningConfig(target="tokens", steps=5, learning_rate=1e-2),
  )
  losses = np.asarray(result.losses)
  assert losses.shape == (6,) and losses[-1] < losses[0]
  assert np.all(np.diff(losses) <= 0)
  assert result.gaussians.means.shape == (1, config.num_gaussians, 3)
  jax.tree.map(np.testing.assert_array_equal, before, jax.tree.map(np.array, params))


@pytest.mark.slow
@pytest.mark.parametrize("target", ["gaussians", "tokens+gaussians"])
def test_gaussian_and_joint_tuning_lower_loss(tiny, target):
  config, params = tiny
  result = tune(
    params,
    *scene(),
    model_config=config,
    tuning=TuningConfig(target=target, steps=4, learning_rate=1e-2, gaussian_learning_rate=1e-2),
  )
  losses = np.asarray(result.losses)
  assert losses[-1] < losses[0]


@pytest.mark.slow
def test_latent_tuning_lowers_loss():
  from tokengs_jax.model import init_params, preset

  # decoder LayerScale 1 (official init: 5e-5) so the decoder's output depends visibly on the
  # latents at initialisation
  config = preset(
    "tiny",
    use_latent_bottleneck=True,
    num_latents=16,
    latent_cross_attn_depth=1,
    dec_init_values=1.0,
  )
  params = init_params(jax.random.PRNGKey(0), config)
  result = tune(
    params,
    *scene(),
    model_config=config,
    tuning=TuningConfig(target="latents", steps=4, learning_rate=1e-2),
  )
  losses = np.asarray(result.losses)
  assert losses[-1] < losses[0]


def test_latent_tuning_needs_latent_model(tiny):
  config, params = tiny
  with pytest.raises(ValueError, match="latent-bottleneck"):
    jax.eval_shape(
      lambda p: tune(
        p, *scene(), model_config=config, tuning=TuningConfig(target="latents", steps=1)
      ),
      params,
    )


@pytest.mark.parametrize(
  "change, error, message",
  [
    ("images", ValueError, r"images must be \[B, V, H, W, 3\]"),
    ("intrinsics", TypeError, "intrinsics must be floating point"),
    ("output_times", ValueError, "output_times needs the input-view times"),
  ],
)
def test_tune_checks_its_inputs_at_trace_time(tiny, change, error, message):
  config, params = tiny
  images, c2w, intrinsics = scene()
  extra = {}
  if change == "images":
    images = images[0]
  elif change == "intrinsics":
    intrinsics = intrinsics.astype(np.int32)
  else:
    extra["output_times"] = jnp.zeros((1, 2))
  with pytest.raises(error, match=message):
    jax.eval_shape(lambda p: tune(p, images, c2w, intrinsics, model_config=config, **extra), params)


def test_times_need_a_time_conditioned_model(tiny):
  config, params = tiny
  with pytest.raises(ValueError, match="without time embedding"):
    jax.eval_shape(
      lambda p: tune(p, *scene(), model_config=config, times=jnp.zeros((1, 2))), params
    )


@pytest.mark.slow
def test_tuning_renders_the_input_views_over_their_mean_colour(tiny):
  """With an "input_mean" background the input-view loss is the loss over the fixed RGB of the
  inputs' mean colour (here far from the official grey, which gives another loss)."""
  from tokengs_jax.camera import invert_rigid
  from tokengs_jax.losses import LossConfig
  from tokengs_jax.objective import ObjectiveConfig, supervision_loss

  config, params = tiny
  images, c2w, intrinsics = scene()
  images = 0.4 * images  # mean colour about 0.2
  result = tune(
    params,
    images,
    c2w,
    intrinsics,
    model_config=config,
    tuning=TuningConfig(steps=0),
    objective=ObjectiveConfig(background="input_mean"),
  )
  mean = tuple(float(c) for c in images.mean(axis=(0, 1, 2, 3)))
  views = (images, invert_rigid(c2w), intrinsics, LossConfig(), RenderConfig())
  expected = supervision_loss(result.gaussians, *views, ObjectiveConfig(background=mean))[0]
  np.testing.assert_allclose(result.losses[0], expected, rtol=1e-5)
  grey = supervision_loss(result.gaussians, *views, ObjectiveConfig())[0]
  assert abs(float(grey) - float(expected)) > 1e-4


@pytest.mark.slow
def test_dynamic_tuning_decodes_at_each_views_time():
  from scenes import DYNAMIC_CONFIG, dynamic_batch, dynamic_params

  params = dynamic_params()
  batch = dynamic_batch([[0.0, 1.0]], [[0.3, 0.8]])
  context = (batch["context_images"], batch["context_c2w"], batch["context_intrinsics"])
  tuning = TuningConfig(target="tokens", steps=3, learning_rate=1e-2)
  result = tune(
    params,
    *context,
    model_config=DYNAMIC_CONFIG,
    tuning=tuning,
    times=batch["context_times"],
    output_times=batch["target_times"],
  )
  losses = np.asarray(result.losses)
  assert losses[-1] < losses[0]
  # one set of tuned Gaussians per output time: static part shared, dynamic part time-dependent
  assert result.gaussians.batch_shape == (1, 2)
  static = DYNAMIC_CONFIG.num_static_gaussians
  means = np.asarray(result.gaussians.means)
  np.testing.assert_allclose(means[:, 1, :static], means[:, 0, :static], rtol=1e-6, atol=1e-7)
  assert np.abs(means[:, 1, static:] - means[:, 0, static:]).max() > 1e-3


def test_overflowing_tuning_renders_are_redone_with_a_larger_budget(tiny):
  # 32x32 views are 4 tiles: 4 N pairs hold every Gaussian in every tile, a quarter of it does
  # not (the tiny model's initial Gaussians cover the views with low opacity: nothing saturates).
  config, params = tiny
  settings = TuningConfig(target="gaussians", steps=2, gaussian_learning_rate=1e-2)
  tight = RenderConfig(max_intersections=config.num_gaussians, chunk_size=32)
  ample = larger_budget(tight, config.num_gaussians, HEIGHT, WIDTH)
  assert ample.max_intersections == 4 * config.num_gaussians  # no scene can overflow it
  kwargs = dict(model_config=config, tuning=settings)
  cut, overflowed, needed = _tune_once(params, *scene(), render_config=tight, **kwargs)
  assert bool(overflowed) and tight.max_intersections < needed <= ample.max_intersections
  # The retry is sized by what the renders reported needing, not by a blind 4x.
  sized = larger_budget(tight, config.num_gaussians, HEIGHT, WIDTH, needed=int(needed))
  assert needed <= sized.max_intersections <= ample.max_intersections
  full, full_overflowed, _ = _tune_once(params, *scene(), render_config=sized, **kwargs)
  assert not bool(full_overflowed)
  # the truncated renders steered the tuning elsewhere
  assert np.abs(np.asarray(cut.gaussians.means - full.gaussians.means)).max() > 1e-5
  result = tune(params, *scene(), render_config=tight, **kwargs)
  np.testing.assert_array_equal(result.losses, full.losses)
  jax.tree.map(np.testing.assert_array_equal, result.gaussians, full.gaussians)


def test_cross_view_renders_tune_on_each_input_view_twice():
  """With `cross_view_renders` the tuning loss scores each input view twice: coloured by the
  model as configured, and by the other views only (one decode: `own_view` per camera, here
  against two decodes, the second with `own_view_colours=False`); at 0 steps it is that
  loss of the feed-forward Gaussians, which the plain tuning loss is not. Timed views refuse it."""
  from scenes import DYNAMIC_CONFIG, MICRO, dynamic_batch, dynamic_params, micro_params

  from tokengs_jax import model
  from tokengs_jax.camera import invert_rigid
  from tokengs_jax.losses import LossConfig
  from tokengs_jax.objective import ObjectiveConfig, supervision_loss

  config = MICRO.replace(gaussian_colours="inputs", input_colour_weights="viewer")
  params = micro_params()
  images, c2w, intrinsics = scene()
  cross = ObjectiveConfig(cross_view_renders=True)

  def loss_at_start(objective):
    steps = TuningConfig(steps=0)
    result = tune(
      params, images, c2w, intrinsics, model_config=config, tuning=steps, objective=objective
    )
    return result.losses[0]

  read_by = lambda c: model.reconstruct(params, images, c2w, intrinsics, config=c, viewer_c2w=c2w)
  twice = lambda x, y=None: jnp.concatenate([x, x if y is None else y], axis=1)
  expected = supervision_loss(
    jax.tree.map(twice, read_by(config), read_by(config.replace(own_view_colours=False))),
    twice(images),
    twice(invert_rigid(c2w)),
    twice(intrinsics),
    LossConfig(),
    RenderConfig(),
    context_images=images,
  )[0]
  np.testing.assert_allclose(loss_at_start(cross), expected, rtol=1e-5)
  assert abs(float(loss_at_start(ObjectiveConfig())) - float(expected)) > 1e-4
  batch = dynamic_batch([[0.0, 1.0]], [[0.3, 0.8]])
  with pytest.raises(ValueError, match="static models"):
    tune(
      dynamic_params(),
      batch["context_images"],
      batch["context_c2w"],
      batch["context_intrinsics"],
      model_config=DYNAMIC_CONFIG,
      objective=cross,
      times=batch["context_times"],
    )


def test_the_tuning_loss_keeps_an_lpips_term_as_the_training_loss_does(monkeypatch):
  """As the official test-time training (its `compute_loss`): a loss that weighs LPIPS scores
  the input views with it, given the VGG weights, in the time-free and the time-conditioned
  tuning loss, and refuses to run without them. A stand-in for the VGG distance (a weight times
  the mean absolute error) keeps the check fast: the term is linear in that weight."""
  from scenes import DYNAMIC_CONFIG, MICRO, dynamic_batch, dynamic_params, micro_params

  from tokengs_jax import lpips
  from tokengs_jax.losses import LossConfig

  monkeypatch.setattr(
    lpips,
    "lpips_distance",
    lambda weights, pred, target: weights["scale"] * jnp.mean(jnp.abs(pred - target), (-3, -2, -1)),
  )
  weighted = LossConfig(lambda_lpips=0.37)
  stand_in = lambda scale: {"scale": jnp.float32(scale)}  # noqa: E731
  params, inputs, start = micro_params(), scene(), TuningConfig(steps=0)

  def first_loss(loss_config, lpips_params=None):
    return tune(
      params,
      *inputs,
      model_config=MICRO,
      tuning=start,
      loss_config=loss_config,
      lpips_params=lpips_params,
    ).losses[0]

  plain = first_loss(LossConfig())
  term_at_1, term_at_2 = (first_loss(weighted, stand_in(s)) - plain for s in (1.0, 2.0))
  assert float(term_at_1) > 1e-3
  np.testing.assert_allclose(term_at_2, 2 * term_at_1, rtol=1e-4)
  with pytest.raises(ValueError, match="lpips_params"):
    first_loss(weighted)

  batch = dynamic_batch([[0.0, 1.0]], [[0.3, 0.8]])
  context = (batch["context_images"], batch["context_c2w"], batch["context_intrinsics"])

  def timed_shapes(lpips_params):
    tune_timed = lambda *a: _tune_once(  # noqa: E731
      *a,
      model_config=DYNAMIC_CONFIG,
      tuning=start,
      loss_config=weighted,
      render_config=RenderConfig(),
      times=batch["context_times"],
      lpips_params=lpips_params,
    )
    return jax.eval_shape(tune_timed, dynamic_params(), *context)  # traced, not compiled

  timed_shapes(stand_in(1.0))
  with pytest.raises(ValueError, match="lpips_params"):
    timed_shapes(None)
