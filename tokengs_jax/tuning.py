"""Test-time scaling: token tuning, scene-latent tuning, Gaussian tuning, joint tuning.

All variants minimise the training loss (`objective.supervision_loss`: RGB + SSIM +
visibility, and LPIPS where the loss weighs it, as the official test-time training's
`compute_loss`) of renders of the *input* views, with Adam, as one jitted `lax.scan` over the steps.
The encoder runs once: its keys/values (or scene latents) are computed before the loop and held
fixed, and the network parameters are never updated (they are closed over, not optimised).

- "tokens": the Gaussian tokens [B, T, C] (official `forward_ttt_tokens`: Adam, 50 steps, lr 1e-4
  in the paper; torch Adam betas (0.9, 0.999)); the decoder is re-run each step.
- "latents": the scene latents [B, L, C] of a latent-bottleneck model (keys/values recomputed
  from them each step, then the decoder).
- "gaussians": the paper's baseline, the Gaussian parameters themselves, as additive offsets in
  an unconstrained parameterisation (logit opacity, log scale, logit colour; means and
  quaternions as they are) so they stay valid.
- "tokens+gaussians": both at once (the paper leaves joint tuning open): tokens as above plus
  Gaussian offsets on top of the decoded Gaussians, each with its own learning rate.

Dynamic (time-conditioned) models: pass the input views' `times`; each input view is then
rendered from the Gaussians decoded at its time (`objective.time_conditioned_loss`), and
the result is decoded at `output_times` (evaluation: the target views' times). The official
`to_ttt()` drops the target time, so its tuning and its tuned output are time-free; that is what
`times=None` gives here.

Context extension needs nothing here: pass more input views than the model was trained with; the
Gaussian count stays `config.num_gaussians`.

Scoring (feed-forward or tuned) is `tokengs_jax.evaluation` (`feed_forward`, `tuned`, `evaluate`).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import typing
from typing import Literal

import jax
import jax.numpy as jnp
import optax

from tokengs_jax import losses, model, splatting
from tokengs_jax.camera import invert_rigid
from tokengs_jax.gaussians import Gaussians
from tokengs_jax.model.inputs import check_times
from tokengs_jax.objective import (
  ObjectiveConfig,
  check_cross_view,
  cross_view_flags,
  supervision_loss,
  time_conditioned_loss,
)

Target = Literal["tokens", "latents", "gaussians", "tokens+gaussians"]
Schedule = Literal["constant", "cosine"]


@dataclasses.dataclass(frozen=True)
class TuningConfig:
  """Test-time tuning settings.

  Attributes:
    target: what is optimised (see the module docstring).
    steps: Adam steps.
    learning_rate: for tokens / latents (paper: 1e-4).
    gaussian_learning_rate: for Gaussian offsets ("gaussians", "tokens+gaussians").
    schedule: "constant" (the official tuning's) or "cosine": each rate decays to 0 over the
      steps (a deviation, so that a high rate's early gain is not spent in oscillation later).
    b1, b2: Adam moments (torch defaults, as the official tuning).
  """

  target: Target = "tokens"
  steps: int = 50
  learning_rate: float = 1e-4
  gaussian_learning_rate: float = 1e-3
  schedule: Schedule = "constant"
  b1: float = 0.9
  b2: float = 0.999


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TuningResult:
  """Tuned Gaussians and the input-view loss before each step.

  Attributes:
    gaussians: Gaussians [B, N] after the last step.
    losses: [steps + 1] input-view loss before each step, then after the last one.
  """

  gaussians: Gaussians
  losses: jax.Array


def _unconstrained(g: Gaussians) -> Gaussians:
  """Gaussians -> unconstrained coordinates (inverse of `_constrained`)."""

  def logit(x):
    return jax.scipy.special.logit(jnp.clip(x, 1e-6, 1 - 1e-6))

  return Gaussians(
    means=g.means,
    opacities=logit(g.opacities),
    scales=jnp.log(jnp.maximum(g.scales, 1e-12)),
    quats=g.quats,
    colors=logit(g.colors),
  )


def _constrained(u: Gaussians) -> Gaussians:
  """Unconstrained coordinates -> valid Gaussians."""
  return Gaussians(
    means=u.means,
    opacities=jax.nn.sigmoid(u.opacities),
    scales=jnp.exp(u.scales),
    quats=u.quats,
    colors=jax.nn.sigmoid(u.colors),
  )


def _offset(gaussians: Gaussians, offsets: Gaussians) -> Gaussians:
  """Applies additive offsets in unconstrained coordinates (zero offsets: `gaussians` itself)."""
  return _constrained(jax.tree.map(jnp.add, _unconstrained(gaussians), offsets))


def tune(
  params,
  images: jax.Array,
  c2w: jax.Array,
  intrinsics: jax.Array,
  *,
  model_config,
  tuning: TuningConfig = TuningConfig(),
  loss_config=None,
  render_config=None,
  objective: ObjectiveConfig | None = None,
  times: jax.Array | None = None,
  output_times: jax.Array | None = None,
  output_c2w: jax.Array | None = None,
  lpips_params=None,
) -> TuningResult:
  """Reconstructs a scene from its input views and tunes it on them.

  Time-conditioned models with `times`: the input views are encoded with their times, and the
  tuning loss renders every input view from the Gaussians decoded at that view's time
  (`objective.time_conditioned_loss`, with the dynamic auxiliary term at its base weight
  when `loss_config.lambda_dyn_aux > 0`); tokens / latents are shared by all times, Gaussian
  offsets are time-independent (added to the Gaussians of every time). Without `times` a
  time-conditioned model decodes time-free (no target-time embedding).

  Never computed from a truncated render: while any render of the run overflowed its tile
  budget (`stats.overflow`), the run is repeated with a budget that holds the most pairs one
  needed (`splatting.larger_budget(..., needed=)`). Call it outside jit.

  Args:
    params: network parameters (read only).
    images: [B, V, H, W, 3] input views in [0, 1] (any V: context extension).
    c2w: [B, V, 4, 4] normalised camera-to-world; intrinsics: [B, V, 4] in pixels.
    model_config: `model.ModelConfig`; tuning: what to tune, steps, learning rates.
    loss_config: `losses.LossConfig` (default: the training loss); lpips_params: the VGG weights
      (`tokengs_jax.lpips.load_vgg_params()`) when its `lambda_lpips` > 0.
    render_config: `splatting.RenderConfig`.
    objective: the input-view renders' chunking, background ("input_mean": of `images`),
      near/far, `cross_view_renders` (default `ObjectiveConfig()`; `decode_times` ignored).
    times: [B, V] normalised input-view times (time-conditioned models).
    output_times: [B, T] times of the returned Gaussians (default `times`).
    output_c2w: [B, T, 4, 4] the cameras the result is rendered from: a set per camera where
      colours depend on the viewer (each input view then tunes with its own colours).

  Returns:
    `TuningResult` (0 steps: the feed-forward one); Gaussians [B] or [B, T] (per time / camera).
  """
  render_config = splatting.RenderConfig() if render_config is None else render_config
  while True:
    result, overflowed, pairs_needed = _tune_once(
      params,
      images,
      c2w,
      intrinsics,
      model_config=model_config,
      tuning=tuning,
      loss_config=loss_config,
      render_config=render_config,
      objective=objective,
      times=times,
      output_times=output_times,
      output_c2w=output_c2w,
      lpips_params=lpips_params,
    )
    if isinstance(overflowed, jax.core.Tracer):
      raise TypeError("tune redoes overflowing renders on the host: call it outside jit/vmap/grad")
    if not bool(overflowed):
      return result
    render_config = splatting.larger_budget(
      render_config,
      result.gaussians.num_gaussians,
      images.shape[-3],
      images.shape[-2],
      needed=int(pairs_needed),
    )
    logging.info(
      "tune: a render overflowed its tile budget; tuning again with max_intersections=%d",
      render_config.max_intersections,
    )


@functools.partial(
  jax.jit, static_argnames=("model_config", "tuning", "loss_config", "render_config", "objective")
)
def _tune_once(
  params,
  images: jax.Array,
  c2w: jax.Array,
  intrinsics: jax.Array,
  *,
  model_config,
  tuning: TuningConfig = TuningConfig(),
  loss_config=None,
  render_config=None,
  objective: ObjectiveConfig | None = None,
  times: jax.Array | None = None,
  output_times: jax.Array | None = None,
  output_c2w: jax.Array | None = None,
  lpips_params=None,
) -> tuple[TuningResult, jax.Array, jax.Array]:
  """`tune` at one render budget; also returns whether any of its renders overflowed ([] bool)
  and the most (Gaussian, tile) pairs one of their views needed ([] float32)."""
  loss_config = losses.LossConfig() if loss_config is None else loss_config
  objective = ObjectiveConfig() if objective is None else objective
  timed = times is not None
  _check_times(model_config, images.shape[0], times, output_times, objective)
  # The encoder runs once; stop_gradient keeps the loop from differentiating into it.
  encoded = jax.lax.stop_gradient(
    model.encode_views(params, images, c2w, intrinsics, model_config, times=times)
  )
  decode = functools.partial(_decode, params, encoded, model_config)
  variables, learning_rates, feed_forward = _initial_variables(
    params, encoded, decode, model_config, tuning, images.shape[0]
  )
  gaussians_of = functools.partial(_gaussians_of, decode, feed_forward)

  def loss_and_budget(v):
    """Input-view loss of the variables `v`, and (whether its render overflowed, the pairs its
    views needed)."""
    loss, terms = _input_view_loss(
      functools.partial(gaussians_of, v),
      images,
      c2w,
      intrinsics,
      times,
      model_config=model_config,
      loss_config=loss_config,
      render_config=render_config,
      objective=objective,
      lpips_params=lpips_params,
    )
    return loss, (terms["render_overflow"] > 0, terms["render_pairs_needed"])

  variables, step_losses, (step_overflows, step_needs) = _adam_scan(
    loss_and_budget, variables, learning_rates, tuning
  )
  final_loss, (final_overflow, final_need) = loss_and_budget(variables)
  if timed:
    at_times = times if output_times is None else output_times
    gaussians = gaussians_of(variables, at_times, output_c2w)
  else:
    gaussians = gaussians_of(variables, viewer_c2w=output_c2w)
  return (
    TuningResult(gaussians=gaussians, losses=jnp.append(step_losses, final_loss)),
    jnp.any(step_overflows) | final_overflow,
    jnp.maximum(jnp.max(step_needs, initial=0.0), final_need),
  )


def _input_view_loss(
  gaussians_of,
  images,
  c2w,
  intrinsics,
  times,
  *,
  model_config,
  loss_config,
  render_config,
  objective,
  lpips_params,
):
  """Tuning's loss on the input views [B, V]; `(loss, terms)`.

  Time-conditioned models (`times` [B, V]) render each view from the Gaussians at its own time;
  time-free ones render each view once, and again coloured by the other views only under
  `objective.cross_view_renders`.

  gaussians_of: `(at_times=[B, T] or None, viewer_c2w=[B, T, 4, 4] or None, own_view=[T] or
  None) -> Gaussians [B, T]` of the tuned variables (`_gaussians_of`).
  """
  if times is not None:
    # the dynamic auxiliary term as official TTT: the loss of a fresh model, i.e. its base weight
    with_aux = model_config.num_dynamic_gs_tokens > 0 and model_config.num_gs_tokens > 0
    return time_conditioned_loss(
      lambda t, w2c: gaussians_of(t, invert_rigid(w2c)),
      times,
      images,
      invert_rigid(c2w),
      intrinsics,
      loss_config,
      render_config,
      dataclasses.replace(objective, decode_times="per_view"),
      lpips_params,
      num_static_gaussians=model_config.num_static_gaussians if with_aux else None,
      context_images=images,
    )
  views = (images, invert_rigid(c2w), intrinsics, c2w)
  if objective.cross_view_renders:
    views = tuple(jnp.concatenate([x, x], axis=1) for x in views)
  scored, world_to_camera, scored_intrinsics, viewers = views
  own_view = cross_view_flags(objective, model_config, viewers.shape[1], images.shape[1])
  return supervision_loss(
    gaussians_of(viewer_c2w=viewers, own_view=own_view),
    scored,
    world_to_camera,
    scored_intrinsics,
    loss_config,
    render_config,
    objective,
    context_images=images,
    lpips_params=lpips_params,
  )


def _check_times(model_config, batch: int, times, output_times, objective) -> None:
  """Trace-time checks of the input-view `times` [B, V] and `output_times` [B, T] (and of an
  `objective` whose cross-view renders are for views without times)."""
  if times is not None and not model_config.time_embedding:
    raise ValueError("times given for a model without time embedding")
  if times is not None and objective.cross_view_renders:
    check_cross_view(model_config)
  if output_times is not None:
    if times is None:
      raise ValueError("output_times needs the input-view times")
    check_times("output_times", output_times, (batch, None), "[B, T]")


def _decode(
  params,
  encoded,
  model_config,
  tokens=None,
  latents=None,
  at_times=None,
  viewer_c2w=None,
  own_view=None,
) -> Gaussians:
  """Gaussians [B] (time-free), or [B, T] at `at_times` [B, T], of the fixed encoding; with
  `viewer_c2w` [B, T, 4, 4] and colours that depend on the viewer, one set per camera [B, T]
  (`own_view` [T] bool: `model.decode`'s).

  tokens: [B, T_tok, C] replacing the learnt Gaussian tokens; latents: [B, L, C] scene latents
  replacing the encoded ones (their keys/values are recomputed).
  """
  if latents is None:
    source = encoded
  else:
    source = model.kv_from_latents(params, latents, model_config).replace(views=encoded.views)
  if at_times is not None:
    return model.decode_at_times(
      params, source, model_config, at_times, tokens, viewer_c2w, own_view
    )
  if not model_config.viewer_dependent:
    viewer_c2w = own_view = None
  return Gaussians.from_flat(
    model.decode(params, source, model_config, tokens, None, viewer_c2w, own_view=own_view)
  )


def _initial_variables(params, encoded, decode, model_config, tuning: TuningConfig, batch: int):
  """What `tuning.target` optimises, at its feed-forward value.

  Returns `(variables, learning_rates, feed_forward)`: variables is a dict with "tokens"
  [B, T_tok, C] (float32), "latents" [B, L, C] and/or "offsets" (zero Gaussian offsets [B, N]);
  learning_rates has the same keys; feed_forward is the Gaussians [B] under the offsets (None
  without offsets).
  """
  target = tuning.target
  variables, learning_rates, feed_forward = {}, {}, None
  if target in ("tokens", "tokens+gaussians"):
    variables["tokens"] = model.initial_tokens(params, model_config, batch).astype(jnp.float32)
    learning_rates["tokens"] = tuning.learning_rate
  if target == "latents":
    if encoded.latents is None:
      raise ValueError("latent tuning needs a latent-bottleneck model (use_latent_bottleneck)")
    variables["latents"] = encoded.latents
    learning_rates["latents"] = tuning.learning_rate
  if target in ("gaussians", "tokens+gaussians"):
    feed_forward = jax.lax.stop_gradient(decode())
    # one offset per Gaussian, shared by every time
    variables["offsets"] = jax.tree.map(jnp.zeros_like, feed_forward)
    learning_rates["offsets"] = tuning.gaussian_learning_rate
  if not variables:
    raise ValueError(f"unknown tuning target {target!r}")
  return variables, learning_rates, feed_forward


def _gaussians_of(
  decode, feed_forward, v: dict, at_times=None, viewer_c2w=None, own_view=None
) -> Gaussians:
  """The Gaussians of the tuned variables `v`: [B], or [B, T] at `at_times` [B, T] or seen from
  `viewer_c2w` [B, T, 4, 4] (`own_view` [T]: `_decode`)."""
  seen_by = {"at_times": at_times, "viewer_c2w": viewer_c2w, "own_view": own_view}
  if "offsets" not in v:
    return decode(tokens=v.get("tokens"), latents=v.get("latents"), **seen_by)
  if "tokens" in v:
    base = decode(tokens=v["tokens"], **seen_by)
  elif at_times is None and viewer_c2w is None:
    base = feed_forward
  else:  # the feed-forward Gaussians at these times / for these cameras (forward only)
    base = jax.lax.stop_gradient(decode(**seen_by))
  offsets = v["offsets"]
  if len(base.batch_shape) == 2:  # one offset per Gaussian, shared by every time and camera
    offsets = jax.tree.map(lambda x: x[:, None], offsets)
  return _offset(base, offsets)


def _adam_scan(loss_and_aux, variables: dict, learning_rates: dict, tuning: TuningConfig):
  """`tuning.steps` Adam steps on `variables` (one learning rate per entry) as one `lax.scan`.

  loss_and_aux: `variables -> ([] loss, aux pytree)`.
  Returns `(variables after the last step, losses [steps] and aux [steps, ...] before each)`.
  """

  if tuning.schedule not in typing.get_args(Schedule):
    raise ValueError(f"unknown tuning schedule {tuning.schedule!r}")

  def schedule(rate):
    if tuning.schedule == "cosine" and tuning.steps > 0:  # optax needs a positive decay length
      return optax.cosine_decay_schedule(rate, tuning.steps)
    return rate

  optimizer = optax.multi_transform(
    {
      name: optax.adam(schedule(rate), b1=tuning.b1, b2=tuning.b2)
      for name, rate in learning_rates.items()
    },
    {name: name for name in variables},
  )

  def step(carry, _):
    v, opt_state = carry
    (loss, aux), grads = jax.value_and_grad(loss_and_aux, has_aux=True)(v)
    updates, opt_state = optimizer.update(grads, opt_state, v)
    return (optax.apply_updates(v, updates), opt_state), (loss, aux)

  (variables, _), (step_losses, step_aux) = jax.lax.scan(
    step, (variables, optimizer.init(variables)), None, length=tuning.steps
  )
  return variables, step_losses, step_aux
