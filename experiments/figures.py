"""The figures the experiments write, drawn with PIL (matplotlib is not a dependency): picture
grids a person can read (cells upscaled nearest to at least 128 px, labelled rows, a colour bar for
depth rows; `labelled_grid`, returned as arrays) and charts written as PNG (`line_plot`,
`scatter_plot`, `trajectory_plot`)."""

from __future__ import annotations

import dataclasses
import itertools
import math
import pathlib
from collections.abc import Sequence

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from tokengs_jax import export

_BLACK, _WHITE = (0, 0, 0), (255, 255, 255)


def _font(size: int | None = None):
  """PIL's default font at `size` px (None: its default size, the charts' text)."""
  return ImageFont.load_default(size=size)


# ----------------------------------------------------------------------------------------------
# Picture grids

MIN_CELL = 128  # pixels of a cell's shorter side
_GRID_TEXT_SIZE = 14
_PAD = 4
_BAR_WIDTH = 16


def upscale(image: np.ndarray, min_size: int = MIN_CELL) -> np.ndarray:
  """[H, W, C] repeated by the smallest integer factor that makes min(H, W) >= min_size."""
  factor = max(1, math.ceil(min_size / min(image.shape[:2])))
  return np.repeat(np.repeat(image, factor, axis=0), factor, axis=1)


def depth_row(
  depths: Sequence[np.ndarray], alphas: Sequence[np.ndarray | None]
) -> tuple[list[np.ndarray], tuple[float, float] | None]:
  """Depth maps [H, W, 1] coloured on one shared scale -> (images, (near, far) depth or None)."""
  inverse_range = export.inverse_depth_range(depths, alphas)
  images = [export.colorize_depth(d, a, inverse_range) for d, a in zip(depths, alphas)]
  if inverse_range is None:
    return images, None
  lo, hi = inverse_range
  return images, (1.0 / max(hi, 1e-12), 1.0 / max(lo, 1e-12))


def _colour_bar(height: int, near_far: tuple[float, float], font) -> Image.Image:
  """A vertical ramp (near at the top) with its depth values written beside it."""
  t = np.linspace(1.0, 0.0, height)[:, None].repeat(_BAR_WIDTH, axis=1)
  ramp = Image.fromarray(export.to_uint8(export.depth_ramp(t)))
  labels = [f"near {near_far[0]:.2f}", f"far {near_far[1]:.2f}"]
  text_width = max(int(font.getlength(label)) for label in labels)
  bar = Image.new("RGB", (_BAR_WIDTH + _PAD + text_width, height), _WHITE)
  bar.paste(ramp, (0, 0))
  draw = ImageDraw.Draw(bar)
  draw.text((_BAR_WIDTH + _PAD, 0), labels[0], fill=_BLACK, font=font)
  draw.text((_BAR_WIDTH + _PAD, height), labels[1], fill=_BLACK, font=font, anchor="ls")
  return bar


