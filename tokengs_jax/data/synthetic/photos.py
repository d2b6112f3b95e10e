"""Photographs as textures: natural-image statistics for the synthetic scenes, read offline.

scikit-image ships a few dozen real photographs inside its wheel (`skimage/data/*.png|jpg`;
nothing is downloaded). They give the ray tracer what no procedural texture has: the edges,
gradients and clutter of real surfaces, which is what a model must match across views to learn
depth. The photographs are split once, here, into a training pool and a held-out pool that only
the frozen test generator (`synthetic.courtyards`) uses, so a test scene's surfaces are never
ones a model was trained on.

Each photograph is decoded once per process, box-downsampled so its longer side is at most
`MAX_SIDE` texels (frames are 32-64 pixels wide: more texels would only alias), and kept as
float32 [H, W, 3] in [0, 1] (grey photographs repeated over the channels).
"""

from __future__ import annotations

import functools
import pathlib

import numpy as np
from PIL import Image

MAX_SIDE = 128

# Colour photographs and grey textures (grey ones are tinted by the texture's two colours).
TRAIN_PHOTOS = (
  "astronaut.png",
  "coffee.png",
  "chelsea.png",
  "hubble_deep_field.jpg",
  "ihc.png",
  "color.png",
  "brick.png",
  "grass.png",
  "camera.png",
  "moon.png",
  "text.png",
  "clock_motion.png",
  "cell.png",
)
# Never drawn by a training generator: only `synthetic.courtyards` (the frozen test family).
HELD_OUT_PHOTOS = (
  "rocket.jpg",
  "motorcycle_left.png",
  "retina.jpg",
  "gravel.png",
  "coins.png",
  "page.png",
)


def _data_dir() -> pathlib.Path:
  try:
    import skimage
  except ImportError as error:  # a main dependency; say which one when it is missing
    raise ImportError("photo textures need scikit-image (`pip install scikit-image`)") from error
  return pathlib.Path(skimage.__file__).parent / "data"


@functools.lru_cache(maxsize=None)
def photo(name: str) -> np.ndarray:
  """The photograph `name` (a file of scikit-image's data folder) as float32 [H, W, 3] in [0, 1],
  longer side at most `MAX_SIDE`."""
  if name not in TRAIN_PHOTOS + HELD_OUT_PHOTOS:
    raise ValueError(
      f"unknown photograph {name!r}; expected one of {TRAIN_PHOTOS + HELD_OUT_PHOTOS}"
    )
  with Image.open(_data_dir() / name) as image:
    image = image.convert("RGB")
    scale = MAX_SIDE / max(image.size)
    if scale < 1:
      size = (max(1, round(image.width * scale)), max(1, round(image.height * scale)))
      image = image.resize(size, Image.BOX)
    return np.asarray(image, np.float32) / 255.0


def is_grey(name: str) -> bool:
  """Whether the photograph has no colour of its own (it is then tinted)."""
  image = photo(name)
  return bool(np.abs(image - image.mean(-1, keepdims=True)).max() < 1e-3)
