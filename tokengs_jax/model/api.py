"""Pure-function interface to the TokenGS network: params pytree in, arrays out.

Every function takes the (hashable, frozen) config as an argument, so it can be a static
argument of `jax.jit` or be closed over; all of them are jit-, vmap- and grad-compatible.

    params = init_params(jax.random.key(0), config)
    gaussians = reconstruct(params, images, c2w, intrinsics, config=config)

For test-time tuning, encode once and decode many times:

    encoded = encode_views(params, images, c2w, intrinsics, config)
    flat = decode(params, encoded, config, tokens=my_tokens)

Time-conditioned models decode one encoding at several times with `decode_at_times`.

`encode_views` and `reconstruct` check their inputs' shapes and dtypes at trace time, and their
values where concrete (`model.inputs.check_views`); the lower-level `encode` /
`predict_gaussians` take what they get.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from tokengs_jax.camera import invert_rigid, plucker_rays
from tokengs_jax.gaussians import Gaussians
from tokengs_jax.model.colours import InputViews
from tokengs_jax.model.configs import IMAGE_MEAN, IMAGE_STD, ModelConfig
from tokengs_jax.model.inputs import check_times, check_views
from tokengs_jax.model.network import EncoderOutput, TokenGS

Params = dict


def _dummy_inputs(config: ModelConfig) -> dict:
  """Smallest inputs that create every parameter: one view of one patch."""
  p = config.patch_size
  inputs = {"images": jnp.zeros((1, 1, p, p, 3)), "plucker": jnp.zeros((1, 1, p, p, 6))}
  if config.time_embedding:
    inputs.update(times=jnp.zeros((1, 1)), target_times=jnp.zeros((1,)))
  return inputs


def init_params(key: jax.Array, config: ModelConfig) -> Params:
  """Freshly initialised parameters (float32), initialised as the official model.

  Args:
    key: a PRNG key.
    config: the architecture.

  Returns:
    The params pytree (nested dicts of float32 arrays).
  """
  return _jitted_init(key, config)


@functools.partial(jax.jit, static_argnums=1)
def _jitted_init(key: jax.Array, config: ModelConfig) -> Params:
  # One compiled program instead of hundreds of eagerly dispatched initialiser ops. The colour
  # source adds no parameters, and the dummy forward pass has no cameras to read colours with.
  network = TokenGS(config.replace(gaussian_colours="head"))
  return network.init(key, **_dummy_inputs(config))["params"]


def param_shapes(config: ModelConfig) -> Params:
  """The params pytree as jax.ShapeDtypeStruct leaves, without allocating anything."""
  return jax.eval_shape(functools.partial(init_params, config=config), jax.random.key(0))


def count_params(config: ModelConfig) -> int:
  """Number of parameters (no allocation)."""
  return sum(leaf.size for leaf in jax.tree_util.tree_leaves(param_shapes(config)))


# The Dense modules built without `matmul_dtype`: their products stay in the compute dtype, so
# their kernels must too (`GaussianHead`'s readout, the linear motion head).
_FULL_PRECISION_MODULES = frozenset({"activation_head", "motion_head"})


def cast_matmul_kernels(params: Params, config: ModelConfig) -> Params:
  """The params with every kernel that `config.matmul_dtype` rounds stored already rounded.

  For repeated calls on frozen weights (serving, evaluating scene by scene): every call would
  otherwise round the same kernels again, 35 casts in the small benchmark's forward, ~4% of its
  bf16 time (docs/benchmarks.md). Inside one jitted loop (token tuning's scan) XLA already hoists
  the casts out of the loop. The network computes the same Gaussians bit for bit from
  either tree (`tests/test_model_matmul.py`). Not for training: the optimiser would update the
  rounded copies. Without a `matmul_dtype` the params come back unchanged.

  Args:
    params: the params pytree (float32 leaves).
    config: the architecture; its `matmul_dtype` decides.

  Returns:
    The same pytree with the matmuls' kernels in `config.matmul_dtype`, everything else as given.
  """
  operand_dtype = config.matmul_operand_dtype
  if operand_dtype is None:
    return params

  def cast(path, leaf):
    names = [entry.key for entry in path]
    rounded = names[-1] == "kernel" and names[0] not in _FULL_PRECISION_MODULES
    return leaf.astype(operand_dtype) if rounded else leaf

  return jax.tree_util.tree_map_with_path(cast, params)


def normalize_images(images: jax.Array) -> jax.Array:
  """RGB -> the encoder's input (ImageNet mean/std, as the official data provider).

  images: [..., 3], float in [0, 1] or uint8 in [0, 255] (scaled by 1/255 here) -> [..., 3]
  float (float32 for uint8, else the input's float dtype).

  Raises ValueError (at trace time) unless the last axis is 3 (e.g. grayscale [..., 1]),
  TypeError for other dtypes, and, when the values are concrete (not traced), ValueError for
  float values outside [0, 1] (e.g. 0..255 floats, which would silently saturate the encoder)
  or NaN.
  """
  if np.ndim(images) == 0 or np.shape(images)[-1] != 3:
    raise ValueError(
      f"images: expected RGB [..., 3], got shape {list(np.shape(images))}"
      + (" (grayscale: repeat it to 3 channels)" if np.shape(images)[-1:] == (1,) else "")
    )
  dtype = jnp.result_type(images)
  if dtype == jnp.uint8:
    images = jnp.asarray(images).astype(jnp.float32) / 255.0
  elif not jnp.issubdtype(dtype, jnp.floating):
    raise TypeError(f"images: expected float in [0, 1] or uint8 in [0, 255], got {dtype}")
  elif not isinstance(images, jax.core.Tracer) and np.size(images):
    values = np.asarray(images)  # numpy: jnp.min here would be staged inside an outer jit
    low, high = float(values.min()), float(values.max())
    if not -_RANGE_SLACK <= low <= high <= 1.0 + _RANGE_SLACK:  # NaN compares false: refused
      raise ValueError(
        f"images: expected float values in [0, 1], got [{low:.4g}, {high:.4g}]"
        + (" (0..255 values: divide by 255 or pass uint8)" if high > 2.0 else "")
      )
  images = jnp.asarray(images)
  mean = jnp.asarray(IMAGE_MEAN, images.dtype)
  std = jnp.asarray(IMAGE_STD, images.dtype)
  return (images - mean) / std


_RANGE_SLACK = 1e-3  # resampled or low-precision images may overshoot [0, 1] by a hair


def encode(
  params: Params,
  images: jax.Array,
  plucker: jax.Array,
  config: ModelConfig,
  times: jax.Array | None = None,
) -> EncoderOutput:
  """Encoder: normalised images + Plücker rays -> shared keys/values.

  Args:
    params: the params pytree.
    images: [B, V, H, W, 3] normalised RGB (see `normalize_images`); H, W divisible by p.
    plucker: [B, V, H, W, 6] Plücker rays (`tokengs_jax.camera.plucker_rays`).
    config: the architecture.
    times: [B, V] normalised input-view times (time-embedding models only).

  Returns:
    EncoderOutput (keys/values [B, heads, V * H * W / p², head_dim]; latents if any).
  """
  return TokenGS(config).apply({"params": params}, images, plucker, times, method=TokenGS.encode)


def kv_from_latents(params: Params, latents: jax.Array, config: ModelConfig) -> EncoderOutput:
  """Latent-bottleneck models: scene latents [B, L, C] -> EncoderOutput (scene-latent tuning)."""
  return TokenGS(config).apply({"params": params}, latents, method=TokenGS.kv_from_latents)


def initial_tokens(params: Params, config: ModelConfig, batch_size: int) -> jax.Array:
  """The learnt Gaussian tokens [B, T, C] ([static, dynamic]); token tuning starts from them."""
  return TokenGS(config).apply({"params": params}, batch_size, method=TokenGS.initial_tokens)


def decode_tokens(
  params: Params,
  encoded: EncoderOutput,
  config: ModelConfig,
  tokens: jax.Array | None = None,
  times: jax.Array | None = None,
) -> jax.Array:
  """Gaussian tokens after the last decoder block, [B, T, C] (the head's input)."""
  return TokenGS(config).apply(
    {"params": params}, encoded, tokens, times, method=TokenGS.decode_tokens
  )


def decode(
  params: Params,
  encoded: EncoderOutput,
  config: ModelConfig,
  tokens: jax.Array | None = None,
  times: jax.Array | None = None,
  viewer_c2w: jax.Array | None = None,
  static_scene: bool = False,
  own_view: jax.Array | None = None,
) -> jax.Array:
  """Decoder + head: cached encoder output -> flat Gaussians.

  Args:
    params: the params pytree.
    encoded: `encode`'s output (or `kv_from_latents`'s).
    config: the architecture.
    tokens: [B, T, C] Gaussian tokens replacing the learnt ones (token tuning); None uses
      `params["gs_tokens"]` (+ dynamic tokens).
    times: [B] normalised target time (time-embedding models; None = unconditioned).
    viewer_c2w: [B, Vr, 4, 4] camera-to-world of the cameras the Gaussians will be rendered
      from: one set per camera, coloured for it where `config.viewer_dependent` (else the same
      set repeated). None: one set, colours from the views' mean.
    static_scene: (static, a Python bool) the scene does not move: the dynamic branch is
      skipped entirely and only the static Gaussians are returned, equal to the first
      `config.num_static_gaussians` of the full decode (colours too, except under
      `input_occlusion_tolerance`, where no dynamic Gaussian hides them). A model without
      dynamic tokens returns what it always does.
    own_view: [Vr] bool, per camera of `viewer_c2w`: whether one at an input view's centre
      reads that view's colours (False: the other views', a render that tests the geometry;
      `ObjectiveConfig.cross_view_renders`). None: `config.own_view_colours` for all; that
      False overrides it.

  Returns:
    [B, T * dec_patch_size², 14] float32 in the official flat layout
    [xyz 3, opacity 1, scale 3, quat 4, rgb 3]; static Gaussians first, then dynamic ones
    (`config.num_static_gaussians` splits them). [B, Vr, ...] with `viewer_c2w`.
  """
  viewers = None if viewer_c2w is None else jnp.asarray(viewer_c2w, jnp.float32)[..., :3, 3]
  return TokenGS(config).apply(
    {"params": params},
    encoded,
    tokens,
    times,
    viewers,
    static_scene,
    own_view,
    method=TokenGS.decode,
  )


def decode_at_times(
  params: Params,
  encoded: EncoderOutput,
  model_config: ModelConfig,
  times: jax.Array,
  tokens: jax.Array | None = None,
  viewer_c2w: jax.Array | None = None,
  own_view: jax.Array | None = None,
) -> Gaussians:
  """Gaussians of a time-conditioned model at several times, from one encoding.

  The decoder is vmapped over the times; the encoder's keys/values are closed over, so they are
  computed once and shared by every decode.

  Args:
    params: network parameters.
    encoded: `model.encode(...)` of the context views (or `model.kv_from_latents(...)`).
    model_config: `model.ModelConfig` with `time_embedding`.
    times: [B, T] normalised times to decode at.
    tokens: [B, num_tokens, C] Gaussian tokens replacing the learnt ones (token tuning); None
      uses the learnt tokens.
    viewer_c2w: [B, T, 4, 4] the camera each time's set is rendered from, or with T = 1
      [B, Vr, 4, 4]: one decode seen from Vr cameras; used where the colours depend on the
      camera (`model_config.viewer_dependent`), ignored otherwise.
    own_view: [T] (or [Vr]) bool, per camera of `viewer_c2w`, as `decode`'s.

  Returns:
    `Gaussians` with batch shape [B, T] (static Gaussians first, identical at every time); [B, Vr]
    for one time seen from Vr cameras with viewer-dependent colours.
  """
  if not model_config.viewer_dependent:
    viewer_c2w = None
  elif times.shape[1] == 1:
    return Gaussians.from_flat(
      decode(params, encoded, model_config, tokens, times[:, 0], viewer_c2w, own_view=own_view)
    )

  def decode_one(time, c2w, own):  # time: [B]; c2w: [B, 4, 4] or None; own: [] bool or None
    if c2w is None:
      return decode(params, encoded, model_config, tokens=tokens, times=time)
    own = None if own is None else own[None]
    return decode(params, encoded, model_config, tokens, time, c2w[:, None], own_view=own)[:, 0]

  in_axes = (1, None if viewer_c2w is None else 1, None if own_view is None else 0)
  decoded = jax.vmap(decode_one, in_axes, out_axes=1)(times, viewer_c2w, own_view)
  return Gaussians.from_flat(decoded)


def predict_gaussians(
  params: Params,
  images: jax.Array,
  plucker: jax.Array,
  config: ModelConfig,
  times: jax.Array | None = None,
  target_times: jax.Array | None = None,
) -> jax.Array:
  """The network alone: normalised images [B, V, H, W, 3] + Plücker [B, V, H, W, 6] -> [B, N, 14].

  N = config.num_gaussians whatever V, H and W are. `times` [B, V] and `target_times` [B] are for
  time-embedding models.
  """
  return TokenGS(config).apply({"params": params}, images, plucker, times, target_times)


def encode_views(
  params: Params,
  images: jax.Array,
  c2w: jax.Array,
  intrinsics: jax.Array,
  config: ModelConfig,
  times: jax.Array | None = None,
) -> EncoderOutput:
  """Images in [0, 1] and cameras -> encoder output (normalisation + Plücker rays + encoder).

  The one prelude every caller that starts from views uses (`reconstruct`, training, tuning).
  Inputs are checked at trace time (`model.inputs.check_views`: ValueError for shapes,
  TypeError for dtypes) and, where concrete, for NaN / inf values and fx, fy <= 0 (ValueError
  naming the view).

  Args:
    params: the params pytree.
    images: [B, V, H, W, 3] RGB, float in [0, 1] or uint8; H, W divisible by the patch size.
    c2w: [B, V, 4, 4] camera-to-world (OpenCV), already normalised as the data pipeline does.
    intrinsics: [B, V, 4] fx, fy, cx, cy in pixels.
    config: the architecture.
    times: [B, V] normalised input-view times (time-embedding models only; required there).

  Returns:
    EncoderOutput (keys/values [B, heads, V * H * W / p², head_dim]; latents if any; the views
    if the model reads its colours from them).
  """
  check_views(images, c2w, intrinsics, config, times)
  height, width = images.shape[-3:-1]
  plucker = plucker_rays(c2w, intrinsics, height, width)
  encoded = encode(params, normalize_images(images), plucker, config, times)
  if config.gaussian_colours == "inputs":
    rgb = jnp.asarray(images, jnp.float32)
    if jnp.result_type(images) == jnp.uint8:
      rgb = rgb / 255.0
    encoded = encoded.replace(views=InputViews(rgb, invert_rigid(c2w), intrinsics, times))
  return encoded


def reconstruct(
  params: Params,
  images: jax.Array,
  c2w: jax.Array,
  intrinsics: jax.Array,
  *,
  config: ModelConfig,
  times: jax.Array | None = None,
  target_times: jax.Array | None = None,
  viewer_c2w: jax.Array | None = None,
  static_scene: bool = False,
  own_view: jax.Array | None = None,
) -> Gaussians:
  """Images in [0, 1] and cameras -> Gaussians (`encode_views` + `decode`).

  Args:
    params: the params pytree.
    images: [B, V, H, W, 3] RGB, float in [0, 1] or uint8.
    c2w: [B, V, 4, 4] camera-to-world (OpenCV), already normalised as the data pipeline does.
    intrinsics: [B, V, 4] fx, fy, cx, cy in pixels.
    config: the architecture (static).
    times: [B, V] normalised context times (dynamic models).
    target_times: [B] normalised time at which to decode the dynamic Gaussians.
    viewer_c2w: [B, Vr, 4, 4] the cameras they will be rendered from (`decode`): batch shape
      [B, Vr], one set per camera, each coloured for its camera where `config.viewer_dependent`.
    static_scene: (static) skip the dynamic branch of a dynamic model (`decode`): the static
      Gaussians alone, `config.num_static_gaussians` per scene.
    own_view: [Vr] bool, per camera of `viewer_c2w` (`decode`).

  Returns:
    `tokengs_jax.gaussians.Gaussians` with N = config.num_gaussians Gaussians per scene
    (`config.num_static_gaussians` for a `static_scene`).

  Raises:
    ValueError / TypeError: at trace time, for inputs of the wrong shape / dtype; outside jit
      (concrete inputs), ValueError naming the view of a NaN / inf image, c2w or intrinsics, or
      of fx, fy <= 0 (`model.inputs.check_views`).
  """
  encoded = encode_views(params, images, c2w, intrinsics, config, times)
  if target_times is not None:
    check_times("target_times", target_times, images.shape[:1], "[B]")
  return Gaussians.from_flat(
    decode(
      params,
      encoded,
      config,
      times=target_times,
      viewer_c2w=viewer_c2w,
      static_scene=static_scene,
      own_view=own_view,
    )
  )