def labelled_grid(
  rows: Sequence[tuple[str, Sequence[np.ndarray]]],
  *,
  title: str = "",
  depth_range: tuple[float, float] | None = None,
  min_cell: int = MIN_CELL,
) -> np.ndarray:
  """Rows of images, each row named on its left; cells upscaled to at least `min_cell` px.

  rows: (label, images [H, W, 3] floats in [0, 1] or uint8) per row.
  depth_range: (near, far) depth of the rows labelled "depth ..." (`depth_row`): draws a colour
    bar at the end of each such row.
  Returns the picture, uint8 [H, W, 3].
  """
  font = _font(_GRID_TEXT_SIZE)
  rows = [
    (label, [upscale(export.to_uint8(img), min_cell) for img in images])
    for label, images in rows
    if len(images)
  ]
  label_width = max([int(font.getlength(label)) for label, _ in rows] + [0]) + 2 * _PAD
  heights = [max(img.shape[0] for img in images) for _, images in rows]
  bars = {
    i: _colour_bar(heights[i], depth_range, font)
    for i, (label, _) in enumerate(rows)
    if depth_range is not None and label.startswith("depth")
  }
  widths = [
    sum(img.shape[1] + _PAD for img in images) + (bars[i].width + _PAD if i in bars else 0)
    for i, (_, images) in enumerate(rows)
  ]
  top = 24 if title else _PAD
  canvas = Image.new(
    "RGB", (label_width + max(widths) + _PAD, top + sum(h + _PAD for h in heights)), _WHITE
  )
  draw = ImageDraw.Draw(canvas)
  if title:
    draw.text((_PAD, _PAD), title, fill=_BLACK, font=font)
  y = top
  for i, ((label, images), height) in enumerate(zip(rows, heights)):
    draw.text((_PAD, y + height // 2), label, fill=_BLACK, font=font, anchor="lm")
    x = label_width
    for img in images:
      canvas.paste(Image.fromarray(img), (x, y))
      x += img.shape[1] + _PAD
    if i in bars:
      canvas.paste(bars[i], (x, y))
    y += height + _PAD
  return np.asarray(canvas)


# ----------------------------------------------------------------------------------------------
# Charts

# Tableau-like palette, distinguishable in print.
PALETTE = (
  (31, 119, 180),
  (255, 127, 14),
  (44, 160, 44),
  (214, 39, 40),
  (148, 103, 189),
  (140, 86, 75),
  (227, 119, 194),
  (127, 127, 127),
  (188, 189, 34),
  (23, 190, 207),
)


def _nice_ticks(low: float, high: float, count: int = 5) -> np.ndarray:
  """About `count` round tick values covering [low, high]."""
  if not math.isfinite(low) or not math.isfinite(high):
    return np.array([0.0])
  if high - low < 1e-12:
    low, high = low - 0.5, high + 0.5
  raw = (high - low) / max(count - 1, 1)
  magnitude = 10.0 ** math.floor(math.log10(raw))
  step = min((m * magnitude for m in (1, 2, 2.5, 5, 10) if m * magnitude >= raw), default=raw)
  return np.arange(math.floor(low / step) * step, high + 0.5 * step, step)


def _label(value: float, ticks: np.ndarray | None = None) -> str:
  """Tick text with as many decimals as the tick spacing needs."""
  if ticks is not None and len(ticks) > 1:
    spacing = float(np.min(np.diff(np.sort(ticks))))
    if spacing > 0:
      text = f"{value:.{max(0, -math.floor(math.log10(spacing)) + 1)}f}"
      return text.rstrip("0").rstrip(".") if "." in text else text
  return f"{value:.3g}"


def _draw_series(
  draw,
  points: list[tuple[float, float]],
  color,
  *,
  dashed: bool = False,
  joined: bool = True,
  markers: bool = True,
) -> None:
  """Line segments between the pixel points (`joined`; dashed: 5 dashes per segment) and a marker
  at each (`markers`)."""
  for (u0, v0), (u1, v1) in itertools.pairwise(points) if joined else ():
    if dashed:
      for t0 in np.arange(0.0, 1.0, 0.2):
        t1 = t0 + 0.1
        draw.line(
          [u0 + t0 * (u1 - u0), v0 + t0 * (v1 - v0), u0 + t1 * (u1 - u0), v0 + t1 * (v1 - v0)],
          fill=color,
          width=2,
        )
    else:
      draw.line([u0, v0, u1, v1], fill=color, width=2)
  for u, v in points if markers else ():
    draw.ellipse([u - 3, v - 3, u + 3, v + 3], fill=color)


# Pixels between the canvas edge and the plot area: room for the tick labels and the texts.
_LEFT, _RIGHT, _TOP, _BOTTOM = 64, 16, 36, 48


def _finite_series(series, log_x: bool) -> dict[str, tuple[np.ndarray, np.ndarray]]:
  """The series as float arrays without their non-finite points (and x <= 0 on a log axis)."""
  clean = {}
  for name, (xs, ys) in series.items():
    xs, ys = np.asarray(xs, np.float64), np.asarray(ys, np.float64)
    keep = np.isfinite(xs) & np.isfinite(ys) & ((xs > 0) if log_x else True)
    clean[name] = (xs[keep], ys[keep])
  return clean


@dataclasses.dataclass(frozen=True)
class _Axes:
  """Data -> pixel mapping of a chart's plot area, and the ticks of both axes."""

  size: tuple[int, int]
  log_x: bool
  x_range: tuple[float, float]  # in axis units (log10 x on a log axis)
  y_range: tuple[float, float]
  x_ticks: list[float]  # in data units
  y_ticks: np.ndarray

  @classmethod
  def fit(cls, clean: dict, log_x: bool, size: tuple[int, int], tick_each_x: bool = True) -> _Axes:
    """Axes spanning every point of the (finite) series; y widened to its outer round ticks.
    tick_each_x: with few distinct x values (or a log axis), a tick at each."""
    all_x = np.concatenate([xs for xs, _ in clean.values()] or [np.zeros(1)])
    all_y = np.concatenate([ys for _, ys in clean.values()] or [np.zeros(1)])
    if all_x.size == 0:
      all_x, all_y = np.zeros(1), np.zeros(1)
    axis_x = np.log10(all_x) if log_x else all_x
    x_lo, x_hi = float(axis_x.min()), float(axis_x.max())
    y_ticks = _nice_ticks(float(all_y.min()), float(all_y.max()))
    y_lo, y_hi = float(min(y_ticks[0], all_y.min())), float(max(y_ticks[-1], all_y.max()))
    if x_hi - x_lo < 1e-12:
      x_lo, x_hi = x_lo - 0.5, x_hi + 0.5
    if y_hi - y_lo < 1e-12:
      y_lo, y_hi = y_lo - 0.5, y_hi + 0.5
    # Few distinct x values (or a log axis): a tick at each, so every data point is labelled.
    distinct = sorted(set(all_x.tolist()))
    at_points = tick_each_x and (log_x or len(distinct) <= 8)
    x_ticks = distinct if at_points else _nice_ticks(x_lo, x_hi).tolist()
    return cls(size, log_x, (x_lo, x_hi), (y_lo, y_hi), x_ticks, y_ticks)

  def u(self, x) -> float:
    (x_lo, x_hi), width = self.x_range, self.size[0]
    axis_x = np.log10(x) if self.log_x else np.asarray(x, np.float64)
    return float(_LEFT + (axis_x - x_lo) / (x_hi - x_lo) * (width - _LEFT - _RIGHT))

  def v(self, y) -> float:
    (y_lo, y_hi), height = self.y_range, self.size[1]
    return float(height - _BOTTOM - (y - y_lo) / (y_hi - y_lo) * (height - _TOP - _BOTTOM))


def _draw_axes(draw, axes: _Axes, font) -> None:
  """The plot-area frame, horizontal grid lines with y labels, and x tick marks with labels."""
  width, height = axes.size
  (x_lo, x_hi), (y_lo, y_hi) = axes.x_range, axes.y_range
  draw.rectangle([_LEFT, _TOP, width - _RIGHT, height - _BOTTOM], outline=_BLACK)
  for tick in axes.y_ticks:
    if y_lo <= tick <= y_hi:
      v = axes.v(tick)
      draw.line([_LEFT - 4, v, width - _RIGHT, v], fill=(225, 225, 225))
      draw.text((4, v - 5), _label(tick, axes.y_ticks), fill=_BLACK, font=font)
  for tick in axes.x_ticks:
    if axes.log_x or x_lo <= tick <= x_hi:
      u = axes.u(tick)
      draw.line([u, height - _BOTTOM, u, height - _BOTTOM + 4], fill=_BLACK)
      draw.text(
        (u - 8, height - _BOTTOM + 6),
        _label(tick, None if axes.log_x else np.asarray(axes.x_ticks)),
        fill=_BLACK,
        font=font,
      )


def _save(image: Image.Image, path) -> pathlib.Path:
  path = pathlib.Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  image.save(path)
  return path


def _chart(axes: _Axes, *, title: str, xlabel: str, ylabel: str):
  """A white canvas with the axes and the texts drawn.  -> (image, draw, font)."""
  width, height = axes.size
  image = Image.new("RGB", axes.size, _WHITE)
  draw = ImageDraw.Draw(image)
  font = _font()
  _draw_axes(draw, axes, font)
  draw.text((_LEFT, 10), title, fill=_BLACK, font=font)
  draw.text(((width - 6 * len(xlabel)) // 2, height - 18), xlabel, fill=_BLACK, font=font)
  draw.text((4, _TOP - 16), ylabel, fill=_BLACK, font=font)
  return image, draw, font


def _legend(draw, font, width: int, entries: Sequence[tuple[str, tuple]]) -> None:
  """(label, colour) entries listed at the top right, each after a stroke of its colour."""
  for row, (name, color) in enumerate(entries):
    y = _TOP + 6 + 14 * row
    draw.line([width - _RIGHT - 150, y + 5, width - _RIGHT - 130, y + 5], fill=color, width=3)
    draw.text((width - _RIGHT - 125, y), name, fill=_BLACK, font=font)


def line_plot(
  path,
  series: dict[str, tuple[Sequence[float], Sequence[float]]],
  *,
  title: str,
  xlabel: str,
  ylabel: str,
  log_x: bool = False,
  size: tuple[int, int] = (640, 420),
  dashed: Sequence[str] = (),
) -> pathlib.Path:
  """Writes a labelled line chart (markers at the data points) as PNG.

  Args:
    path: output PNG path.
    series: legend label -> (x values, y values); non-finite points are skipped. Where an x
      repeats (seeds of one setting), the line joins the mean at each x and every point keeps
      its marker, so the line does not zigzag between repeats.
    title, xlabel, ylabel: texts.
    log_x: logarithmic x axis (x must be > 0).
    size: (width, height) in pixels.
    dashed: labels drawn with dashed lines.
  """
  clean = _finite_series(series, log_x)
  axes = _Axes.fit(clean, log_x, size)
  image, draw, font = _chart(axes, title=title, xlabel=xlabel, ylabel=ylabel)
  colors = [PALETTE[index % len(PALETTE)] for index in range(len(clean))]
  for color, (name, (xs, ys)) in zip(colors, clean.items()):
    at = np.unique(xs)
    means = [(axes.u(x), axes.v(ys[xs == x].mean())) for x in at]
    _draw_series(draw, means, color, dashed=name in dashed, markers=False)
    _draw_series(draw, [(axes.u(x), axes.v(y)) for x, y in zip(xs, ys)], color, joined=False)
  _legend(draw, font, size[0], list(zip(clean, colors)))
  return _save(image, path)


def scatter_plot(
  path,
  series: dict[str, tuple[Sequence[float], Sequence[float]]],
  *,
  title: str,
  xlabel: str,
  ylabel: str,
  diagonal: str | None = None,
  size: tuple[int, int] = (640, 420),
) -> pathlib.Path:
  """Writes a labelled scatter chart (a marker per point, no lines) as PNG.

  Args:
    path: output PNG path.
    series: legend label -> (x values, y values); non-finite points are skipped.
    title, xlabel, ylabel: texts.
    diagonal: legend label of a dashed y = x line from 0 (or the lowest value) to the highest
      value (None: no line).
    size: (width, height) in pixels.
  """
  clean = _finite_series(series, log_x=False)
  lines = {}
  if diagonal is not None:
    values = np.concatenate([np.concatenate(xy) for xy in clean.values()] or [np.zeros(0)])
    ends = np.array([min(values.min(), 0.0), values.max()]) if values.size else np.array([0, 1])
    lines[diagonal] = (ends, ends)
  axes = _Axes.fit({**clean, **lines}, False, size, tick_each_x=False)
  image, draw, font = _chart(axes, title=title, xlabel=xlabel, ylabel=ylabel)
  for xs, ys in lines.values():
    ends = [(axes.u(x), axes.v(y)) for x, y in zip(xs, ys)]
    _draw_series(draw, ends, (127, 127, 127), dashed=True, markers=False)
  colors = [PALETTE[index % len(PALETTE)] for index in range(len(clean))]
  for color, (xs, ys) in zip(colors, clean.values()):
    _draw_series(draw, [(axes.u(x), axes.v(y)) for x, y in zip(xs, ys)], color, joined=False)
  _legend(
    draw, font, size[0], list(zip(clean, colors)) + [(name, (127, 127, 127)) for name in lines]
  )
  return _save(image, path)


def trajectory_plot(
  path,
  trajectories: np.ndarray,
  *,
  title: str,
  background: np.ndarray | None = None,
  size: int = 512,
) -> pathlib.Path:
  """Draws 2-D trajectories (e.g. projected Gaussian centres over time) as coloured polylines.

  Args:
    path: output PNG path.
    trajectories: [N, T, 2] pixel coordinates in the frame of `background` (or any units when
      there is none: then they are fitted to the canvas).
    title: text at the top.
    background: optional [H, W, 3] image in [0, 1] drawn underneath (dimmed).
    size: canvas edge when there is no background.
  Each trajectory goes from dark (first time) to its palette colour (last time), with a dot at the end.
  """
  trajectories = np.asarray(trajectories, np.float64)
  if background is not None:
    base = (np.clip(np.asarray(background, np.float64), 0, 1) * 0.5 + 0.25) * 255
    scale = max(1, size // max(background.shape[:2]))
    image = Image.fromarray(base.astype(np.uint8)).resize(
      (background.shape[1] * scale, background.shape[0] * scale), Image.NEAREST
    )
    points = trajectories * scale
  else:
    image = Image.new("RGB", (size, size), _WHITE)
    finite = trajectories[np.isfinite(trajectories).all(-1)]
    lo, hi = (finite.min(0), finite.max(0)) if finite.size else (np.zeros(2), np.ones(2))
    span = max(float((hi - lo).max()), 1e-9)
    points = 16 + (trajectories - lo) / span * (size - 32)
  draw = ImageDraw.Draw(image)
  for index, track in enumerate(points):
    color = np.array(PALETTE[index % len(PALETTE)], np.float64)
    steps = len(track)
    for t in range(steps - 1):
      if np.isfinite(track[t]).all() and np.isfinite(track[t + 1]).all():
        shade = 0.35 + 0.65 * (t + 1) / max(steps - 1, 1)
        draw.line([*track[t], *track[t + 1]], fill=tuple(int(c) for c in color * shade), width=2)
    if np.isfinite(track[-1]).all():
      u, v = track[-1]
      draw.ellipse([u - 2, v - 2, u + 2, v + 2], fill=tuple(int(c) for c in color))
  ImageDraw.Draw(image).text((4, 4), title, fill=_BLACK, font=_font())
  return _save(image, path)
