"""The encoder's blocks (`tokengs_jax.model.encoder`): rematerialised blocks change nothing but
memory."""

import chex
import jax
import jax.numpy as jnp
import pytest
from scenes import MICRO, micro_params, random_inputs

from tokengs_jax.model import reconstruct


@pytest.mark.slow
def test_remat_changes_nothing_but_memory():
  params = micro_params()
  images, c2w, intrinsics = random_inputs(jax.random.key(1), 1, 2, 8, 8)

  def loss(p, config):
    return jnp.sum(reconstruct(p, images, c2w, intrinsics, config=config).means)

  grad = jax.jit(jax.grad(loss), static_argnums=1)
  plain = grad(params, MICRO)
  remat = grad(params, MICRO.replace(remat=True))
  chex.assert_trees_all_close(plain, remat, rtol=1e-5, atol=1e-7)
