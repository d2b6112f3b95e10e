"""Gaussians pytree and the official flat layout."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tokengs_jax.gaussians import Gaussians


def test_flat_round_trip_and_layout():
  flat = jnp.asarray(np.random.default_rng(0).normal(size=(2, 5, 14)), jnp.float32)
  g = Gaussians.from_flat(flat)
  assert g.means.shape == (2, 5, 3) and g.opacities.shape == (2, 5) and g.quats.shape == (2, 5, 4)
  np.testing.assert_array_equal(g.opacities, flat[..., 3])
  np.testing.assert_array_equal(g.scales, flat[..., 4:7])
  np.testing.assert_array_equal(g.quats, flat[..., 7:11])
  np.testing.assert_array_equal(g.colors, flat[..., 11:])
  np.testing.assert_array_equal(g.to_flat(), flat)
  assert g.num_gaussians == 5 and g.batch_shape == (2,)


def test_is_a_pytree_for_jit_vmap_grad():
  g = Gaussians.from_flat(jnp.ones((3, 4, 14)))
  assert len(jax.tree.leaves(g)) == 5
  summed = jax.jit(jax.vmap(lambda x: jnp.sum(x.to_flat())))(g)
  np.testing.assert_allclose(summed, 4 * 14)
  grads = jax.grad(lambda x: jnp.sum(x.means * 2.0))(g)
  np.testing.assert_allclose(grads.means, 2.0)
  np.testing.assert_allclose(grads.colors, 0.0)


def test_rejects_wrong_channel_count():
  with pytest.raises(ValueError):
    Gaussians.from_flat(jnp.ones((4, 13)))


def test_validate_returns_the_batch_shape_and_names_a_bad_field():
  g = Gaussians.from_flat(jnp.ones((2, 5, 14)))
  assert g.validate() == (2,)
  # batch shapes broadcast: one scene's colours shared by a batch of 2
  shared = Gaussians(g.means, g.opacities, g.scales, g.quats, g.colors[:1])
  assert shared.validate() == (2,)
  cases = {
    "colors": (jnp.ones((2, 5, 4)), r"colors must be \[..., N, 3\]"),
    "quats": (jnp.ones((2, 5, 3)), r"quats must be \[..., N, 4\]"),
    "opacities": (jnp.ones((2, 6)), "N = 6"),
    "scales": (jnp.ones((3, 5, 3)), "do not broadcast"),
    "means": (jnp.ones((2, 5, 3), jnp.complex64), "real numbers"),
  }
  for field, (value, match) in cases.items():
    fields = {**vars(g), field: value}
    with pytest.raises(ValueError, match=match):
      Gaussians(**fields).validate()


def test_first_set_takes_index_zero_of_every_batch_axis():
  flat = jnp.arange(2 * 3 * 5 * 14, dtype=jnp.float32).reshape(2, 3, 5, 14)
  first = Gaussians.from_flat(flat).first_set()
  assert first.batch_shape == ()
  np.testing.assert_array_equal(first.to_flat(), flat[0, 0])
  single = Gaussians.from_flat(flat[0])
  np.testing.assert_array_equal(single.first_set().to_flat(), flat[0, 0])


def test_static_and_dynamic_split_every_field_at_the_static_count():
  flat = jnp.arange(2 * 3 * 5 * 14, dtype=jnp.float32).reshape(2, 3, 5, 14)
  static, dynamic = Gaussians.from_flat(flat).static_and_dynamic(2)
  assert static.batch_shape == dynamic.batch_shape == (2, 3)
  np.testing.assert_array_equal(static.to_flat(), flat[..., :2, :])
  np.testing.assert_array_equal(dynamic.to_flat(), flat[..., 2:, :])
  # host arrays (the dynamic pictures) and traced ones (the auxiliary loss) alike
  host = jax.tree.map(np.asarray, Gaussians.from_flat(flat[0]))
  assert isinstance(host.static_and_dynamic(2)[1].opacities, np.ndarray)
  np.testing.assert_array_equal(host.static_and_dynamic(2)[1].to_flat(), flat[0, :, 2:])
  traced = jax.jit(lambda g: g.static_and_dynamic(4)[1].to_flat())(Gaussians.from_flat(flat))
  np.testing.assert_array_equal(traced, flat[..., 4:, :])
