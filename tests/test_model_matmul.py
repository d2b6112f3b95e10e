"""The bf16-operand / float32-result matmul mode (`ModelConfig.matmul_dtype`, `model.matmul`)."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scenes import FULL, official_fixture

from tokengs_jax.model import (
  cast_matmul_kernels,
  init_params,
  param_shapes,
  predict_gaussians,
  preset,
)
from tokengs_jax.model.layers import attend
from tokengs_jax.model.matmul import dense_dot_general, matmul

BF16 = jnp.bfloat16
_TENSOR = r"tensor<(?:[^>]*x)?(\w+)>"  # captures the element type
_DOT = rf"stablehlo.dot_general .*?: \({_TENSOR}, {_TENSOR}\)"


def _rounded(x):
  return x.astype(BF16).astype(jnp.float32)


def test_matmul_forward_and_backward_are_the_rounded_operand_products():
  """Forward and both gradients equal float32 products of bf16-rounded operands and cotangent
  (what a bf16 x bf16 -> f32 dot computes), so the backward is a bf16 dot too, not autodiff
  through the casts (which would multiply float32 cotangents)."""
  kx, kw, kg = jax.random.split(jax.random.key(0), 3)
  x = jax.random.normal(kx, (2, 5, 48))
  kernel = jax.random.normal(kw, (48, 24))
  out_grad = jax.random.normal(kg, (2, 5, 24))
  out, vjp = jax.vjp(lambda a, b: matmul(a, b, BF16), x, kernel)
  x_grad, kernel_grad = vjp(out_grad)
  assert out.dtype == x_grad.dtype == kernel_grad.dtype == jnp.float32
  hi = jax.lax.Precision.HIGHEST
  np.testing.assert_allclose(out, jnp.matmul(_rounded(x), _rounded(kernel), precision=hi), 1e-5)
  expected_x = jnp.matmul(_rounded(out_grad), _rounded(kernel).T, precision=hi)
  np.testing.assert_allclose(x_grad, expected_x, 1e-5, 1e-5)
  expected_kernel = jnp.einsum("bni,bno->io", _rounded(x), _rounded(out_grad), precision=hi)
  np.testing.assert_allclose(kernel_grad, expected_kernel, 1e-5, 1e-5)
  # and all of it is within bf16 rounding of the float32 product
  np.testing.assert_allclose(out, x @ kernel, rtol=0, atol=0.2)
  assert not np.allclose(out, x @ kernel, rtol=0, atol=1e-4)  # it really rounds


def test_dense_dot_general_refuses_other_contractions():
  x, kernel = jnp.ones((4, 3)), jnp.ones((4, 5))
  with pytest.raises(NotImplementedError, match="contraction"):
    dense_dot_general(BF16)(x, kernel, (((0,), (0,)), ((), ())))


def test_attention_matmul_dtype_rounds_every_product_and_stays_close():
  kq, kk, kv, kg = jax.random.split(jax.random.key(1), 4)
  q, k, v = (jax.random.normal(key, (2, 2, 40, 16)) for key in (kq, kk, kv))
  out_grad = jax.random.normal(kg, q.shape)

  def run(matmul_dtype):
    out, vjp = jax.vjp(lambda *a: attend(*a, tile=256, matmul_dtype=matmul_dtype), q, k, v)
    return out, vjp(out_grad)

  exact, mixed = run(None), run(BF16)
  for a, b in zip(jax.tree.leaves(exact), jax.tree.leaves(mixed)):
    assert b.dtype == jnp.float32
    np.testing.assert_allclose(b, a, rtol=0, atol=0.05 * float(jnp.abs(a).max()))
  assert not np.allclose(mixed[0], exact[0], rtol=0, atol=1e-6)
  text = jax.jit(lambda *a: run(BF16)).lower(q, k, v).as_text()
  assert _dot_signatures(text) == {("bf16", "bf16", "f32")}


def _dot_signatures(stablehlo: str) -> set:
  """{(lhs, rhs, result) element types} of every dot_general of a lowered program."""
  return set(re.findall(_DOT + rf" -> {_TENSOR}", stablehlo))


def _official():
  config, params, io = official_fixture()
  return config, params, io["images_rgb"], io["plucker"], io["gaussians"]


def _loss_and_grads(params, images, plucker, config):
  def loss(p):
    return jnp.mean(jnp.square(predict_gaussians(p, images, plucker, config) - 0.5))

  return jax.jit(jax.value_and_grad(loss))(params)


def test_bf16_matmuls_stay_close_to_float32_on_official_weights():
  """On the official fixture (weights re-drawn at a visible scale): Gaussians within 4e-3 of the
  official float32 output (measured 2.0e-3; 4.8e-7 in float32), loss and gradients close."""
  config, params, images, plucker, official = _official()
  mixed = config.replace(matmul_dtype="bfloat16")
  assert param_shapes(mixed) == param_shapes(config)  # the same plain float32 params
  gaussians = jax.jit(predict_gaussians, static_argnums=3)(params, images, plucker, mixed)
  assert gaussians.dtype == jnp.float32
  error = float(np.abs(np.asarray(gaussians) - official).max())
  assert 1e-5 < error < 4e-3, error
  (loss, grads), (loss_mixed, grads_mixed) = (
    _loss_and_grads(params, images, plucker, c) for c in (config, mixed)
  )
  np.testing.assert_allclose(loss_mixed, loss, rtol=1e-4)  # measured 2.8e-6
  flat, flat_mixed = (
    jnp.concatenate([g.ravel() for g in jax.tree.leaves(t)]) for t in (grads, grads_mixed)
  )
  assert bool(jnp.isfinite(flat_mixed).all())
  relative = float(jnp.linalg.norm(flat_mixed - flat) / jnp.linalg.norm(flat))
  assert relative < 1e-2, relative  # measured 1.3e-3


def test_bf16_matmul_train_step_runs_only_bf16_dots_but_the_heads():
  """Every dot of the lowered value_and_grad is bf16 x bf16 -> f32 except the Gaussian head's
  (its forward and its two backward products); the float32 model has no bf16 at all."""
  config = preset(
    "tiny", enc_depth=1, dec_depth=1, enc_embed_dim=32, enc_num_heads=2, num_gs_tokens=4
  )
  images, plucker = jnp.zeros((1, 2, 16, 16, 3)), jnp.zeros((1, 2, 16, 16, 6))
  params = param_shapes(config)

  def program(c):
    def loss(p):
      return jnp.sum(predict_gaussians(p, images, plucker, c))

    return jax.jit(jax.value_and_grad(loss)).lower(params).as_text()

  mixed = program(config.replace(matmul_dtype="bfloat16"))
  signatures = re.findall(_DOT, mixed)
  assert signatures.count(("f32", "f32")) == 3
  assert signatures.count(("bf16", "bf16")) > 20
  assert _dot_signatures(mixed) == {("bf16", "bf16", "f32"), ("f32", "f32", "f32")}
  assert "bf16" not in program(config)


def test_kernels_cast_once_give_the_same_gaussians_bit_for_bit():
  """`cast_matmul_kernels` stores every rounded kernel rounded; the Gaussians do not change, and
  a kernel the model keeps in float32 (the Gaussian head's) would change them if it were cast."""
  config = FULL.replace(dynamic_motion="linear", matmul_dtype="bfloat16")
  keys = iter(jax.random.split(jax.random.key(3), 200))
  # every weight away from its (often zero) initial value, so that any wrong cast shows
  params = jax.tree.map(
    lambda x: x + 0.1 * jax.random.normal(next(keys), x.shape),
    init_params(jax.random.key(0), config),
  )
  images, plucker = jnp.zeros((1, 2, 16, 16, 3)), jnp.zeros((1, 2, 16, 16, 6))
  images = images + jax.random.uniform(jax.random.key(4), images.shape)
  plucker = plucker + jax.random.normal(jax.random.key(5), plucker.shape)
  times, target_times = jnp.array([[0.0, 0.5]]), jnp.array([0.25])
  forward = jax.jit(predict_gaussians, static_argnums=3)

  def gaussians(p):
    return np.asarray(forward(p, images, plucker, config, times, target_times))

  cast = cast_matmul_kernels(params, config)
  dtypes = [leaf.dtype for leaf in jax.tree.leaves(cast)]
  assert dtypes.count(BF16) > 20
  assert cast["activation_head"]["deconv"]["kernel"].dtype == jnp.float32
  assert cast["motion_head"]["kernel"].dtype == jnp.float32
  np.testing.assert_array_equal(gaussians(cast), gaussians(params))
  head = cast["activation_head"]["deconv"]
  wrong = {**cast, "activation_head": {"deconv": {**head, "kernel": _rounded(head["kernel"])}}}
  assert np.abs(gaussians(wrong) - gaussians(params)).max() > 0
  assert cast_matmul_kernels(params, FULL) is params  # float32 matmuls: nothing to round


def test_matmul_dtype_is_validated():
  with pytest.raises(ValueError, match="matmul_dtype"):
    preset("tiny", matmul_dtype="float16")
  assert preset("tiny", matmul_dtype="float32").matmul_operand_dtype is None
  assert preset("tiny", matmul_dtype="bfloat16").matmul_operand_dtype == jnp.bfloat16
