"""Growing a pretrained model for finetuning: more tokens, dynamic from static, more Gaussians.

As the official finetuning initialisation (`init_tokens_from_existing`, and the same rule for the
scene latents, `init_latents_from_existing`): the first rows of a larger table are the pretrained
tokens, the extra rows are pretrained tokens taken cyclically plus N(0, noise_std^2) noise; a
smaller table takes evenly spaced rows. Dynamic tokens start as cyclic copies of the static
tokens without noise (a random subset when fewer).

Not in the official code: a head that decodes r times more Gaussians per token (a larger
`dec_patch_size`) starts with each pretrained Gaussian split into r children: the parent's
readout columns plus noise, so the children begin where the parent was and part under training.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from tokengs_jax.model.head import RAW_CHANNELS
from tokengs_jax.train.optim import path_name


def expand_tokens(
  key: jax.Array, tokens: jax.Array, num_tokens: int, noise_std: float = 0.01
) -> jax.Array:
  """A `[num_tokens, D]` table initialised from pretrained `tokens [N, D]`.

  Args:
    key: PRNG key for the noise on the extra rows.
    tokens: `[N, D]` pretrained table.
    num_tokens: rows of the new table.
    noise_std: std of the Gaussian noise added to the copied extra rows.

  Returns:
    `[num_tokens, D]`: `tokens` then noisy cyclic copies (or `num_tokens` evenly spaced rows).
  """
  count = tokens.shape[0]
  if num_tokens <= count:
    # torch.linspace(0, N - 1, M).long() truncates toward zero
    return tokens[np.linspace(0, count - 1, num_tokens).astype(np.int64)]
  extra = jnp.tile(tokens, (-(-(num_tokens - count) // count), 1))[: num_tokens - count]
  extra = extra + noise_std * jax.random.normal(key, extra.shape, tokens.dtype)
  return jnp.concatenate([tokens, extra], axis=0)


def dynamic_tokens_from_static(
  key: jax.Array, static_tokens: jax.Array, num_dynamic: int
) -> jax.Array:
  """`[num_dynamic, D]` dynamic tokens: cyclic copies of `static_tokens [N, D]` (no noise), or a
  random subset when fewer."""
  count = static_tokens.shape[0]
  if num_dynamic > count:
    return jnp.tile(static_tokens, (-(-num_dynamic // count), 1))[:num_dynamic]
  if num_dynamic == count:
    return static_tokens
  return static_tokens[jax.random.permutation(key, count)[:num_dynamic]]


HEAD_NAMES = ("activation_head/deconv/kernel", "activation_head/deconv/bias")


def split_gaussians(
  key: jax.Array, readout: jax.Array, channels: int, count: int, noise_std: float = 0.01
) -> jax.Array:
  """A head readout for `count` Gaussians per token from one for fewer: each parent split evenly.

  Args:
    key: PRNG key for the noise.
    readout: `[..., G * channels]` pretrained kernel `[C, G * channels]` or bias `[G * channels]`,
      Gaussian `k`'s channels at columns `k * channels ... (k + 1) * channels - 1`.
    channels: raw channels per Gaussian (14).
    count: Gaussians per token of the new head, a multiple of `G`.
    noise_std: noise std relative to the readout's own std, on the children's kernel columns
      (none on a bias): identical children would receive identical gradients forever.

  Returns:
    `[..., count * channels]`: new Gaussian `n` is a copy of parent `n // (count // G)`.
  """
  parents = readout.shape[-1] // channels
  if count % parents:
    raise ValueError(f"cannot split {parents} Gaussians per token into {count}")
  blocks = readout.reshape(*readout.shape[:-1], parents, channels)
  children = jnp.repeat(blocks, count // parents, axis=-2).reshape(*readout.shape[:-1], -1)
  if readout.ndim == 1:
    return children
  scale = noise_std * jnp.std(readout)
  return children + scale * jax.random.normal(key, children.shape, readout.dtype)


def transplant_params(
  key: jax.Array,
  pretrained,
  fresh,
  token_names: tuple[str, ...] = ("gs_tokens", "latents"),
  noise_std: float = 0.01,
  dynamic_from_static: bool = True,
):
  """Loads `pretrained` into the structure of `fresh`, growing token tables (tolerant load).

  Leaves present in both with equal shapes are copied; a leaf whose path has a component starting
  with one of `token_names` (the Gaussian tokens, static and dynamic, and the scene latents) and
  whose row count differs is resized with `expand_tokens`; the Gaussian head's readout, when the
  model decodes a multiple of the pretrained Gaussians per token, with `split_gaussians`; anything
  else keeps its fresh initialisation and is reported. With `dynamic_from_static`, a
  `gs_tokens_dynamic` table that the pretrained (static) model lacks starts from its `gs_tokens`
  (`dynamic_tokens_from_static`), as the official `init_dynamic_tokens_from_static`. `pretrained` may be partial, e.g. an official
  checkpoint read with `load_official_checkpoint(..., strict=False)`.

  Returns:
    `(params, report)` with `report` a list of "path: action" strings for the non-copied leaves.
  """
  flat_pre = {path_name(p): v for p, v in jax.tree_util.tree_leaves_with_path(pretrained)}
  report = []

  def pick(path, leaf):
    name = path_name(path)
    old = flat_pre.get(name)
    if (
      old is None
      and dynamic_from_static
      and name == "gs_tokens_dynamic"
      and (flat_pre.get("gs_tokens") is not None)
    ):
      report.append(f"{name}: from static gs_tokens")
      return dynamic_tokens_from_static(
        jax.random.fold_in(key, len(report)),
        jnp.asarray(flat_pre["gs_tokens"], leaf.dtype),
        leaf.shape[0],
      )
    if old is not None and old.shape == leaf.shape:
      return jnp.asarray(old, leaf.dtype)
    is_token = any(part.startswith(token_names) for part in name.split("/"))
    if (
      old is not None and is_token and old.ndim == 2 == leaf.ndim and old.shape[1] == leaf.shape[1]
    ):
      report.append(f"{name}: tokens {old.shape[0]} -> {leaf.shape[0]}")
      return expand_tokens(
        jax.random.fold_in(key, len(report)), jnp.asarray(old, leaf.dtype), leaf.shape[0], noise_std
      )
    if old is not None and name.endswith(HEAD_NAMES) and old.shape[:-1] == leaf.shape[:-1]:
      parents, count = old.shape[-1] // RAW_CHANNELS, leaf.shape[-1] // RAW_CHANNELS
      if count % parents == 0:
        report.append(f"{name}: Gaussians per token {parents} -> {count} (split)")
        return split_gaussians(
          jax.random.fold_in(key, len(report)),
          jnp.asarray(old, leaf.dtype),
          RAW_CHANNELS,
          count,
          noise_std,
        )
    report.append(f"{name}: kept fresh ({'missing' if old is None else f'shape {old.shape}'})")
    return leaf

  return jax.tree_util.tree_map_with_path(pick, fresh), report
