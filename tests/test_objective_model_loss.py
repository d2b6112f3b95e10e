"""The model losses: time-conditioned decoding against the static path, the dynamic auxiliary
term and its schedule, view chunks and the input-mean background with the real model, one
Gaussian set per view."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scenes import (
  DYNAMIC_CONFIG,
  MICRO,
  dynamic_batch,
  dynamic_params,
  gaussians_in_front,
  scene_of_two_examples,
  synthetic_batch,
)

from tokengs_jax import losses, model, splatting
from tokengs_jax.camera import invert_rigid
from tokengs_jax.objective import (
  ObjectiveConfig,
  dynamic_model_loss,
  static_model_loss,
  supervision_loss,
  time_conditioned_loss,
  tokengs_loss_fn,
)


def _loss_and_grads(loss_fn, params, batch):
  return jax.jit(jax.value_and_grad(loss_fn, has_aux=True))(params, batch, jax.random.PRNGKey(0), 0)


def _assert_same(result, expected):
  (loss, _), grads = result
  (expected_loss, _), expected_grads = expected
  np.testing.assert_allclose(loss, expected_loss, rtol=1e-5)
  scale = max(float(np.max(np.abs(g))) for g in jax.tree.leaves(expected_grads))
  jax.tree.map(
    lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-5 * scale),
    grads,
    expected_grads,
  )


@pytest.mark.slow
def test_time_conditioned_loss_matches_the_static_path_when_targets_share_a_time():
  """With every target view at one time t, rendering each view from the Gaussians decoded at its
  time (one-shot, chunked with the decoder inside the chunks, or decoding once as official) is
  the static objective on `reconstruct(..., target_times=t)`: same loss, same gradient."""
  params = dynamic_params()
  batch = dynamic_batch([[0.0, 1.0]], [[0.4, 0.4]])
  loss_config = losses.LossConfig()

  def reference(params, batch, key, step):
    del key, step
    gaussians = model.reconstruct(
      params,
      batch["context_images"],
      batch["context_c2w"],
      batch["context_intrinsics"],
      config=DYNAMIC_CONFIG,
      times=batch["context_times"],
      target_times=batch["target_times"][:, 0],
    )
    return supervision_loss(
      gaussians,
      batch["target_images"],
      invert_rigid(batch["target_c2w"]),
      batch["target_intrinsics"],
      loss_config,
      splatting.RenderConfig(),
    )

  expected = _loss_and_grads(reference, params, batch)
  for objective in (
    ObjectiveConfig(),
    ObjectiveConfig(view_chunk_size=1),
    ObjectiveConfig(decode_times="first"),
  ):
    result = _loss_and_grads(
      tokengs_loss_fn(DYNAMIC_CONFIG, loss_config, objective=objective), params, batch
    )
    _assert_same(result, expected)
    for name in ("rgb", "ssim", "visibility"):
      np.testing.assert_allclose(result[0][1][name], expected[0][1][name], rtol=1e-5, atol=1e-7)


@pytest.mark.slow
def test_dynamic_aux_loss_is_the_loss_of_the_dynamic_gaussians_alone_with_its_schedule():
  params = dynamic_params()
  batch = dynamic_batch([[0.0, 1.0]], [[0.4, 0.4]])
  loss_config = losses.LossConfig(
    lambda_dyn_aux=0.3, dyn_aux_hold_steps=2, dyn_aux_decay_steps=4, dyn_aux_min=0.0
  )
  plain = dataclasses.replace(loss_config, lambda_dyn_aux=0.0)
  gaussians = model.reconstruct(
    params,
    batch["context_images"],
    batch["context_c2w"],
    batch["context_intrinsics"],
    config=DYNAMIC_CONFIG,
    times=batch["context_times"],
    target_times=batch["target_times"][:, 0],
  )
  dynamic = jax.tree.map(lambda x: x[:, DYNAMIC_CONFIG.num_static_gaussians :], gaussians)
  views = (batch["target_images"], invert_rigid(batch["target_c2w"]), batch["target_intrinsics"])
  main = float(supervision_loss(gaussians, *views, plain, splatting.RenderConfig())[0])
  dyn = float(supervision_loss(dynamic, *views, plain, splatting.RenderConfig())[0])

  loss_fn = jax.jit(
    tokengs_loss_fn(DYNAMIC_CONFIG, loss_config, objective=ObjectiveConfig(decode_times="first"))
  )
  for step, weight in ((0, 0.3), (2, 0.3), (4, 0.15), (7, 0.0)):
    loss, terms = loss_fn(params, batch, None, step)
    np.testing.assert_allclose(terms["dyn_aux_weight"], weight, rtol=1e-6)
    np.testing.assert_allclose(terms["dyn_aux"], dyn if weight else 0.0, rtol=1e-5)
    np.testing.assert_allclose(loss, main + weight * dyn, rtol=1e-5)


def test_motion_term_weighs_the_moving_pixels_one_plus_lambda_times():
  params = dynamic_params()
  batch = dynamic_batch([[0.0, 1.0]], [[0.4, 0.4]])
  plain = losses.LossConfig(rgb_loss="l1", lambda_rgb=0.8)
  objective = ObjectiveConfig(decode_times="first")

  def terms_with(**changes):
    loss_fn = tokengs_loss_fn(
      DYNAMIC_CONFIG, dataclasses.replace(plain, **changes), objective=objective
    )
    return jax.jit(loss_fn)(params, batch, None, 0)

  base_loss, base_terms = terms_with()
  assert "motion" not in base_terms
  # every pixel moves: the term is the RGB term itself; none moves: it is 0
  loss, terms = terms_with(lambda_motion=2.0, motion_threshold=-1.0)
  np.testing.assert_allclose(terms["motion"], base_terms["rgb"], rtol=1e-6)
  np.testing.assert_allclose(loss, base_loss + 0.8 * 2.0 * base_terms["rgb"], rtol=1e-5)
  _, terms = terms_with(lambda_motion=2.0, motion_threshold=2.0)
  assert float(terms["motion"]) == 0.0
  # random images: some pixels move, a share of the RGB error
  loss, terms = terms_with(lambda_motion=2.0)
  assert 0 < float(terms["motion"]) < float(base_terms["rgb"])
  np.testing.assert_allclose(loss, base_loss + 0.8 * 2.0 * terms["motion"], rtol=1e-5)


def test_coverage_term_scores_the_whole_render_and_not_the_dynamic_auxiliary_one():
  params = dynamic_params()
  batch = dynamic_batch([[0.0, 1.0]], [[0.4, 0.4]])
  with_aux = losses.LossConfig(rgb_loss="l1", lambda_rgb=0.8, lambda_dyn_aux=0.5)
  objective = ObjectiveConfig(decode_times="first")

  def loss_and_terms(config):
    return jax.jit(tokengs_loss_fn(DYNAMIC_CONFIG, config, objective=objective))(
      params, batch, None, 0
    )

  base_loss, base_terms = loss_and_terms(with_aux)
  loss, terms = loss_and_terms(dataclasses.replace(with_aux, lambda_coverage=3.0))
  assert 0 < float(terms["coverage"]) <= 1
  # the auxiliary render of the dynamic Gaussians alone is not charged for what it leaves bare
  np.testing.assert_allclose(terms["dyn_aux"], base_terms["dyn_aux"], rtol=1e-6)
  np.testing.assert_allclose(loss, base_loss + 3.0 * terms["coverage"], rtol=1e-5)


def test_mask_term_scores_the_main_and_the_auxiliary_render_and_needs_the_batch_masks():
  """Official `lambda_mask`: the main loss gains weight * its "mask" term, the auxiliary loss (the
  same loss on the dynamic render, official) its own; weight 0: no term, the masks carried or
  not; a weight without the batch's `target_masks`: ValueError."""
  params = dynamic_params()
  batch = dynamic_batch([[0.0, 1.0]], [[0.4, 0.4]])
  objective = ObjectiveConfig(decode_times="first")
  with_aux = losses.LossConfig(rgb_loss="l1", lambda_rgb=0.8, lambda_dyn_aux=0.5)
  with_mask = dataclasses.replace(with_aux, lambda_mask=2.0)
  # all foreground: the targets are unchanged by the official white compositing
  masked = {**batch, "target_masks": np.ones(batch["target_images"].shape[:-1], np.float32)}

  def loss_and_terms(config, batch):
    return jax.jit(tokengs_loss_fn(DYNAMIC_CONFIG, config, objective=objective))(
      params, batch, None, 0
    )

  base_loss, base_terms = loss_and_terms(with_aux, batch)
  off_loss, off_terms = loss_and_terms(with_aux, masked)
  assert "mask" not in off_terms
  np.testing.assert_allclose(off_loss, base_loss, rtol=1e-6)
  loss, terms = loss_and_terms(with_mask, masked)
  assert 0 < float(terms["mask"]) < 1
  np.testing.assert_allclose(
    loss - 0.5 * terms["dyn_aux"],
    base_loss - 0.5 * base_terms["dyn_aux"] + 2.0 * terms["mask"],
    rtol=1e-5,
  )
  assert float(terms["dyn_aux"]) > float(base_terms["dyn_aux"])  # the dynamic alpha is scored
  with pytest.raises(ValueError, match="target_masks"):
    loss_and_terms(with_mask, batch)


