"""The scene-flow term (not in the paper or the official code; docs/deviations.md).

Where the data knows how every surface moves (Kubric: depth maps, segmentations and per-frame
object poses; `data.targets.target_flows`), the dynamic Gaussians can be told. The photometric
loss alone did not make them follow 1-6-pixel objects (issue 24: their velocities stayed at a
fifth of the objects' or less); this term supervises the motion directly, as other dynamic
methods supervise 2D optical flow, in 3D.

The dynamic Gaussians' velocities are rendered as their colour into a target view, so a pixel
reads the velocity of the Gaussians it is drawn from, weighted as its colour would be, and is
compared with alpha x the velocity of the surface it sees, on the pixels that move only. Both
restrictions matter: a blob over a 2-pixel object covers mostly still background, so scored on
every pixel the absolute error's best velocity is the median of its pixels', 0 (measured: the
velocities went to 0); and the static Gaussians in front of an object would otherwise ask the
dynamic ones to overshoot.

A Gaussian's velocity is the difference quotient of its centre between the view's time and
`FLOW_TIME_STEP` later, in the example's frame per unit of normalised time: exact for
`dynamic_motion="linear"` (centres move linearly) and for static Gaussians (0).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from tokengs_jax.gaussians import Gaussians
from tokengs_jax.objective.settings import ObjectiveConfig

FLOW_TIME_STEP = 0.05


def velocities(gaussians: Gaussians, later_means: jax.Array) -> jax.Array:
  """[..., N, 3] velocity of Gaussians [..., N] whose centres are `later_means` [..., N, 3]
  `FLOW_TIME_STEP` later."""
  return (later_means - gaussians.means) / FLOW_TIME_STEP


def flow_loss(
  gaussians: Gaussians,
  velocity: jax.Array,
  flows: jax.Array,
  world_to_camera: jax.Array,
  intrinsics: jax.Array,
  render_config,
  objective: ObjectiveConfig,
) -> jax.Array:
  """Mean absolute error of the rendered velocity against alpha x the views' flows, over the
  pixels whose flow is not 0 (and their 3 components).

  Only the velocity learns from it: the Gaussians' geometry and opacity enter as constants, so
  the term cannot trade image quality for a lower flow error by moving or hiding Gaussians.

  Args:
    gaussians: Gaussians [B, Vc or 1, N] at the views' times (the dynamic ones).
    velocity: [B, Vc or 1, N, 3] their velocities (`velocities`).
    flows: [B, Vc, H, W, 3] the velocity each view's pixel sees (0: static).
    world_to_camera: [B, Vc, 4, 4]; intrinsics: [B, Vc, 4].
    render_config: `splatting.RenderConfig`; objective: its near / far culling.

  Returns:
    [] float32.
  """
  from tokengs_jax import splatting

  frozen = jax.tree.map(jax.lax.stop_gradient, gaussians)
  moving = Gaussians(
    means=frozen.means,
    opacities=frozen.opacities,
    scales=frozen.scales,
    quats=frozen.quats,
    colors=velocity.astype(jnp.float32),
  )
  rendered = splatting.render(
    moving,
    world_to_camera[:, :, None],
    intrinsics[:, :, None],
    height=flows.shape[-3],
    width=flows.shape[-2],
    config=dataclasses.replace(render_config, eps2d=objective.eps2d),
    near=objective.near,
    far=objective.far,
  )
  moves = jnp.any(flows != 0, axis=-1, keepdims=True)
  error = jnp.abs(rendered.rgb[:, :, 0] - rendered.alpha[:, :, 0] * flows) * moves
  return jnp.sum(error) / jnp.maximum(3.0 * jnp.sum(moves), 1.0)


def flow_term(
  gaussians_at, views: dict, shared, flows, num_static, loss_config, render_config, objective
):
  """(the time-conditioned loss's views, with "flows" [B, V, H, W, 3] when
  `loss_config.lambda_flow > 0`; `with_flow(loss, terms, gaussians, chunk_views) -> (loss,
  terms)`, which adds lambda_flow x the flow term "flow" of a view chunk's Gaussians
  [B, Vc or 1, N] from `num_static` on (None: all of them), or returns its arguments when the
  term is off).

  A Gaussian's velocity needs its centre `FLOW_TIME_STEP` after its view's time. Under
  `decode_times="first"` every view is rendered from one decode at the first view's time, so
  that is one more decode: shared with every chunk like the first ([B, 1]), or chunked with the
  views as "later" when it is one set per view ([B, V]). Otherwise each chunk decodes its own.
  """
  shared_later = None

  def with_flow(loss, terms: dict, gaussians: Gaussians, chunk: dict):
    if "flows" not in chunk:
      return loss, terms
    later = chunk.get("later", shared_later)
    if later is None:
      later = gaussians_at(chunk["times"] + FLOW_TIME_STEP, chunk["world_to_camera"]).means
    terms = dict(terms)
    if num_static is not None:
      gaussians, later = gaussians.static_and_dynamic(num_static)[1], later[..., num_static:, :]
    terms["flow"] = flow_loss(
      gaussians,
      velocities(gaussians, later.astype(jnp.float32)),
      chunk["flows"],
      chunk["world_to_camera"],
      chunk["intrinsics"],
      render_config,
      objective,
    )
    terms["loss"] = loss + loss_config.lambda_flow * terms["flow"]
    return terms["loss"], terms

  if flows is None or not loss_config.lambda_flow > 0:
    return views, with_flow
  views = {**views, "flows": flows.astype(jnp.float32)}
  if objective.decode_times == "first":
    first = views["times"][:, :1] + FLOW_TIME_STEP
    later = gaussians_at(first, views["world_to_camera"]).means
    if shared is not None:
      shared_later = later
    else:
      views["later"] = later
  return views, with_flow
