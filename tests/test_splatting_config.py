"""`RenderConfig` (`splatting.config`): the budget ladder, and sizes it refuses."""

import numpy as np
import pytest
from render_scenes import HEIGHT, INTR, NUM, W2C, WIDTH, random_scene

from tokengs_jax.splatting import RenderConfig, render


def test_budget_ladder_sorts_small_scenes_in_a_small_buffer():
  config = RenderConfig()
  assert config.budget_ladder(65536, 256) == (262144, 524288, 1048576)
  assert config.budget_ladder(100, 256) == (4096,)  # small scenes: one size
  assert config.intersection_budget(100, 4) == 416  # never above N x tiles (chunk multiple)
  # whichever ladder step a scene is binned at, the image is the same
  g = random_scene(5)
  tiles = 3 * 4
  ladder = RenderConfig(min_intersections=32, chunk_size=8)
  single = RenderConfig(min_intersections=NUM * tiles, chunk_size=8)
  assert len(ladder.budget_ladder(NUM, tiles)) == 3 and len(single.budget_ladder(NUM, tiles)) == 1
  a = render(g, W2C[None], INTR[None], height=HEIGHT, width=WIDTH, config=ladder)
  b = render(g, W2C[None], INTR[None], height=HEIGHT, width=WIDTH, config=single)
  assert int(a.stats.num_intersections[0]) <= ladder.budget_ladder(NUM, tiles)[1]  # a lower step
  assert not bool(a.stats.truncated[0])
  np.testing.assert_array_equal(a.rgb, b.rgb)
  np.testing.assert_array_equal(a.depth, b.depth)


@pytest.mark.parametrize("knob", ["tile_size", "chunk_size", "tiles_per_step"])
def test_render_config_refuses_non_positive_sizes(knob):
  with pytest.raises(ValueError, match=knob):
    RenderConfig(**{knob: 0})


def test_render_config_refuses_a_subtile_that_does_not_divide_the_tile():
  with pytest.raises(ValueError, match="subtile_size"):
    RenderConfig(subtile_size=6)
  with pytest.raises(ValueError, match="subtile_size"):
    RenderConfig(subtile_size=0)
  assert RenderConfig(tile_size=8).subtile_size == 8  # the default fits gsplat's and 8-px tiles
