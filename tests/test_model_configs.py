"""Model configs (`tokengs_jax.model.configs`): options of official checkpoints, the decoder's
LayerScale rule, and the presets (parameter counts written out from the official modules, values,
the tiny preset at its resolution)."""

import functools

import jax
import numpy as np
import pytest
from scenes import MICRO, official_fixture, random_inputs

from tokengs_jax.model import (
  ModelConfig,
  config_from_official,
  count_params,
  init_params,
  param_shapes,
  preset,
  reconstruct,
)
from tokengs_jax.model.official import official_name


def test_config_from_official_options():
  config, _, _ = official_fixture()
  assert (config.enc_depth, config.dec_depth, config.enc_embed_dim, config.enc_num_heads) == (
    2,
    2,
    32,
    2,
  )
  assert config.dec_patch_size == config.patch_size == 8  # dec_patch_size defaults to patch
  assert config.image_size == (16, 24) and config.num_gaussians == 4 * 64
  assert config_from_official({"patch_size": 4, "dec_patch_size": None}).dec_patch_size == 4
  latent = config_from_official(
    {
      "use_latent_bottleneck": True,
      "clip_head_z_init": 0.1,
      "multiscale_encoder_layers": [5, 7, 9, 11],
    }
  )
  assert latent.use_latent_bottleneck and latent.multiscale_encoder_layers == (5, 7, 9, 11)
  with pytest.raises(ValueError, match="token_dim"):
    config_from_official({"enc_embed_dim": 64, "token_dim": 32, "enc_num_heads": 2})


def test_decoder_layer_scale_rule():
  assert MICRO.decoder_layer_scale == pytest.approx(5e-3 * 0.01)  # official default rule
  assert MICRO.replace(dec_init_values=0.01).decoder_layer_scale == 0.01
  no_scale = MICRO.replace(gs_token_std=0.0)  # official: Identity instead of LayerScale
  names = {
    official_name(tuple(k.key for k in path))
    for path, _ in jax.tree_util.tree_leaves_with_path(param_shapes(no_scale))
  }
  assert not any("gs_cross_attn_scale" in n for n in names)


# ----- presets ------------------------------------------------------------------------------------


def expected_param_count(c: ModelConfig) -> int:
  """Parameter count written out from the official module definitions."""
  width, head, hidden = c.enc_embed_dim, c.head_dim, c.mlp_hidden_dim

  def linear(i, o):
    return i * o + o

  norm = lambda n: 2 * n
  attention = linear(width, 3 * width) + 2 * norm(head) + linear(width, width)
  mlp = linear(width, hidden) + linear(hidden, width)
  encoder_block = 2 * norm(width) + attention + mlp + 2 * width

  def decoder_block(layer_scale):
    cross = norm(width) + 2 * linear(width, width) + norm(head)
    return cross + norm(width) + attention + norm(width) + mlp + (3 * width if layer_scale else 0)

  p = c.patch_size
  total = linear(3 * p * p, width) + linear(6 * p * p, width) + 2 * norm(width)
  if c.time_embedding:
    total += 2 * linear(c.time_embedding_dim * p * p, width)
  total += c.enc_depth * encoder_block
  total += (len(c.multiscale_encoder_layers) if c.use_multiscale_encoder else 1) * norm(width)
  if c.use_latent_bottleneck:
    total += linear(c.encoder_feature_dim, 2 * width) + norm(head) + c.num_latents * width
    total += c.latent_cross_attn_depth * decoder_block(True) + linear(width, 2 * width)
  else:
    total += linear(c.encoder_feature_dim, 2 * width)
  total += norm(head)  # k_proj_norm
  total += c.dec_depth * decoder_block(c.decoder_layer_scale)
  total += linear(width, 14 * c.dec_patch_size**2) + c.num_tokens * width
  return total


@pytest.mark.parametrize(
  "name", ["tiny", "re10k", "dl3dv_4view", "dl3dv_latent_6view", "kubric_dyn"]
)
def test_preset_parameter_counts(name):
  config = preset(name)
  count = count_params(config)  # jax.eval_shape: nothing is allocated
  assert count == expected_param_count(config)
  print(f"{name}: {count / 1e6:.2f} M parameters")


def test_preset_values():
  re10k = preset("re10k")
  assert (re10k.enc_depth, re10k.dec_depth, re10k.enc_embed_dim, re10k.num_gs_tokens) == (
    6,
    24,
    1024,
    1024,
  )
  assert preset("re10k_4096").num_gaussians == 4096 * 64
  dl3dv = preset("dl3dv_6view")
  assert (dl3dv.enc_depth, dl3dv.dec_depth, dl3dv.image_size, dl3dv.num_input_views) == (
    3,
    12,
    (256, 448),
    6,
  )
  latent = preset("dl3dv_latent_2view")
  assert latent.use_latent_bottleneck and latent.gaussian_z_offset == 0.0
  assert latent.multiscale_encoder_layers == (5, 7, 9, 11) and latent.decoder_layer_scale == 0.01
  kubric = preset("kubric_dyn")
  assert kubric.num_dynamic_gs_tokens == 256 and kubric.time_embedding
  assert preset("tiny", dtype="bfloat16").dtype == "bfloat16"
  with pytest.raises(KeyError, match="unknown preset"):
    preset("nope")


@pytest.mark.slow
def test_tiny_preset_runs_at_its_resolution():
  config = preset("tiny")
  params = init_params(jax.random.key(0), config)
  images, c2w, intrinsics = random_inputs(
    jax.random.key(1), 1, config.num_input_views, *config.image_size
  )
  gaussians = jax.jit(functools.partial(reconstruct, config=config))(
    params, images, c2w, intrinsics
  )
  assert gaussians.means.shape == (1, config.num_gaussians, 3)
  # at initialisation the Gaussians sit in front of the first camera (z-offset 1)
  np.testing.assert_allclose(np.asarray(gaussians.means[..., 2]).mean(), 1.0, atol=0.1)
