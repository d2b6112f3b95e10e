"""Mixed-precision matmuls: operands rounded to a narrow dtype, products accumulated and returned
in float32, in the forward and in the backward pass.

Why: on a CPU with native bfloat16 dot instructions (avx512_bf16) XLA:CPU runs a bfloat16 x
bfloat16 -> float32 dot about twice as fast as a float32 one, but a bfloat16 -> bfloat16 dot no
faster than float32 (docs/benchmarks.md, "Model" has the figures). `ModelConfig.matmul_dtype`
selects this mode; everything else (parameters, LayerNorm, softmax, GELU, residuals) stays in
the compute dtype.

Autodiff of `lax.dot_general(a.astype(bf16), b.astype(bf16), preferred_element_type=f32)`
would differentiate through the casts and run the backward dots on float32 operands (the
float32 cotangent promotes the rounded operand back), i.e. at float32 speed; the `custom_vjp`
of `matmul` rounds the cotangent too, so every dot of the train step is a bf16 x bf16 -> f32 one.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax import lax


def einsum(spec: str, a: jax.Array, b: jax.Array, operand_dtype) -> jax.Array:
  """`jnp.einsum(spec, a, b)` on operands cast to `operand_dtype`, accumulated in float32.

  Returns float32 (callers cast where they need another dtype). With float32 operands this is
  the plain float32 einsum.
  """
  return jnp.einsum(
    spec, a.astype(operand_dtype), b.astype(operand_dtype), preferred_element_type=jnp.float32
  )


@functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
def matmul(x: jax.Array, kernel: jax.Array, operand_dtype) -> jax.Array:
  """x @ kernel with operands rounded to `operand_dtype` and float32 accumulation.

  Args:
    x: [..., K].
    kernel: [K, N], same dtype as x.
    operand_dtype: dtype both operands (and, in the backward pass, the cotangent) are rounded
      to before each dot.

  Returns:
    [..., N] in x's dtype.
  """
  return _matmul_fwd(x, kernel, operand_dtype)[0]


def _matmul_fwd(x, kernel, operand_dtype):
  if x.dtype != kernel.dtype:
    raise TypeError(f"matmul operands differ in dtype: {x.dtype} vs {kernel.dtype}")
  x_op, kernel_op = x.astype(operand_dtype), kernel.astype(operand_dtype)
  out = lax.dot_general(
    x_op, kernel_op, (((x.ndim - 1,), (0,)), ((), ())), preferred_element_type=jnp.float32
  )
  # The rounded operands are the residuals: the backward needs nothing finer, at half the bytes.
  return out.astype(x.dtype), (x_op, kernel_op)


def _matmul_bwd(operand_dtype, residuals, out_grad):
  x_op, kernel_op = residuals
  grad_op = out_grad.astype(operand_dtype)
  x_grad = lax.dot_general(
    grad_op, kernel_op, (((grad_op.ndim - 1,), (1,)), ((), ())), preferred_element_type=jnp.float32
  )
  leading = tuple(range(x_op.ndim - 1))
  kernel_grad = lax.dot_general(
    x_op, grad_op, ((leading, leading), ((), ())), preferred_element_type=jnp.float32
  )
  return x_grad.astype(out_grad.dtype), kernel_grad.astype(out_grad.dtype)


matmul.defvjp(_matmul_fwd, _matmul_bwd)


def dense_dot_general(operand_dtype):
  """A `dot_general` for `flax.linen.Dense(dot_general=...)` that runs `matmul`.

  Dense contracts the inputs' last axis with the kernel's first and has no batch axes; any
  other contraction is refused rather than silently computed another way.
  """

  def dot_general(x, kernel, dimension_numbers, precision=None, preferred_element_type=None):
    del precision, preferred_element_type  # the operand dtype decides; the result is x's dtype
    if dimension_numbers != (((x.ndim - 1,), (0,)), ((), ())):
      raise NotImplementedError(f"only Dense's contraction is supported, got {dimension_numbers}")
    return matmul(x, kernel, operand_dtype)

  return dot_general
