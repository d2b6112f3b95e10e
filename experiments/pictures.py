"""Grids a person can read: cells upscaled (nearest) to at least 128 px, labelled rows, and a
colour bar for depth rows."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from tokengs_jax import export

MIN_CELL = 128  # pixels of a cell's shorter side
_PAD = 4
_BAR_WIDTH = 16
_TEXT = (0, 0, 0)


def _font(size: int = 14):
  return ImageFont.load_default(size=size)


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
  bar = Image.new("RGB", (_BAR_WIDTH + _PAD + text_width, height), (255, 255, 255))
  bar.paste(ramp, (0, 0))
  draw = ImageDraw.Draw(bar)
  draw.text((_BAR_WIDTH + _PAD, 0), labels[0], fill=_TEXT, font=font)
  draw.text((_BAR_WIDTH + _PAD, height), labels[1], fill=_TEXT, font=font, anchor="ls")
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
  font = _font()
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
    "RGB", (label_width + max(widths) + _PAD, top + sum(h + _PAD for h in heights)), (255, 255, 255)
  )
  draw = ImageDraw.Draw(canvas)
  if title:
    draw.text((_PAD, _PAD), title, fill=_TEXT, font=font)
  y = top
  for i, ((label, images), height) in enumerate(zip(rows, heights)):
    draw.text((_PAD, y + height // 2), label, fill=_TEXT, font=font, anchor="lm")
    x = label_width
    for img in images:
      canvas.paste(Image.fromarray(img), (x, y))
      x += img.shape[1] + _PAD
    if i in bars:
      canvas.paste(bars[i], (x, y))
    y += height + _PAD
  return np.asarray(canvas)
