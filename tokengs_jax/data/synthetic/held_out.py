"""Writers of the held-out static test families, in the layout the real loaders read.

- `generate_galleries`: polygonal galleries, orbiting camera (`scenes.GalleryConfig`; a validation
  family: the synthetic default's levers were chosen looking at it).
- `generate_courtyards`: the frozen test family (`courtyards`: open courtyards, held-out
  photographs, a sideways tracking camera; a fixed seed).

Both write `<root>/test/NNNNNN.torch` chunks (+ `.depth.npz` true depths) + `index.json` and
`<root>/eval_index.json`, whose targets are never input frames (`gallery_views`).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import pathlib

import numpy as np

from tokengs_jax.data.synthetic import cameras, courtyards, scenes
from tokengs_jax.data.synthetic.generate import RE10K_FPS, write_chunked_split
from tokengs_jax.data.synthetic.raytrace import render

# rng streams of the test families: disjoint from each other and from the rooms' train / test ids
_HELD_OUT_STREAMS = {"galleries": 7, "courtyards": 11}


@dataclasses.dataclass(frozen=True)
class GalleryDatasetConfig:
  """Options of `generate_galleries` beyond the sizes (and of `generate_courtyards`, whose
  `scene` is a `courtyards.CourtyardConfig`)."""

  fov_x_degrees: tuple[float, float] = (45.0, 95.0)
  supersample: int = 2
  jpeg_quality: int = 95
  scenes_per_chunk: int = 16
  num_targets: int = 3  # per scene in `eval_index.json`, evenly inside the context span
  scene: scenes.GalleryConfig | courtyards.CourtyardConfig = scenes.GalleryConfig()


def _render_held_out_scene(
  family: str,
  seed: int,
  index: int,
  height: int,
  width: int,
  frames: int,
  config: GalleryDatasetConfig,
) -> dict:
  """One scene of a held-out test family (`galleries` or `courtyards`), with the fields of
  `render_re10k_like_scene`."""
  rng = np.random.default_rng([seed, _HELD_OUT_STREAMS[family], index])
  sample = {"galleries": scenes.sample_gallery_scene, "courtyards": courtyards.sample_courtyard}
  scene, c2w = sample[family](rng, frames, config.scene)
  fov_x = np.deg2rad(rng.uniform(*config.fov_x_degrees))
  intrinsics = cameras.pinhole_intrinsics(height, width, fov_x)
  outputs = [render(scene, pose, intrinsics, height, width, config.supersample) for pose in c2w]
  return {
    "key": f"{ {'galleries': 'gallery', 'courtyards': 'courtyard'}[family] }{seed}_{index:06d}",
    "url": "",
    "timestamps": np.arange(frames, dtype=np.int64) * (1_000_000 // RE10K_FPS),
    "c2w": c2w.astype(np.float32),
    "intrinsics": np.broadcast_to(intrinsics, (frames, 4)).astype(np.float32),
    "images": np.stack([np.round(o.rgb * 255.0).astype(np.uint8) for o in outputs]),
    "depths": np.stack([o.depth for o in outputs]),
  }


def render_gallery_scene(
  seed: int,
  index: int,
  height: int,
  width: int,
  frames: int,
  config: GalleryDatasetConfig = GalleryDatasetConfig(),
) -> dict:
  """One gallery scene, with the fields of `render_re10k_like_scene`."""
  return _render_held_out_scene("galleries", seed, index, height, width, frames, config)


def gallery_views(frames: int, num_targets: int) -> dict:
  """Evaluation views of a gallery scene: inputs at the first and last frame, targets evenly
  spaced strictly between them (never an input frame, so copying an input is never exact)."""
  if frames - 2 < num_targets:
    raise ValueError(f"{frames} frames cannot hold {num_targets} targets between two inputs")
  targets = np.linspace(0, frames - 1, num_targets + 2)[1:-1].round().astype(int)
  return {"context": [0, frames - 1], "target": [int(t) for t in targets]}


def _generate_held_out(
  family: str,
  root: str | os.PathLike,
  num_scenes: int,
  height: int,
  width: int,
  frames: int,
  seed: int,
  config: GalleryDatasetConfig,
  workers: int,
) -> dict:
  """Writes a test family: `<root>/test/NNNNNN.torch` (+ `.depth.npz`) + `<root>/test/index.json`
  (the pixelSplat layout, as `generate_re10k_like`) and `<root>/eval_index.json` (scene key ->
  {"context", "target"}, the pixelSplat / MVSplat evaluation-index format; `gallery_views`).

  Returns the evaluation index.
  """
  index = write_chunked_split(
    pathlib.Path(root) / "test",
    num_scenes,
    functools.partial(
      _render_held_out_scene, family, seed, height=height, width=width, frames=frames, config=config
    ),
    scenes_per_chunk=config.scenes_per_chunk,
    jpeg_quality=config.jpeg_quality,
    workers=workers,
  )
  views = gallery_views(frames, config.num_targets)
  evaluation = {key: views for key in index}
  (pathlib.Path(root) / "eval_index.json").write_text(json.dumps(evaluation, indent=1))
  return evaluation


def generate_galleries(
  root: str | os.PathLike,
  num_scenes: int = 24,
  height: int = 64,
  width: int = 64,
  frames: int = 13,
  seed: int = 0,
  *,
  config: GalleryDatasetConfig = GalleryDatasetConfig(),
  workers: int = 1,
) -> dict:
  """Writes the gallery test set (`_generate_held_out`); returns its evaluation index."""
  return _generate_held_out(
    "galleries", root, num_scenes, height, width, frames, seed, config, workers
  )


COURTYARD_DATASET = GalleryDatasetConfig(
  fov_x_degrees=(50.0, 90.0), scene=courtyards.CourtyardConfig()
)


def generate_courtyards(
  root: str | os.PathLike,
  num_scenes: int = 24,
  height: int = 64,
  width: int = 64,
  frames: int = 13,
  *,
  config: GalleryDatasetConfig = COURTYARD_DATASET,
  workers: int = 1,
) -> dict:
  """Writes the frozen courtyard test set (`courtyards`; seed `courtyards.FROZEN_SEED`, whatever
  the experiment's) in the layout of `_generate_held_out`; returns its evaluation index."""
  return _generate_held_out(
    "courtyards", root, num_scenes, height, width, frames, courtyards.FROZEN_SEED, config, workers
  )
