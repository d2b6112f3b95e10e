"""Input-pipeline throughput (batches/s) on generated RE10K-like chunks.

    python benchmarks/data.py --scenes 16 --frames 40 --batch-size 8 --batches 20 --workers 0 2

Writes chunks of 360x640 JPEG frames (the RE10K storage size) to a temporary directory, then times
`InputPipeline` producing RE10K-preset batches (2 context + 4 target views at 256x256, so 6 JPEG
decodes + LANCZOS resizes per example). The first batch (worker start-up) is not timed.

Resident memory per pipeline, sampled every 0.1 s while it runs: the main process's peak and final
`VmRSS` (`/proc/self/status`), its `ru_maxrss` so far (the process's high-water mark, all pipelines
before included), and the peak of its workers' summed `VmRSS` (shared pages counted in each). The
host memory policy (`--host-memory`, as `process.setup` takes it; "auto" retains on XLA:CPU) is the
main process's: grain starts its workers with `spawn`, so they run with glibc's defaults.
A long run for the policy's A/B:

    python benchmarks/data.py --batches 300 --workers 0 2 --host-memory retain
    python benchmarks/data.py --batches 300 --workers 0 2 --host-memory default
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import resource
import tempfile
import threading
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


def _rss_mb(pid: int | str = "self") -> float:
  """`VmRSS` of a process in MB (0 when it has ended)."""
  try:
    with open(f"/proc/{pid}/status") as status:
      for line in status:
        if line.startswith("VmRSS:"):
          return int(line.split()[1]) / 1024
  except OSError:
    pass
  return 0.0


def _children() -> list[int]:
  """This process's child processes (the pipeline's workers)."""
  pids = []
  for task in os.listdir("/proc/self/task"):
    try:
      with open(f"/proc/self/task/{task}/children") as listed:
        pids += [int(pid) for pid in listed.read().split()]
    except OSError:
      pass
  return pids


class _RssSampler:
  """Samples this process's and its children's resident memory in a thread while it is entered:
  the peak between samples is what a long run would have to hold."""

  def __init__(self, period: float = 0.1):
    self.period, self.peak, self.children_peak = period, 0.0, 0.0
    self._stop = threading.Event()
    self._thread = threading.Thread(target=self._run, name="rss", daemon=True)

  def _sample(self) -> None:
    self.peak = max(self.peak, _rss_mb())
    self.children_peak = max(self.children_peak, sum(_rss_mb(pid) for pid in _children()))

  def _run(self) -> None:
    while not self._stop.wait(self.period):
      self._sample()

  def __enter__(self) -> "_RssSampler":
    self._sample()
    self._thread.start()
    return self

  def __exit__(self, *exc) -> None:
    self._stop.set()
    self._thread.join()
    self._sample()
    self.final = _rss_mb()
    self.max_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kB on Linux


def _time_pipeline(source, config, workers: int, batch_size: int, batches: int) -> None:
  pipeline = InputPipeline(
    source, config, batch_size=batch_size, seed=0, shard_index=0, shard_count=1, num_workers=workers
  )
  with _RssSampler() as rss:
    iterator = iter(pipeline)
    next(iterator)
    start = time.perf_counter()
    for _ in range(batches):
      batch = next(iterator)
    elapsed = time.perf_counter() - start
    del iterator, batch  # the workers end: the final figure is what the main process keeps
  print(
    f"workers={workers} batch={batch_size}: {batches / elapsed:.2f} batches/s "
    f"({batches * batch_size / elapsed:.1f} examples/s); RSS MB: main peak {rss.peak:.0f}, "
    f"final {rss.final:.0f}, ru_maxrss {rss.max_rss:.0f}; workers' peak {rss.children_peak:.0f}",
    flush=True,
  )


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--scenes", type=int, default=16)
  parser.add_argument("--frames", type=int, default=40)
  parser.add_argument("--batch-size", type=int, default=8)
  parser.add_argument("--batches", type=int, default=20)
  parser.add_argument("--workers", type=int, nargs="+", default=[0, 2])
  process.add_arguments(parser)
  args = parser.parse_args()
  print(process.setup(host_memory=args.host_memory), flush=True)
  with tempfile.TemporaryDirectory() as tmp:
    root = Path(tmp)
    start = time.perf_counter()
    _write_scenes(root, args.scenes, args.frames)
    print(
      f"wrote {args.scenes} scenes x {args.frames} frames in {time.perf_counter() - start:.1f} s "
      f"(RSS {_rss_mb():.0f} MB)",
      flush=True,
    )
    source = ChunkedSceneSource(root)
    sampler = BoundedSamplerConfig(2, 4, 10, args.frames - 1, 0, 0, 10, args.frames - 1)
    config = dataclasses.replace(DATASET_PRESETS["re10k"], sampler=sampler)  # scenes are short
    for workers in args.workers:
      _time_pipeline(source, config, workers, args.batch_size, args.batches)


if __name__ == "__main__":
  main()
