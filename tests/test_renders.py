"""tokengs_jax.renders: the evaluation's target renders (one set for every target or one per
target) and their exact compaction."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scenes import EVAL_HEIGHT as HEIGHT
from scenes import EVAL_WIDTH as WIDTH
from scenes import evaluation_batch, evaluation_gaussians

from tokengs_jax import renders, splatting
from tokengs_jax.camera import invert_rigid
from tokengs_jax.gaussians import Gaussians


def test_render_targets_renders_one_set_per_target_view_when_given():
  """Gaussians [B, V]: set v is seen by camera v only (dynamic models decode one per target)."""
  batch = evaluation_batch(np.random.default_rng(4), [0, 4], [1, 3])
  per_view = evaluation_gaussians((1, 2))
  rendered = renders.render_targets(
    per_view, batch["target_c2w"], batch["target_intrinsics"], height=HEIGHT, width=WIDTH
  )
  assert rendered.rgb.shape == (1, 2, HEIGHT, WIDTH, 3) and rendered.depth.shape == (
    1,
    2,
    HEIGHT,
    WIDTH,
    1,
  )
  for view in range(2):
    one = jax.tree.map(lambda x: x[:, view], per_view)
    alone = renders.render_targets(
      one,
      batch["target_c2w"][:, view : view + 1],
      batch["target_intrinsics"][:, view : view + 1],
      height=HEIGHT,
      width=WIDTH,
    )
    np.testing.assert_allclose(rendered.rgb[:, view], alone.rgb[:, 0], atol=1e-6)
  assert np.abs(rendered.rgb[0, 0] - rendered.rgb[0, 1]).max() > 1e-3


@pytest.mark.parametrize("batch_shape", [(1,), (1, 2)])
def test_render_targets_compacted_renders_the_same_images_exactly(batch_shape):
  """`compact=True` moves out what no target can draw (here most of 600 Gaussians: behind the
  cameras, off the images, transparent) and renders the same images, depth and alpha, to the bit;
  one set for every target, or one per target."""
  batch = evaluation_batch(np.random.default_rng(6), [0, 4], [1, 3])
  g = evaluation_gaussians(batch_shape, n=600, seed=3)
  spread = jax.random.uniform(jax.random.key(7), g.means.shape, minval=-6.0, maxval=6.0)
  opacities = jnp.where(jnp.arange(600) % 7 == 0, 0.003, g.opacities)
  g = Gaussians(g.means + spread, opacities, g.scales, g.quats, g.colors)
  targets = batch["target_c2w"], batch["target_intrinsics"]
  full = renders.render_targets(g, *targets, height=HEIGHT, width=WIDTH)
  compacted = renders.render_targets(g, *targets, height=HEIGHT, width=WIDTH, compact=True)
  assert full.alpha.max() > 0.5
  w2c = invert_rigid(jnp.asarray(targets[0]))
  if len(batch_shape) == 2:
    w2c, targets = w2c[:, :, None], (None, targets[1][:, :, None])
  small = splatting.compaction.compact_for_cameras(g, w2c, targets[1], height=HEIGHT, width=WIDTH)
  assert small.num_gaussians < 600  # something was moved out
  for name in ("rgb", "depth", "alpha"):
    np.testing.assert_array_equal(getattr(compacted, name), getattr(full, name), err_msg=name)
