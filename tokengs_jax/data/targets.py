"""The target views' per-pixel truth beyond their images, for `pipeline.make_example`.

`target_objects [Vt, H, W]` (where the record's `segmentations` show an object) and
`target_masks [Vt, H, W]` (the foreground masks: the record's `alphas`, Kubric's PNG alpha), each
resized, cropped and mirrored as `make_example` did the target images. A record without the field
(or without it for a chosen frame) raises `MissingTargetField`, which the pipeline reports as a
bad example.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from tokengs_jax.data.transforms import resize_and_center_crop, resize_and_center_crop_mask


class MissingTargetField(ValueError):
  """The record lacks a per-pixel field an example was asked to carry."""


def target_fields(record: dict, target: Sequence[int], config, flipped: bool) -> dict:
  """The fields `config` (a `pipeline.ExampleConfig`) asks for, of the record's target frames
  `target` [Vt], as float32 [Vt, H, W] at `config.image_shape`, mirrored left-right when the
  images were (`flipped`): "target_objects" (1 on object pixels) with `config.target_objects`,
  "target_masks" (alpha / 255, 1: foreground) with `config.target_masks`."""
  image_shape, fields = config.image_shape, {}
  if config.target_objects:
    segmentations = _read(record, "segmentations", target, "target_objects")
    fields["target_objects"] = resize_and_center_crop_mask(segmentations > 0, image_shape)
  if config.target_masks:
    alphas = _read(record, "alphas", target, "target_masks")
    # the images' own resize (official: the masks go through the images' transform), on the
    # alpha repeated into the three channels that transform takes
    rgb = np.repeat(alphas.astype(np.uint8)[..., None], 3, axis=-1)
    resized, _ = resize_and_center_crop(rgb, np.zeros((len(target), 4), np.float32), image_shape)
    fields["target_masks"] = resized[..., 0] / 255.0
  return {
    name: np.ascontiguousarray(value[:, :, ::-1] if flipped else value).astype(np.float32)
    for name, value in fields.items()
  }


def _read(record: dict, field: str, target: Sequence[int], purpose: str) -> np.ndarray:
  """The record's `field` at the frames `target`, stacked; `MissingTargetField` naming `purpose`
  if the record (or one of those frames: a lazy sequence's `.present(i)`) has none."""
  if field not in record:
    raise MissingTargetField(f"{purpose} needs the record's '{field}'")
  frames = record[field]
  missing = [int(i) for i in target if hasattr(frames, "present") and not frames.present(int(i))]
  if missing:
    raise MissingTargetField(f"{purpose} needs {field}, none for frames {missing}")
  return np.stack([np.asarray(frames[int(i)]) for i in target])
