"""Input-pipeline throughput (batches/s) on generated RE10K-like chunks.

    python benchmarks/data.py --scenes 16 --frames 40 --batch-size 8 --batches 20 --workers 0 2

Writes chunks of 360x640 JPEG frames (the RE10K storage size) to a temporary directory, then times
`InputPipeline` producing RE10K-preset batches (2 context + 4 target views at 256x256, so 6 JPEG
decodes + LANCZOS resizes per example). The first batch (worker start-up) is not timed.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np

from tokengs_jax import process
from tokengs_jax.data import (
  BoundedSamplerConfig,
  ChunkedSceneSource,
  DATASET_PRESETS,
  InputPipeline,
  write_chunk,
)


def _write_scenes(root: Path, scenes: int, frames: int, per_chunk: int = 4) -> None:
  rng = np.random.default_rng(0)
  v, u = np.mgrid[0:360, 0:640]
  for start in range(0, scenes, per_chunk):
    chunk = []
    for s in range(start, min(start + per_chunk, scenes)):
      c2w = np.tile(np.eye(4), (frames, 1, 1))
      c2w[:, 2, 3] = np.linspace(0, 2, frames)
      images = np.empty((frames, 360, 640, 3), np.uint8)
      for f in range(
        frames
      ):  # smooth texture + noise: JPEG sizes like real photos' order of magnitude
        phase = rng.uniform(0, 6, 3)
        base = 127 + 100 * np.sin(u[..., None] / 37.0 + v[..., None] / 53.0 + phase)
        images[f] = np.clip(base + rng.normal(0, 12, base.shape), 0, 255)
      chunk.append(
        {
          "key": f"scene{s:04d}",
          "c2w": c2w,
          "intrinsics": np.tile([500.0, 500.0, 320.0, 180.0], (frames, 1)),
          "images": images,
        }
      )
    write_chunk(root / f"{start // per_chunk:06d}.torch", chunk)


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--scenes", type=int, default=16)
  parser.add_argument("--frames", type=int, default=40)
  parser.add_argument("--batch-size", type=int, default=8)
  parser.add_argument("--batches", type=int, default=20)
  parser.add_argument("--workers", type=int, nargs="+", default=[0, 2])
  args = parser.parse_args()
  process.setup()
  with tempfile.TemporaryDirectory() as tmp:
    root = Path(tmp)
    start = time.perf_counter()
    _write_scenes(root, args.scenes, args.frames)
    print(
      f"wrote {args.scenes} scenes x {args.frames} frames in {time.perf_counter() - start:.1f} s"
    )
    source = ChunkedSceneSource(root)
    sampler = BoundedSamplerConfig(2, 4, 10, args.frames - 1, 0, 0, 10, args.frames - 1)
    config = dataclasses.replace(DATASET_PRESETS["re10k"], sampler=sampler)  # scenes are short
    for workers in args.workers:
      iterator = iter(
        InputPipeline(
          source,
          config,
          batch_size=args.batch_size,
          seed=0,
          shard_index=0,
          shard_count=1,
          num_workers=workers,
        )
      )
      next(iterator)
      start = time.perf_counter()
      for _ in range(args.batches):
        batch = next(iterator)
      elapsed = time.perf_counter() - start
      print(
        f"workers={workers} batch={args.batch_size} images={batch['context_images'].shape[2:4]}: "
        f"{args.batches / elapsed:.2f} batches/s ({args.batches * args.batch_size / elapsed:.1f} examples/s)"
      )


if __name__ == "__main__":
  main()
