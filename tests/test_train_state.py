"""`train.state`: a fresh `TrainState` holds the parameters, the optimiser's initial state, step 0
and the seed's key (and, when asked, the parameters' moving average), and is a pytree that jit maps
and `replace` updates."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from tokengs_jax.train.state import TrainState, create_train_state, ema_update, trained_params

PARAMS = {"w": jnp.arange(6.0).reshape(2, 3), "b": jnp.ones(3)}


def test_a_fresh_state_is_step_zero_with_the_seeds_key_and_the_optimisers_init():
  state = create_train_state(PARAMS, optax.adam(1e-3), seed=7)
  assert state.step.shape == () and state.step.dtype == jnp.int32 and int(state.step) == 0
  np.testing.assert_array_equal(state.rng, jax.random.PRNGKey(7))
  assert state.params is PARAMS
  adam = state.opt_state[0]  # ScaleByAdamState: zero moments, count 0
  assert int(adam.count) == 0
  for moments in (adam.mu, adam.nu):
    assert jax.tree.structure(moments) == jax.tree.structure(PARAMS)
    assert all(not np.any(leaf) for leaf in jax.tree.leaves(moments))
  other = create_train_state(PARAMS, optax.adam(1e-3), seed=8)
  assert not np.array_equal(other.rng, state.rng)


def test_the_state_is_a_pytree_jit_maps_and_replace_updates():
  state = create_train_state(PARAMS, optax.sgd(0.5), seed=0)
  # params (2) + sgd's empty state (none) + step + rng
  assert len(jax.tree.leaves(state)) == 4

  @jax.jit
  def step(state):
    grads = jax.tree.map(jnp.ones_like, state.params)
    updates, opt_state = optax.sgd(0.5).update(grads, state.opt_state)
    params = optax.apply_updates(state.params, updates)
    return state.replace(params=params, opt_state=opt_state, step=state.step + 1)

  after = step(step(state))
  assert isinstance(after, TrainState) and int(after.step) == 2
  np.testing.assert_allclose(after.params["w"], PARAMS["w"] - 1.0)
  np.testing.assert_array_equal(after.rng, state.rng)
  with pytest.raises(dataclasses.FrozenInstanceError):
    after.step = jnp.zeros((), jnp.int32)


def test_the_parameter_average_starts_as_a_copy_of_the_params_and_is_absent_when_off():
  assert create_train_state(PARAMS, optax.sgd(0.5), seed=0).ema_params is None
  state = create_train_state(PARAMS, optax.sgd(0.5), seed=0, ema_decay=0.9)
  jax.tree.map(np.testing.assert_array_equal, state.ema_params, PARAMS)
  assert state.ema_params["w"] is not PARAMS["w"]  # its own buffers: the step donates both
  assert trained_params(state) is state.ema_params
  assert trained_params(state.replace(ema_params=None)) is state.params
  moved = ema_update(state.ema_params, {"w": PARAMS["w"] + 10.0, "b": PARAMS["b"]}, 0.9)
  np.testing.assert_allclose(moved["w"], PARAMS["w"] + 1.0, rtol=1e-6)
  np.testing.assert_array_equal(moved["b"], PARAMS["b"])
