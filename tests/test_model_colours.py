"""Gaussian colours read from the input views (`tokengs_jax.model.colours`)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tokengs_jax import model
from tokengs_jax.camera import invert_rigid, project_points
from tokengs_jax.model.colours import (
  InputViews,
  bilinear_sample,
  input_colours,
  viewer_colours,
  with_input_colours,
)

H, W = 6, 8


def _numpy_bilinear(image, u, v):
  """Reference: pixel centres at +0.5, coordinates clamped to the outermost centres."""
  x = np.clip(u - 0.5, 0, W - 1)
  y = np.clip(v - 0.5, 0, H - 1)
  x0, y0 = int(np.floor(x)), int(np.floor(y))
  x1, y1 = min(x0 + 1, W - 1), min(y0 + 1, H - 1)
  fx, fy = x - x0, y - y0
  top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
  bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
  return top * (1 - fy) + bottom * fy


def test_bilinear_sample_matches_a_per_point_reference():
  rng = np.random.default_rng(0)
  images = rng.random((1, 2, H, W, 3)).astype(np.float32)
  # pixel centres, points between them, the image border and outside it (clamped)
  uv = np.array([[0.5, 0.5], [7.5, 5.5], [3.25, 2.75], [0.0, 0.0], [8.0, 6.0], [-3.0, 9.0]])
  uv = np.broadcast_to(uv, (1, 2, len(uv), 2)).astype(np.float32)
  got = np.asarray(bilinear_sample(jnp.asarray(images), jnp.asarray(uv)))
  for view in range(2):
    for n, (u, v) in enumerate(uv[0, view]):
      np.testing.assert_allclose(got[0, view, n], _numpy_bilinear(images[0, view], u, v), atol=1e-6)
  np.testing.assert_allclose(got[0, 0, 0], images[0, 0, 0, 0], atol=1e-7)  # exact at a centre


def _two_views():
  """Two cameras looking down +z, the second 0.2 along +x; images constant 0.2 and 0.8."""
  c2w = np.tile(np.eye(4, dtype=np.float32), (1, 2, 1, 1))
  c2w[0, 1, 0, 3] = 0.2
  intrinsics = np.tile(np.array([8.0, 8.0, W / 2, H / 2], np.float32), (1, 2, 1))
  images = np.zeros((1, 2, H, W, 3), np.float32)
  images[0, 0] = 0.2
  images[0, 1] = 0.8
  return InputViews(jnp.asarray(images), invert_rigid(jnp.asarray(c2w)), jnp.asarray(intrinsics))


def test_input_colours_average_the_views_that_see_the_point():
  views = _two_views()
  means = jnp.array(
    [
      [
        [0.0, 0.0, 2.0],  # both views see it: the mean of 0.2 and 0.8
        [-1.6, 0.0, 2.0],  # u = 8 * -0.8 + 4 < 0 in view 0 (and further left in view 1): no one
        [0.0, 0.0, -1.0],  # behind both cameras
        [1.1, 0.0, 2.0],  # view 0: u = 8.4 > W, view 1: u = 7.6: only view 1
      ]
    ]
  )
  colours, seen = input_colours(means, views)
  np.testing.assert_array_equal(np.asarray(seen), [[True, False, False, True]])
  np.testing.assert_allclose(np.asarray(colours[0, 0]), 0.5, atol=1e-6)
  np.testing.assert_allclose(np.asarray(colours[0, 3]), 0.8, atol=1e-6)


def test_a_non_finite_centre_is_unseen_with_a_zero_gradient():
  views = _two_views()
  means = jnp.array([[[0.0, 0.0, 2.0], [jnp.nan, 0.0, 2.0], [jnp.inf, 1.0, 2.0]]])
  colours, seen = input_colours(means, views)
  np.testing.assert_array_equal(np.asarray(seen), [[True, False, False]])
  assert bool(jnp.all(jnp.isfinite(colours)))
  grad = jax.grad(lambda m: jnp.sum(input_colours(m, views)[0]))(means)
  np.testing.assert_array_equal(np.asarray(grad[0, 1:]), 0.0)


def test_viewer_colours_follow_the_view_whose_ray_is_nearest():
  """Views 0.2 / 0.8 at x = 0 / 0.2: a point both see takes the colour of the view at the viewer,
  the mean from halfway (equal rays) or at sharpness 0, and a view that does not see a point
  never counts."""
  views = _two_views()
  means = jnp.array([[[0.1, 0.0, 2.0], [1.1, 0.0, 2.0], [0.0, 0.0, -1.0]]])  # both, view 1, none
  viewers = jnp.array([[[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.1, 0.0, 0.0]]])
  colours, seen = viewer_colours(means, views, means, viewers, sharpness=1e4)
  np.testing.assert_array_equal(np.asarray(seen), [[[True, True, False]] * 3])  # per viewer
  np.testing.assert_allclose(np.asarray(colours[0, :, 0, 0]), [0.2, 0.8, 0.5], atol=1e-5)
  np.testing.assert_allclose(np.asarray(colours[0, :, 1, 0]), 0.8, atol=1e-6)
  mean, _ = input_colours(means, views)
  flat, _ = viewer_colours(means, views, means, viewers, sharpness=0.0)
  np.testing.assert_allclose(np.asarray(flat[0, :, :2]), np.asarray(mean[0, None, :2]).repeat(3, 0))
  # softer: the nearer view dominates without taking all the weight
  soft, _ = viewer_colours(means, views, means, viewers[:, :1], sharpness=100.0)
  assert 0.2 < float(soft[0, 0, 0, 0]) < 0.5
  grad = jax.grad(lambda m: jnp.sum(viewer_colours(m, views, m, viewers, 100.0)[0]))(means)
  assert bool(jnp.all(jnp.isfinite(grad)))


def test_a_viewer_at_an_input_view_reads_only_the_other_views_without_own_view():
  """own_view=False: from view 0's centre a point both see takes view 1's colour at any
  sharpness, a point only view 0 sees is unseen from there (head colour), and a viewer elsewhere
  weighs the views as before."""
  views = _two_views()
  means = jnp.array(
    [[[0.1, 0.0, 2.0], [-0.9, 0.0, 2.0]]]
  )  # both views; view 0 only (u = 0.4, -0.4)
  viewers = jnp.array([[[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]]])  # view 0's centre; halfway
  colours, seen = viewer_colours(means, views, means, viewers, 100.0, own_view=False)
  np.testing.assert_array_equal(np.asarray(seen), [[[True, False], [True, True]]])
  np.testing.assert_allclose(np.asarray(colours[0, 0, 0]), 0.8, atol=1e-6)
  kept, kept_seen = viewer_colours(means, views, means, viewers, 100.0)
  np.testing.assert_array_equal(np.asarray(kept_seen), True)
  np.testing.assert_allclose(np.asarray(colours[0, 1]), np.asarray(kept[0, 1]), atol=1e-7)
  flat = jnp.concatenate([means, jnp.zeros((1, 2, 8)), jnp.full((1, 2, 3), 0.33)], axis=-1)
  coloured = with_input_colours(flat, views, viewers=viewers, sharpness=100.0, own_view=False)
  np.testing.assert_allclose(np.asarray(coloured[0, 0, :, 11:]), [[0.8] * 3, [0.33] * 3], atol=1e-6)


def test_own_view_per_viewer_is_each_viewer_read_as_that_flag_alone(tiny_inputs_model):
  """`own_view` [T] decides per viewer: one decode for the input cameras twice, flags
  [True, True, False, False], equals the decodes with `own_view_colours` True and False side by
  side; a model configured never to read its own view ignores the flags."""
  config, params = tiny_inputs_model
  config = config.replace(input_colour_weights="viewer", viewer_colour_sharpness=100.0)
  views = _plane_views(size=(32, 32))
  c2w = invert_rigid(views.world_to_camera)
  twice = jnp.concatenate([c2w, c2w], axis=1)
  args = (params, views.images, c2w, views.intrinsics)
  flags = np.array([True, True, False, False])
  mixed = model.reconstruct(*args, config=config, viewer_c2w=twice, own_view=flags).to_flat()
  own = model.reconstruct(*args, config=config, viewer_c2w=c2w).to_flat()
  others = config.replace(own_view_colours=False)
  cross = model.reconstruct(*args, config=others, viewer_c2w=c2w).to_flat()
  np.testing.assert_array_equal(np.asarray(mixed), np.concatenate([own, cross], axis=1))
  assert np.abs(np.asarray(own - cross)).max() > 1e-3  # the flags matter here
  never = model.reconstruct(*args, config=others, viewer_c2w=twice, own_view=flags).to_flat()
  np.testing.assert_array_equal(np.asarray(never), np.concatenate([cross, cross], axis=1))


def test_decoded_for_cameras_one_set_each_same_geometry(tiny_inputs_model):
  """`reconstruct(viewer_c2w=)`: one set per camera whose geometry is the camera-free decode's;
  viewer weights colour set v from view v (the input cameras themselves, sharp weights), mean
  weights repeat the one set."""
  config, params = tiny_inputs_model
  views = _plane_views(size=(32, 32))
  c2w = invert_rigid(views.world_to_camera)
  args = (params, views.images, c2w, views.intrinsics)
  one = model.reconstruct(*args, config=config)
  repeated = model.reconstruct(*args, config=config, viewer_c2w=c2w)
  assert repeated.batch_shape == (1, 2)
  np.testing.assert_array_equal(np.asarray(repeated.to_flat()[:, 1]), np.asarray(one.to_flat()))
  sharp = config.replace(input_colour_weights="viewer", viewer_colour_sharpness=1e4)
  assert sharp.viewer_dependent and not config.viewer_dependent
  each = model.reconstruct(*args, config=sharp, viewer_c2w=c2w)
  np.testing.assert_allclose(
    np.asarray(each.to_flat()[..., :11]), np.asarray(repeated.to_flat()[..., :11])
  )
  uv, depth = project_points(one.means, views.world_to_camera, views.intrinsics)
  inside = np.asarray((depth > 0.025) & jnp.all((uv >= 0) & (uv <= 32), axis=-1))[0]  # [V, N]
  samples = np.asarray(bilinear_sample(views.images, uv))[0]
  for v in range(2):
    only_v = inside[v] & ~inside[1 - v]  # seen by view v alone: its sample whatever the weight
    both = inside[v] & inside[1 - v]
    assert both.any()
    colours = np.asarray(each.colors[0, v])
    np.testing.assert_allclose(colours[both | only_v], samples[v][both | only_v], atol=1e-4)


def _plane_views(depth=2.0, size=(24, 32)):
  """Two cameras 0.3 apart along +x photographing the plane z = `depth` textured 0.5 + 0.4 sin 3x
  (each pixel the texture where its centre's ray meets the plane)."""
  h, w = size
  intrinsics = np.tile(np.array([20.0, 20.0, w / 2, h / 2], np.float32), (1, 2, 1))
  c2w = np.tile(np.eye(4, dtype=np.float32), (1, 2, 1, 1))
  c2w[0, 1, 0, 3] = 0.3
  u = np.arange(w) + 0.5
  images = np.zeros((1, 2, h, w, 3), np.float32)
  for view in range(2):
    x = (u - w / 2) / 20.0 * depth + c2w[0, view, 0, 3]
    images[0, view] = (0.5 + 0.4 * np.sin(3 * x))[None, :, None]
  return InputViews(jnp.asarray(images), invert_rigid(jnp.asarray(c2w)), jnp.asarray(intrinsics))


def _view_disagreement(means, views):
  uv, _ = project_points(means, views.world_to_camera, views.intrinsics)
  samples = bilinear_sample(views.images, uv)  # [1, 2, N, 3]
  return jnp.sum((samples[:, 0] - samples[:, 1]) ** 2)


def test_points_on_the_photographed_surface_read_one_colour_from_both_views():
  """Checks the projection and the +0.5 pixel-centre convention end to end: on the surface both
  views give the texture's colour; off it they disagree."""
  views = _plane_views()
  xs = np.linspace(-0.4, 0.6, 9, dtype=np.float32)
  on = jnp.asarray(np.stack([xs, np.zeros_like(xs), np.full_like(xs, 2.0)], -1)[None])
  colours, seen = input_colours(on, views)
  assert bool(jnp.all(seen))
  np.testing.assert_allclose(np.asarray(colours[0, :, 0]), 0.5 + 0.4 * np.sin(3 * xs), atol=6e-3)
  off = on.at[..., 2].multiply(0.7)
  assert float(_view_disagreement(on, views)) < 0.02 * float(_view_disagreement(off, views))


def test_the_disagreement_gradient_points_along_the_ray_to_the_surface():
  """What trains geometry through the colours: at a wrong depth, descending the views'
  disagreement moves the point along its view-0 ray toward the photographed surface."""
  views = _plane_views()
  ray = jnp.array([0.1, 0.0, 1.0])
  slope = jax.grad(lambda d: _view_disagreement((d * ray)[None, None], views))
  assert float(slope(1.7)) < 0 < float(slope(2.3))


def test_reconstruct_reads_colours_from_the_inputs_and_differentiates(tiny_inputs_model):
  config, params = tiny_inputs_model
  rng = np.random.default_rng(0)
  images = jnp.asarray(rng.random((1, 2, 32, 32, 3)), jnp.float32)
  c2w = np.tile(np.eye(4, dtype=np.float32), (1, 2, 1, 1))
  c2w[0, 1, 0, 3] = 0.1
  intrinsics = jnp.asarray(np.tile(np.array([30, 30, 16, 16], np.float32), (1, 2, 1)))
  gaussians = model.reconstruct(params, images, jnp.asarray(c2w), intrinsics, config=config)
  views = InputViews(images, invert_rigid(jnp.asarray(c2w)), intrinsics)
  expected, seen = input_colours(gaussians.means, views)
  assert bool(jnp.any(seen))
  np.testing.assert_allclose(
    np.asarray(gaussians.colors)[np.asarray(seen)], np.asarray(expected)[np.asarray(seen)]
  )
  # uint8 inputs read the same colours
  as_uint8 = jnp.round(images * 255).astype(jnp.uint8)
  again = model.reconstruct(params, as_uint8, jnp.asarray(c2w), intrinsics, config=config)
  np.testing.assert_allclose(np.asarray(again.colors), np.asarray(gaussians.colors), atol=3e-3)

  def colour_sum(p):
    g = model.reconstruct(p, images, jnp.asarray(c2w), intrinsics, config=config)
    return jnp.sum(g.colors * g.means[..., :1])

  grads = jax.jit(jax.grad(colour_sum))(params)
  leaves = jax.tree_util.tree_leaves(grads)
  assert all(bool(jnp.all(jnp.isfinite(g))) for g in leaves)
  assert float(jnp.abs(grads["activation_head"]["deconv"]["kernel"]).max()) > 0


def test_the_low_level_forward_cannot_read_colours(tiny_inputs_model):
  config, params = tiny_inputs_model
  with pytest.raises(ValueError, match="encode_views"):
    model.predict_gaussians(
      params, jnp.zeros((1, 2, 32, 32, 3)), jnp.zeros((1, 2, 32, 32, 6)), config
    )


@pytest.fixture(scope="module")
def tiny_inputs_model():
  config = model.preset(
    "tiny",
    image_size=(32, 32),
    num_gs_tokens=16,
    dec_patch_size=2,
    clip_head_readout_std=0.3,
    gaussian_colours="inputs",
  )
  return config, model.init_params(jax.random.key(0), config)


def test_tuned_scene_latents_keep_reading_colours_from_the_views():
  """Scene-latent tuning rebuilds the encoder output from the latents; the views must survive."""
  from tokengs_jax.tuning import _decode

  config = model.preset(
    "tiny",
    use_latent_bottleneck=True,
    num_latents=8,
    latent_cross_attn_depth=1,
    num_gs_tokens=8,
    dec_patch_size=2,
    clip_head_readout_std=0.3,
    gaussian_colours="inputs",
  )
  params = model.init_params(jax.random.key(0), config)
  views = _plane_views(size=(16, 16))
  c2w = invert_rigid(views.world_to_camera)
  encoded = model.encode_views(params, views.images, c2w, views.intrinsics, config)
  gaussians = _decode(params, encoded, config, latents=encoded.latents * 1.5)
  expected, seen = input_colours(gaussians.means, views)
  assert bool(jnp.any(seen))
  np.testing.assert_allclose(
    np.asarray(gaussians.colors)[np.asarray(seen)],
    np.asarray(expected)[np.asarray(seen)],
    atol=1e-6,
  )


def test_per_view_positions_read_each_view_where_the_point_was_then():
  """A point that moved between the views' times: read at one place it averages 0.2 and 0.8
  images' pixels as any static point; with its position per view, each view is read there."""
  views = _two_views()
  images = np.zeros((1, 2, H, W, 3), np.float32)
  images[0, 0, :, :4] = 1.0  # view 0: left half white; view 1: right half white
  images[0, 1, :, 4:] = 1.0
  views = views.replace(images=jnp.asarray(images))
  # view 0 (camera at x = 0) saw it at x = -0.5; view 1 (camera at x = 0.2) at x = 0.7
  per_view = jnp.array([[[[-0.5, 0.0, 2.0]], [[0.7, 0.0, 2.0]]]])
  colours, seen = input_colours(per_view, views)
  assert bool(seen[0, 0])
  np.testing.assert_allclose(np.asarray(colours[0, 0]), 1.0, atol=1e-6)  # white in both
  still, _ = input_colours(per_view[:, 0], views)  # where view 0 saw it, read in both views
  np.testing.assert_allclose(np.asarray(still[0, 0]), 0.5, atol=1e-6)
  # a point outside view 1's image at its time counts only view 0
  colours, seen = input_colours(per_view.at[0, 1, 0, 0].set(5.0), views)
  np.testing.assert_allclose(np.asarray(colours[0, 0]), 1.0, atol=1e-6)


def _dynamic_inputs_model(**overrides):
  """(config, params) of a tiny dynamic model reading its colours from the views, with a random
  target-time embedding (it starts at zero, as the official one: time would move nothing)."""
  fields = dict(
    image_size=(32, 32),
    num_gs_tokens=8,
    num_dynamic_gs_tokens=4,
    time_embedding=True,
    gs_token_std=1.0,
    dec_patch_size=2,
    clip_head_readout_std=0.3,
    gaussian_colours="inputs",
  )
  config = model.preset("tiny", **{**fields, **overrides})
  params = model.init_params(jax.random.key(1), config)
  # under linear motion the velocities are what time moves (zero at initialisation too)
  moves = params["patch_time_embed_tgt"]["proj"] if "patch_time_embed_tgt" in params else None
  moves = moves or params["motion_head"]
  moves["kernel"] = jax.random.normal(jax.random.key(2), moves["kernel"].shape)
  return config, params


def test_dynamic_gaussians_read_the_views_at_the_views_times():
  """With the input times, each dynamic Gaussian's colour is read in view v at its centre decoded
  at view v's time; static Gaussians are read where they are."""
  config, params = _dynamic_inputs_model()
  views = _plane_views(size=(32, 32))
  c2w = invert_rigid(views.world_to_camera)
  times = jnp.array([[0.0, 1.0]])
  encoded = model.encode_views(params, views.images, c2w, views.intrinsics, config, times=times)
  flat = model.decode(params, encoded, config, times=jnp.array([0.5]))  # [1, N, 14]
  first = config.num_static_gaussians
  at = [model.decode(params, encoded, config, times=times[:, v]) for v in range(2)]
  per_view = jnp.stack([f[:, first:, :3] for f in at], axis=1)  # [1, V, Nd, 3]
  moving, moving_seen = input_colours(per_view, views)
  still, still_seen = input_colours(flat[:, :first, :3], views)
  assert bool(jnp.any(moving_seen)) and bool(jnp.any(still_seen))
  rgb = np.asarray(flat[..., 11:14])
  np.testing.assert_allclose(
    rgb[:, first:][moving_seen], np.asarray(moving)[moving_seen], atol=1e-5
  )
  np.testing.assert_allclose(rgb[:, :first][still_seen], np.asarray(still)[still_seen], atol=1e-5)
  # the trajectories move, so reading every view at the target-time centres would differ
  assert float(jnp.abs(at[0][:, first:, :3] - at[1][:, first:, :3]).max()) > 1e-4


def test_linear_motion_reads_each_view_where_the_moved_gaussian_was_then():
  """`dynamic_motion="linear"`: a dynamic Gaussian's colour is read in view v at its centre moved
  to view v's time (what a decode at that time puts there), static ones where they are."""
  config, params = _dynamic_inputs_model(dynamic_motion="linear", clip_head_readout_std=0.02)
  head = config.replace(gaussian_colours="head")
  views = _plane_views(size=(32, 32))
  views = views.replace(images=jax.random.uniform(jax.random.key(5), views.images.shape))
  c2w = invert_rigid(views.world_to_camera)
  times, target = jnp.array([[0.0, 1.0]]), jnp.array([0.3])
  first = config.num_static_gaussians
  encoded = model.encode_views(params, views.images, c2w, views.intrinsics, config, times=times)
  got = model.decode(params, encoded, config, times=target)
  flat = model.decode(params, encoded, head, times=target)
  at = jnp.stack(
    [model.decode(params, encoded, head, times=times[:, v])[:, first:] for v in range(2)], axis=1
  )
  np.testing.assert_allclose(
    np.asarray(got), np.asarray(with_input_colours(flat, views, at)), rtol=0, atol=1e-6
  )
  # the views' times matter: read at the target-time centres the colours differ
  at_target = with_input_colours(flat, views, None)
  assert float(jnp.abs(got[:, first:, 11:] - at_target[:, first:, 11:]).max()) > 1e-3


# the learnt tokens' case is slow: the tuned ones take the same path with other values
@pytest.mark.parametrize("tuned", [pytest.param(False, marks=pytest.mark.slow), True])
def test_decoding_only_the_dynamic_tokens_at_the_views_times_changes_nothing(tuned):
  """`decode` decodes the dynamic tokens alone at each view's time, against the static tokens'
  keys/values of the decode at the target time: its Gaussians and their gradients equal those of
  decoding every token at each view's time (the reference below), for the learnt tokens and for
  tuned ones, with the occlusion test on (it renders the scene at each view's time)."""
  # a smaller readout than the helper's keeps the centres within ~50 (at 0.3 they reach 1e24 and
  # their gradients 1e26, where float32 cannot compare two summation orders)
  config, params = _dynamic_inputs_model(clip_head_readout_std=0.02, input_occlusion_tolerance=0.1)
  head = config.replace(gaussian_colours="head")  # the same parameters, no colours read
  # noise images: a colour read anywhere else differs
  views = _plane_views(size=(32, 32))
  views = views.replace(images=jax.random.uniform(jax.random.key(5), views.images.shape))
  c2w = invert_rigid(views.world_to_camera)
  times, target = jnp.array([[0.0, 1.0]]), jnp.array([0.4])
  first = config.num_static_gaussians
  tokens = None
  if tuned:
    learnt = model.initial_tokens(params, config, 1)
    tokens = learnt + 0.3 * jax.random.normal(jax.random.key(3), learnt.shape)

  def encoded(params):
    return model.encode_views(params, views.images, c2w, views.intrinsics, config, times=times)

  def decoded(params, tokens):
    return model.decode(params, encoded(params), config, tokens, target)

  def reference(params, tokens, dynamic_at_view_times=True):
    flat = model.decode(params, encoded(params), head, tokens, target)
    at = None
    if dynamic_at_view_times:
      each = [model.decode(params, encoded(params), head, tokens, times[:, v]) for v in range(2)]
      at = jnp.stack([f[:, first:] for f in each], axis=1)
    return with_input_colours(flat, views, at, occlusion_tolerance=0.1)

  got, expected = jax.jit(decoded)(params, tokens), jax.jit(reference)(params, tokens)
  np.testing.assert_allclose(np.asarray(got), np.asarray(expected), rtol=0, atol=1e-5)
  # the dynamic Gaussians' colours do depend on where they were at the views' times
  at_target = reference(params, tokens, dynamic_at_view_times=False)
  assert float(jnp.abs(expected[:, first:, 11:] - at_target[:, first:, 11:]).max()) > 1e-3

  weights = jax.random.normal(jax.random.key(4), got.shape)
  grads = [
    jax.jit(jax.grad(lambda p, t, f=f: jnp.sum(f(p, t) * weights), argnums=(0, 1)))(params, tokens)
    for f in (decoded, reference)
  ]
  for new, old in zip(jax.tree.leaves(grads[0]), jax.tree.leaves(grads[1]), strict=True):
    np.testing.assert_allclose(
      np.asarray(new), np.asarray(old), rtol=0, atol=1e-5 * max(1.0, float(jnp.abs(old).max()))
    )
  time_kernel = grads[0][0]["patch_time_embed_tgt"]["proj"]["kernel"]
  assert float(jnp.abs(time_kernel).max()) > 0


def _occlusion_scene():
  """Two cameras looking down +z, the second 1.0 along +x, 16x16 images constant 0.2 / 0.8; an
  opaque Gaussian at z = 1 in front of view 0's centre hides a point at z = 3 from view 0 only
  (view 1 sees the point at u = 2.7 and has the front Gaussian outside its image)."""
  c2w = np.tile(np.eye(4, dtype=np.float32), (1, 2, 1, 1))
  c2w[0, 1, 0, 3] = 1.0
  intrinsics = np.tile(np.array([16.0, 16.0, 8.0, 8.0], np.float32), (1, 2, 1))
  images = np.zeros((1, 2, 16, 16, 3), np.float32)
  images[0, 0], images[0, 1] = 0.2, 0.8
  views = InputViews(jnp.asarray(images), invert_rigid(jnp.asarray(c2w)), jnp.asarray(intrinsics))
  front = [0.0, 0.0, 1.0, 0.99, 0.2, 0.2, 0.2, 1.0, 0.0, 0.0, 0.0, 0.5, 0.5, 0.5]
  back = [0.0, 0.0, 3.0, 0.99, 0.01, 0.01, 0.01, 1.0, 0.0, 0.0, 0.0, 0.5, 0.5, 0.5]
  return views, jnp.asarray([[front, back]], jnp.float32)


def test_a_view_that_hides_a_gaussian_gives_it_no_colour():
  views, flat = _occlusion_scene()
  plain = with_input_colours(flat, views)
  np.testing.assert_allclose(np.asarray(plain[0, :, 11]), [0.2, 0.5], atol=1e-5)
  tested = with_input_colours(flat, views, occlusion_tolerance=0.1)
  # the back point is read in view 1 only; the front one, the surface view 0 sees, stays
  np.testing.assert_allclose(np.asarray(tested[0, :, 11]), [0.2, 0.8], atol=1e-5)
  np.testing.assert_array_equal(np.asarray(tested[..., :11]), np.asarray(flat[..., :11]))
  # a tolerance wider than the gap between the two (z 3 against 1) hides nothing
  loose = with_input_colours(flat, views, occlusion_tolerance=2.5)
  np.testing.assert_allclose(np.asarray(loose[0, :, 11]), [0.2, 0.5], atol=1e-5)
  # seen from view 0's camera with viewer weights, the hidden view's colour is not taken either
  viewers = jnp.zeros((1, 1, 3))
  sharp = with_input_colours(flat, views, viewers=viewers, sharpness=1e4, occlusion_tolerance=0.1)
  np.testing.assert_allclose(np.asarray(sharp[0, 0, :, 11]), [0.2, 0.8], atol=1e-5)
  unhidden = with_input_colours(flat, views, viewers=viewers, sharpness=1e4)
  np.testing.assert_allclose(np.asarray(unhidden[0, 0, :, 11]), [0.2, 0.2], atol=1e-5)
  grad = jax.grad(
    lambda f: jnp.sum(
      with_input_colours(f, views, viewers=viewers, sharpness=100.0, occlusion_tolerance=0.1)
    )
  )(flat)
  assert bool(jnp.all(jnp.isfinite(grad)))


def test_a_gaussian_hidden_in_every_view_keeps_the_views_colours():
  """Moved so that view 1 does not contain it, the back point is hidden in the only view left:
  the test would leave it no colour, so it is read as without the test."""
  views, flat = _occlusion_scene()
  flat = flat.at[0, 1, 0].set(-0.2)  # view 0 still sees the front Gaussian over it
  # view 1's principal point moved off the image: u = 16 * -1.2 / 3 - 8 < 0, outside
  views = views.replace(intrinsics=views.intrinsics.at[0, 1, 2].set(-8.0))
  tested = with_input_colours(flat, views, occlusion_tolerance=0.1)
  plain = with_input_colours(flat, views)
  np.testing.assert_allclose(np.asarray(tested), np.asarray(plain), atol=1e-6)
  np.testing.assert_allclose(np.asarray(tested[0, 1, 11]), 0.2, atol=1e-5)


def test_the_occlusion_tolerance_and_the_sharpnesses_are_checked():
  with pytest.raises(ValueError, match="input_occlusion_tolerance"):
    model.preset("tiny", input_occlusion_tolerance=-0.1)
  with pytest.raises(ValueError, match="dynamic_colour_sharpness"):
    model.preset("tiny", dynamic_colour_sharpness=float("nan"))
  with pytest.raises(ValueError, match="viewer_colour_sharpness"):
    model.preset("tiny", viewer_colour_sharpness=float("inf"))
  assert model.preset("tiny", input_occlusion_tolerance=0.1).input_occlusion_tolerance == 0.1


def test_the_dynamic_gaussians_can_average_the_views_while_the_static_ones_follow_the_viewer():
  """`dynamic_sharpness=0`: a dynamic Gaussian takes the mean of the views that see it (read
  where it was at each view's time), a static one the view nearest the viewer."""
  views = _two_views()
  point = [0.1, 0.0, 2.0, 0.9, 0.1, 0.1, 0.1, 1.0, 0.0, 0.0, 0.0, 0.5, 0.5, 0.5]
  flat = jnp.asarray([[point, point]], jnp.float32)  # static, dynamic
  at_view_times = jnp.broadcast_to(flat[:, None, 1:], (1, 2, 1, 14))
  viewers = jnp.zeros((1, 1, 3))  # view 0's centre
  kwargs = dict(viewers=viewers, sharpness=1e4)
  same = with_input_colours(flat, views, at_view_times, **kwargs)
  np.testing.assert_allclose(np.asarray(same[0, 0, :, 11]), [0.2, 0.2], atol=1e-5)
  mixed = with_input_colours(flat, views, at_view_times, dynamic_sharpness=0.0, **kwargs)
  np.testing.assert_allclose(np.asarray(mixed[0, 0, :, 11]), [0.2, 0.5], atol=1e-5)
