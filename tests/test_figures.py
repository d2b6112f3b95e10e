"""experiments.figures: upscaled grids, line and trajectory plots, tick labels (PIL)."""

import numpy as np
from PIL import Image

from experiments import figures


def test_upscale_is_nearest_neighbour_to_at_least_the_minimum():
  image = np.arange(2 * 3 * 3).reshape(2, 3, 3).astype(np.uint8)
  big = figures.upscale(image, 128)
  assert big.shape == (128, 192, 3)
  np.testing.assert_array_equal(big[::64, ::64], image)
  assert figures.upscale(np.zeros((200, 300, 3))).shape == (200, 300, 3)


def test_line_plot_draws_every_series(tmp_path):
  path = figures.line_plot(
    tmp_path / "p.png",
    {"a": ([1, 2, 4], [1.0, 2.0, 1.5]), "b": ([1, 2, 4], [0.5, float("nan"), 3.0])},
    title="t",
    xlabel="x",
    ylabel="y",
    log_x=True,
    dashed=("b",),
  )
  image = np.asarray(Image.open(path))
  for color in figures.PALETTE[:2]:
    assert np.any(np.all(image == np.array(color, np.uint8), axis=-1)), color


def test_line_plot_joins_the_mean_of_repeats_not_each_repeat(tmp_path):
  series = {"a": ([1, 1, 2], [0.0, 2.0, 1.0])}
  path = figures.line_plot(tmp_path / "p.png", series, title="t", xlabel="x", ylabel="y")
  image = np.asarray(Image.open(path))
  axes = figures._Axes.fit(figures._finite_series(series, False), False, (640, 420))
  color = np.array(figures.PALETTE[0], np.uint8)

  def painted(x, y):
    u, v = round(axes.u(x)), round(axes.v(y))
    return np.any(np.all(image[v - 1 : v + 2, u - 1 : u + 2] == color, axis=-1))

  assert painted(1, 0.0) and painted(1, 2.0) and painted(1.5, 1.0)  # markers and the mean line
  assert not painted(1, 0.5)  # no segment between the two repeats at x = 1


def test_trajectory_plot_on_background(tmp_path):
  tracks = np.stack([np.linspace([2, 2], [20, 10], 5), np.linspace([30, 5], [5, 30], 5)])
  path = figures.trajectory_plot(
    tmp_path / "t.png", tracks, title="flow", background=np.zeros((32, 32, 3)), size=64
  )
  assert Image.open(path).size == (64, 64)


def test_tick_labels_keep_significant_zeros():
  ticks = np.array([0.0, 10.0, 25.0, 50.0])
  assert [figures._label(v, ticks) for v in ticks] == ["0", "10", "25", "50"]
  assert figures._label(19.0, np.array([18.5, 19.0, 19.5])) == "19"