def test_supervision_targets_whiten_the_masked_out_background_as_official():
  """Targets with `target_masks` are composited on white (official `gt * mask + (1 - mask)`)
  whatever the weight; without masks they are the batch's images."""
  from tokengs_jax.objective.model_loss import supervision_targets

  images = np.full((1, 1, 2, 2, 3), 0.25, np.float32)
  masks = np.array([[[[1.0, 0.0], [0.5, 1.0]]]], np.float32)
  off = losses.LossConfig()
  got, got_masks = supervision_targets({"target_images": images, "target_masks": masks}, off)
  np.testing.assert_allclose(got[0, 0, :, :, 0], [[0.25, 1.0], [0.625, 0.25]])
  assert got_masks is masks
  unmasked, no_masks = supervision_targets({"target_images": images}, off)
  assert unmasked is images and no_masks is None


def test_dynamic_aux_on_motion_scores_the_dynamic_gaussians_on_the_moving_pixels_only():
  params = dynamic_params()
  batch = dynamic_batch([[0.0, 1.0]], [[0.4, 0.4]])
  motion = losses.LossConfig(rgb_loss="l1", lambda_rgb=0.8, lambda_motion=2.0)
  objective = ObjectiveConfig(decode_times="first")

  def loss_and_terms(config):
    return jax.jit(tokengs_loss_fn(DYNAMIC_CONFIG, config, objective=objective))(
      params, batch, None, 0
    )

  with_aux = dataclasses.replace(motion, lambda_dyn_aux=0.5)
  base_loss, base_terms = loss_and_terms(with_aux)
  loss, terms = loss_and_terms(dataclasses.replace(with_aux, dyn_aux_on_motion=True))
  # the main loss is unchanged; only the auxiliary term is the dynamic render's motion term
  np.testing.assert_allclose(
    loss - 0.5 * terms["dyn_aux"], base_loss - 0.5 * base_terms["dyn_aux"], rtol=1e-5
  )
  assert 0 < float(terms["dyn_aux"]) < float(base_terms["dyn_aux"])
  dynamic = dataclasses.replace(with_aux, dyn_aux_on_motion=True, motion_threshold=2.0)
  _, nothing_moves = loss_and_terms(dynamic)
  encoded = model.encode_views(
    params,
    batch["context_images"],
    batch["context_c2w"],
    batch["context_intrinsics"],
    DYNAMIC_CONFIG,
    times=batch["context_times"],
  )
  # no moving pixel: the auxiliary term is the dynamic Gaussians' visibility alone
  assert 0 <= float(nothing_moves["dyn_aux"]) < float(terms["dyn_aux"])
  with pytest.raises(ValueError, match="lambda_motion"):
    losses.LossConfig(dyn_aux_on_motion=True)
  # without the moving pixels (views that are their own inputs, as in token tuning): refused
  views = (batch["target_images"], invert_rigid(batch["target_c2w"]), batch["target_intrinsics"])
  with pytest.raises(ValueError, match="moving pixels"):
    time_conditioned_loss(
      lambda t, w2c: model.decode_at_times(params, encoded, DYNAMIC_CONFIG, t),
      batch["target_times"],
      *views,
      dynamic,
      splatting.RenderConfig(),
      objective,
      num_static_gaussians=DYNAMIC_CONFIG.num_static_gaussians,
    )


