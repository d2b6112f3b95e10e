"""The compositor (`splatting.rasterize`): its halving ladder of block sizes."""


def test_compositor_block_sizes_halve_down_to_eight():
  from tokengs_jax.splatting import rasterize

  def sizes(tiles_per_step):
    tiling = rasterize.Tiling(32, 32, 8, 4, 4, 1, 32, tiles_per_step, 0.999, 1 / 255, 1e-4)
    return rasterize.step_sizes(tiling)

  assert sizes(128) == (128, 64, 32, 16, 8)
  assert sizes(35) == (35, 17, 8)
  assert sizes(3) == (3,)  # no ladder below 16: `test_chunking_...` compares the two paths
