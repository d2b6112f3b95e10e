"""Command line: write a synthetic dataset and print the throughput.

python -m tokengs_jax.data.synthetic re10k --root data/synthetic_re10k --num-train 256 --num-test 32
python -m tokengs_jax.data.synthetic kubric --root data/synthetic_kubric --num-scenes 16
"""

from __future__ import annotations

import dataclasses
import time

import tyro

from tokengs_jax import process
from tokengs_jax.data.synthetic import generate


@dataclasses.dataclass(frozen=True)
class Re10k:
  """RE10K-format chunks of static rooms (pixelSplat layout)."""

  root: str
  num_train: int = 256
  num_test: int = 32
  height: int = 64
  width: int = 64
  frames: int = 32
  seed: int = 0
  workers: int = 1
  config: generate.Re10kLikeConfig = generate.Re10kLikeConfig()


@dataclasses.dataclass(frozen=True)
class Kubric:
  """Kubric-4D-layout tars of dynamic scenes."""

  root: str
  num_scenes: int = 16
  height: int = 64
  width: int = 64
  frames: int = 24
  num_cameras: int = 9
  seed: int = 0
  subset: str = "v0"
  workers: int = 1
  config: generate.KubricLikeConfig = generate.KubricLikeConfig()


def main(args: Re10k | Kubric) -> None:
  start, start_cpu = time.perf_counter(), time.process_time()
  if isinstance(args, Re10k):
    generate.generate_re10k_like(
      args.root,
      args.num_train,
      args.num_test,
      args.height,
      args.width,
      args.frames,
      args.seed,
      config=args.config,
      workers=args.workers,
    )
    count, images = args.num_train + args.num_test, (args.num_train + args.num_test) * args.frames
  else:
    generate.generate_kubric_like(
      args.root,
      args.num_scenes,
      args.height,
      args.width,
      args.frames,
      args.num_cameras,
      args.seed,
      subset=args.subset,
      config=args.config,
      workers=args.workers,
    )
    count, images = args.num_scenes, args.num_scenes * args.frames * args.num_cameras
  seconds, cpu = time.perf_counter() - start, time.process_time() - start_cpu
  # CPU time of this process (workers=1) is the figure that does not depend on other load.
  print(
    f"{count} scenes ({images} images) in {seconds:.1f} s wall, {cpu:.1f} s CPU: "
    f"{count / cpu:.2f} scenes/CPU-s, {images / cpu:.1f} images/CPU-s"
  )


if __name__ == "__main__":
  process.setup()
  main(tyro.extras.subcommand_cli_from_dict({"re10k": Re10k, "kubric": Kubric}))