def test_dynamic_aux_on_objects_scores_the_dynamic_render_against_the_object_mask():
  """The auxiliary term becomes: the dynamic render's error on the object pixels, its alpha
  against the mask everywhere, and the visibility; the main loss does not change."""
  params = dynamic_params()
  batch = dynamic_batch([[0.0, 1.0]], [[0.4, 0.4]])
  objective = ObjectiveConfig(decode_times="first")
  official = losses.LossConfig(rgb_loss="l1", lambda_rgb=0.8, lambda_dyn_aux=0.5)
  on_objects = dataclasses.replace(official, dyn_aux_on_objects=True)
  height, width = batch["target_images"].shape[2:4]
  objects = np.zeros(batch["target_images"].shape[:-1], np.float32)
  objects[..., : height // 2, :] = 1.0  # the top half is an object

  def loss_and_terms(config, objects):
    return jax.jit(tokengs_loss_fn(DYNAMIC_CONFIG, config, objective=objective))(
      params, {**batch, "target_objects": objects}, None, 0
    )

  base_loss, base_terms = loss_and_terms(official, objects)
  loss, terms = loss_and_terms(on_objects, objects)
  np.testing.assert_allclose(
    loss - 0.5 * terms["dyn_aux"], base_loss - 0.5 * base_terms["dyn_aux"], rtol=1e-5
  )
  assert "objects_alpha" not in terms  # only the auxiliary render is scored on the objects
  # an empty mask: the alpha term alone asks the dynamic render to be transparent everywhere
  _, empty = loss_and_terms(on_objects, np.zeros_like(objects))
  _, full = loss_and_terms(on_objects, np.ones_like(objects))
  assert float(terms["dyn_aux"]) != pytest.approx(float(empty["dyn_aux"]))
  assert float(full["dyn_aux"]) != pytest.approx(float(empty["dyn_aux"]))
  with pytest.raises(ValueError, match="target_objects"):
    jax.jit(tokengs_loss_fn(DYNAMIC_CONFIG, on_objects, objective=objective))(
      params, batch, None, 0
    )
  with pytest.raises(ValueError, match="two masks"):
    losses.LossConfig(lambda_motion=1.0, dyn_aux_on_motion=True, dyn_aux_on_objects=True)


def test_the_object_terms_are_the_masked_error_and_the_alpha_error():
  """`_score_at_times` of the auxiliary render with "objects": objects_rgb is the error on the mask's pixels over all
  pixels, objects_alpha the render's alpha against the mask, each side averaged on its own."""
  from tokengs_jax.gaussians import Gaussians
  from tokengs_jax.objective.model_loss import _score_at_times

  height = width = 16
  flat = jnp.asarray(
    [[[[0.0, 0.0, 2.0, 0.99, 0.3, 0.3, 0.3, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0]]]], jnp.float32
  )
  gaussians = Gaussians.from_flat(flat)  # [1, 1] one red Gaussian in front of the camera
  w2c = jnp.eye(4)[None, None]
  intrinsics = jnp.asarray([[[16.0, 16.0, 8.0, 8.0]]])
  images = jnp.zeros((1, 1, height, width, 3))
  objects = jnp.zeros((1, 1, height, width)).at[..., 4:12, 4:12].set(1.0)
  views = {"world_to_camera": w2c, "intrinsics": intrinsics, "images": images, "objects": objects}
  config = losses.LossConfig(rgb_loss="l1")
  _, terms, _ = _score_at_times(
    gaussians,
    views,
    world_to_camera=w2c,
    intrinsics=intrinsics,
    loss_config=config,
    render_config=splatting.RenderConfig(),
    objective=ObjectiveConfig(background=(0.0, 0.0, 0.0)),
    lpips_params=None,
    context_images=None,
    auxiliary=True,
  )
  rendered = splatting.render(
    gaussians, w2c[:, :, None], intrinsics[:, :, None], height=16, width=16, background=jnp.zeros(3)
  )
  alpha = np.asarray(rendered.alpha)[0, 0, 0, ..., 0]
  rgb = np.asarray(rendered.rgb)[0, 0, 0]
  mask = np.asarray(objects)[0, 0]
  balanced = np.mean((1 - alpha[mask > 0]) ** 2) + np.mean(alpha[mask == 0] ** 2)
  np.testing.assert_allclose(terms["objects_alpha"], balanced, rtol=1e-5)
  np.testing.assert_allclose(
    terms["objects_rgb"], np.mean(mask[..., None] * np.abs(rgb)), rtol=1e-5
  )


@pytest.mark.slow
def test_chunked_objective_matches_one_shot(tiny):
  config, params = tiny
  batch = synthetic_batch(batch_size=1, target_views=2)
  key = jax.random.PRNGKey(0)
  results = []
  for chunk_size in (None, 1):
    loss_fn = tokengs_loss_fn(config, objective=ObjectiveConfig(view_chunk_size=chunk_size))
    results.append(jax.jit(jax.value_and_grad(loss_fn, has_aux=True))(params, batch, key, 0))
  _assert_same(results[1], results[0])
  ((_, terms), _), ((_, chunked_terms), _) = results
  for name in ("rgb", "ssim", "visibility", "psnr"):
    np.testing.assert_allclose(chunked_terms[name], terms[name], rtol=1e-5, atol=1e-7)


@pytest.mark.slow
def test_input_mean_objective_uses_each_examples_own_inputs(tiny):
  """The loss of two examples with different inputs is the mean of each one's loss over the fixed
  RGB of its own inputs' mean colour (the inputs', not the targets')."""
  config, params = tiny
  batch = synthetic_batch(batch_size=2, target_views=1)
  batch["target_images"] = 1.0 - batch["target_images"]  # mean colours unlike the inputs'
  key = jax.random.PRNGKey(0)
  input_mean = tokengs_loss_fn(config, objective=ObjectiveConfig(background="input_mean"))
  alone = []
  for b in range(2):
    one = {name: value[b : b + 1] for name, value in batch.items()}
    mean = tuple(float(c) for c in one["context_images"].mean(axis=(0, 1, 2, 3)))
    loss_fn = tokengs_loss_fn(config, objective=ObjectiveConfig(background=mean))
    alone.append(float(loss_fn(params, one, key, 0)[0]))
  np.testing.assert_allclose(input_mean(params, batch, key, 0)[0], np.mean(alone), rtol=1e-5)


def _two_supervision_views():
  """(images [2, 2, 16, 16, 3], world_to_camera, intrinsics): two examples, two views 0.3 apart."""
  images = jax.random.uniform(jax.random.key(2), (2, 2, 16, 16, 3))
  w2c = jnp.tile(jnp.eye(4), (2, 2, 1, 1)).at[:, 1, 0, 3].set(0.3)
  intrinsics = jnp.tile(jnp.array([16.0, 16.0, 8.0, 8.0]), (2, 2, 1))
  return images, w2c, intrinsics


def test_objectives_with_input_mean_use_each_examples_own_input_colour():
  """Two examples with different inputs, scored together (in view chunks), lose exactly what
  each loses alone over the fixed RGB of its own inputs' mean colour: static and time-conditioned
  objectives, the dynamic auxiliary render included."""

  gaussians, context = scene_of_two_examples()
  images, w2c, intrinsics = _two_supervision_views()
  times = jnp.array([[0.2, 0.7], [0.4, 0.9]])
  loss_config = losses.LossConfig(lambda_dyn_aux=0.3)
  render = splatting.RenderConfig()

  def static(g, views, objective, ctx=None):
    return supervision_loss(g, *views, loss_config, render, objective, context_images=ctx)[0]

  def timed(g, views, t, objective, ctx=None):
    def at(t, _world_to_camera):  # the same Gaussians at every time and camera: [B, T]
      return jax.tree.map(lambda x: jnp.repeat(x[:, None], t.shape[1], axis=1), g)

    return time_conditioned_loss(
      at, t, *views, loss_config, render, objective, num_static_gaussians=12, context_images=ctx
    )[0]

  together = ObjectiveConfig(view_chunk_size=1, background="input_mean")
  alone = [
    ObjectiveConfig(background=tuple(float(c) for c in jnp.mean(context[b], axis=(0, 1, 2))))
    for b in range(2)
  ]
  views = (images, w2c, intrinsics)
  one = lambda x, b: jax.tree.map(lambda y: y[b : b + 1], x)
  each = np.mean([static(one(gaussians, b), one(views, b), alone[b]) for b in range(2)])
  np.testing.assert_allclose(static(gaussians, views, together, context), each, rtol=1e-5)
  # the swapped inputs' colours give another loss: each example reads its own
  assert abs(float(static(gaussians, views, together, context[::-1])) - each) > 1e-4
  each = np.mean(
    [timed(one(gaussians, b), one(views, b), times[b : b + 1], alone[b]) for b in range(2)]
  )
  np.testing.assert_allclose(timed(gaussians, views, times, together, context), each, rtol=1e-5)


def test_objectives_render_one_set_per_view_as_each_view_alone():
  """Gaussians [B, V] (colours for each camera, `model.decode(viewer_c2w=)`): the static and
  the time-conditioned objectives (one decode for every view) score view v with set v alone,
  in view chunks or not; the same set repeated scores as the shared set."""

  gaussians, _ = scene_of_two_examples()
  images, w2c, intrinsics = _two_supervision_views()
  render = splatting.RenderConfig()
  recoloured = dataclasses.replace(gaussians, colors=1.0 - gaussians.colors)
  per_view = jax.tree.map(lambda a, b: jnp.stack([a, b], axis=1), gaussians, recoloured)
  repeated = jax.tree.map(lambda a: jnp.stack([a, a], axis=1), gaussians)

  def static(g, objective, loss_config, view=slice(None)):
    views = (images[:, view], w2c[:, view], intrinsics[:, view])
    return float(supervision_loss(g, *views, loss_config, render, objective)[0])

  def timed(g, objective, loss_config):
    first = ObjectiveConfig(view_chunk_size=objective.view_chunk_size, decode_times="first")
    at = lambda times, world_to_camera: g  # one decode: a set per view's camera, or [B, 1]
    times = jnp.zeros((2, 2))
    return float(
      time_conditioned_loss(at, times, images, w2c, intrinsics, loss_config, render, first)[0]
    )

  with_vis, without = losses.LossConfig(), losses.LossConfig(lambda_vis=0.0)
  one = jax.tree.map(lambda a: a[:, None], gaussians)
  objective = ObjectiveConfig(view_chunk_size=1)  # the chunked path: it slices the sets
  shared = static(gaussians, objective, with_vis)
  np.testing.assert_allclose(static(repeated, objective, with_vis), shared, rtol=1e-6)
  alone = [static(g, objective, without, slice(v, v + 1)) for v, g in enumerate(_sets_of(per_view))]
  np.testing.assert_allclose(static(per_view, objective, without), np.mean(alone), rtol=1e-5)
  assert abs(static(per_view, objective, without) - static(gaussians, objective, without)) > 1e-4
  np.testing.assert_allclose(
    timed(repeated, objective, with_vis), timed(one, objective, with_vis), rtol=1e-5
  )
  np.testing.assert_allclose(
    timed(per_view, objective, without), static(per_view, objective, without), rtol=1e-5
  )


def _sets_of(gaussians):
  """Gaussians [B, V] -> the V sets [B]."""
  return [jax.tree.map(lambda a: a[:, v], gaussians) for v in range(gaussians.batch_shape[1])]


def test_cross_view_renders_score_the_inputs_again_coloured_by_the_other_views():
  """`cross_view_renders`: the supervision views are the targets (and the inputs, under input
  supervision) coloured by the model as configured, then every input view again, coloured by
  the other views only (`own_view` False: a stand-in `reconstruct` paints each camera's set by
  the flag it is given).
  Refused for a model whose colours do not depend on the camera and for time-conditioned ones."""
  batch = synthetic_batch(batch_size=1, context_views=2, target_views=2)
  config = MICRO.replace(gaussian_colours="inputs", input_colour_weights="viewer")
  keys = jax.random.split(jax.random.key(4))
  shared = gaussians_in_front(*keys, (1, 32), spread=0.5, opacity=0.8, scale=0.1)
  painted = lambda grey: dataclasses.replace(shared, colors=jnp.full_like(shared.colors, grey))

  def reconstruct(params, images, c2w, intrinsics, *, config, viewer_c2w, own_view):
    reads_own = [True] * viewer_c2w.shape[1] if own_view is None else own_view
    sets = [painted(0.3 if own else 0.7) for own in reads_own]
    return jax.tree.map(lambda *a: jnp.stack(a, axis=1), *sets)

  settings = dict(
    model_config=config,
    loss_config=losses.LossConfig(),
    render_config=splatting.RenderConfig(),
    reconstruct=reconstruct,
  )
  views = {
    name: jnp.concatenate([batch[f"target_{name}"], batch[f"context_{name}"]], axis=1)
    for name in ("images", "c2w", "intrinsics")
  }  # targets 0, 1; inputs 2, 3

  def expected(indices, greys):
    sets = jax.tree.map(lambda *a: jnp.stack(a, axis=1), *map(painted, greys))
    return supervision_loss(
      sets,
      views["images"][:, indices],
      invert_rigid(views["c2w"][:, indices]),
      views["intrinsics"][:, indices],
      settings["loss_config"],
      settings["render_config"],
      context_images=batch["context_images"],
    )[0]

  def loss(objective, **changes):
    return static_model_loss(None, batch, objective=objective, **{**settings, **changes})[0]

  cross = ObjectiveConfig(cross_view_renders=True)
  np.testing.assert_allclose(loss(cross), expected([0, 1, 2, 3], [0.3, 0.3, 0.7, 0.7]), rtol=1e-5)
  both = loss(dataclasses.replace(cross, use_input_supervision=True))
  np.testing.assert_allclose(both, expected([0, 1, 2, 3, 2, 3], [0.3] * 4 + [0.7] * 2), rtol=1e-5)
  assert abs(float(both) - float(expected([0, 1, 2, 3, 2, 3], [0.3] * 6))) > 1e-4
  with pytest.raises(ValueError, match="viewer weights"):
    loss(cross, model_config=MICRO.replace(gaussian_colours="inputs"))
  with pytest.raises(ValueError, match="static models"):
    dynamic_model_loss(
      None,
      batch,
      0,
      model_config=DYNAMIC_CONFIG,
      loss_config=settings["loss_config"],
      render_config=settings["render_config"],
      objective=cross,
    )
