"""Line plots and trajectory plots as PNG without matplotlib (PIL's ImageDraw + its bitmap font).

matplotlib is not a dependency of the project; the studies only need labelled line charts and a
2-D trajectory picture, which PIL draws well enough.
"""

from __future__ import annotations

import itertools
import math
import pathlib
from collections.abc import Sequence

import numpy as np
from PIL import Image, ImageDraw, ImageFont

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


def _draw_series(draw, points: list[tuple[float, float]], color, *, dashed: bool) -> None:
  """Line segments (dashed: 5 dashes per segment) and a marker at every pixel point."""
  for (u0, v0), (u1, v1) in itertools.pairwise(points):
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
  for u, v in points:
    draw.ellipse([u - 3, v - 3, u + 3, v + 3], fill=color)


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
    series: legend label -> (x values, y values); non-finite points are skipped.
    title, xlabel, ylabel: texts.
    log_x: logarithmic x axis (x must be > 0).
    size: (width, height) in pixels.
    dashed: labels drawn with dashed lines.
  """
  width, height = size
  left, right, top, bottom = 64, 16, 36, 48
  image = Image.new("RGB", size, "white")
  draw = ImageDraw.Draw(image)
  font = ImageFont.load_default()
  clean = {}
  for name, (xs, ys) in series.items():
    xs, ys = np.asarray(xs, np.float64), np.asarray(ys, np.float64)
    keep = np.isfinite(xs) & np.isfinite(ys) & ((xs > 0) if log_x else True)
    clean[name] = (xs[keep], ys[keep])
  all_x = np.concatenate([xs for xs, _ in clean.values()] or [np.zeros(1)])
  all_y = np.concatenate([ys for _, ys in clean.values()] or [np.zeros(1)])
  if all_x.size == 0:
    all_x, all_y = np.zeros(1), np.zeros(1)
  fx = np.log10 if log_x else (lambda v: np.asarray(v, np.float64))
  x_lo, x_hi = float(fx(all_x).min()), float(fx(all_x).max())
  y_ticks = _nice_ticks(float(all_y.min()), float(all_y.max()))
  y_lo, y_hi = float(min(y_ticks[0], all_y.min())), float(max(y_ticks[-1], all_y.max()))
  if x_hi - x_lo < 1e-12:
    x_lo, x_hi = x_lo - 0.5, x_hi + 0.5
  if y_hi - y_lo < 1e-12:
    y_lo, y_hi = y_lo - 0.5, y_hi + 0.5

  def to_pixel(x, y):
    u = left + (fx(x) - x_lo) / (x_hi - x_lo) * (width - left - right)
    v = height - bottom - (y - y_lo) / (y_hi - y_lo) * (height - top - bottom)
    return float(u), float(v)

  draw.rectangle([left, top, width - right, height - bottom], outline=(0, 0, 0))
  for tick in y_ticks:
    if y_lo <= tick <= y_hi:
      _, v = to_pixel(all_x[0] if not log_x else 10**x_lo, tick)
      draw.line([left - 4, v, width - right, v], fill=(225, 225, 225))
      draw.text((4, v - 5), _label(tick, y_ticks), fill=(0, 0, 0), font=font)
  x_ticks = (
    sorted(set(all_x.tolist()))
    if log_x or len(set(all_x.tolist())) <= 8
    else _nice_ticks(x_lo, x_hi).tolist()
  )
  for tick in x_ticks:
    if log_x or x_lo <= tick <= x_hi:
      u, _ = to_pixel(tick, y_lo)
      draw.line([u, height - bottom, u, height - bottom + 4], fill=(0, 0, 0))
      draw.text(
        (u - 8, height - bottom + 6),
        _label(tick, None if log_x else np.asarray(x_ticks)),
        fill=(0, 0, 0),
        font=font,
      )
  draw.text((left, 10), title, fill=(0, 0, 0), font=font)
  draw.text(((width - 6 * len(xlabel)) // 2, height - 18), xlabel, fill=(0, 0, 0), font=font)
  draw.text((4, top - 16), ylabel, fill=(0, 0, 0), font=font)
  legend_y = top + 6
  for index, (name, (xs, ys)) in enumerate(clean.items()):
    color = PALETTE[index % len(PALETTE)]
    order = np.argsort(xs)
    _draw_series(
      draw, [to_pixel(x, y) for x, y in zip(xs[order], ys[order])], color, dashed=name in dashed
    )
    draw.line(
      [width - right - 150, legend_y + 5, width - right - 130, legend_y + 5], fill=color, width=3
    )
    draw.text((width - right - 125, legend_y), name, fill=(0, 0, 0), font=font)
    legend_y += 14
  path = pathlib.Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  image.save(path)
  return path


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
    image = Image.new("RGB", (size, size), "white")
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
  ImageDraw.Draw(image).text((4, 4), title, fill=(0, 0, 0), font=ImageFont.load_default())
  path = pathlib.Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  image.save(path)
  return path
