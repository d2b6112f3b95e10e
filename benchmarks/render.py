"""Renderer benchmark: forward and forward+backward time, peak memory, and runtime vs error.

    python benchmarks/render.py --out benchmarks/render.json            # full grid
    python benchmarks/render.py --sizes 65536 --images 256x256 --sweep  # one point + knob sweep

Scene ("fine"): N Gaussians uniform in [-1.6,1.6]x[-1.2,1.2]x[-1,1], scales uniform in
[smin, smax] (default 0.005-0.04), opacities 0.2-0.95, random rotations and colours, one camera 4
units away on the z axis with fx = fy = 0.9 W. Errors are max |rgb| differences against the same
scene rendered with an exact configuration (chunk 32, ample budget).
"""

from __future__ import annotations

import argparse
import json
import resource
import time

import jax
import jax.numpy as jnp
import numpy as np

from tokengs_jax.gaussians import Gaussians
from tokengs_jax.splatting import RenderConfig, render


def make_scene(num, scale_range, seed=0):
  rng = np.random.default_rng(seed)
  return Gaussians(
      means=jnp.asarray(rng.uniform([-1.6, -1.2, -1.0], [1.6, 1.2, 1.0], (num, 3)), jnp.float32),
      opacities=jnp.asarray(rng.uniform(0.2, 0.95, num), jnp.float32),
      scales=jnp.asarray(rng.uniform(*scale_range, (num, 3)), jnp.float32),
      quats=jnp.asarray(rng.normal(size=(num, 4)), jnp.float32),
      colors=jnp.asarray(rng.uniform(0, 1, (num, 3)), jnp.float32))


def make_camera(height, width):
  w2c = np.eye(4, dtype=np.float32)
  w2c[2, 3] = 4.0
  intr = np.array([0.9 * width, 0.9 * width, width / 2, height / 2], np.float32)
  return jnp.asarray(w2c[None]), jnp.asarray(intr[None])


def best_time(fn, *args, repeats):
  jax.block_until_ready(fn(*args))  # compile
  times = []
  for _ in range(repeats):
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    times.append(time.perf_counter() - start)
  return min(times)


def measure(gaussians, height, width, config, repeats):
  w2c, intr = make_camera(height, width)
  forward = jax.jit(lambda g: render(g, w2c, intr, height=height, width=width, config=config))
  grad = jax.jit(jax.grad(
      lambda g: jnp.sum(render(g, w2c, intr, height=height, width=width, config=config).rgb)))
  out = forward(gaussians)
  row = dict(
      forward_s=best_time(forward, gaussians, repeats=repeats),
      forward_backward_s=best_time(grad, gaussians, repeats=repeats),
      peak_rss_gib=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
      intersections=int(out.stats.num_intersections[0]), budget=int(out.stats.budget[0]),
      overflow=bool(out.stats.overflow[0]), tile_chunks=int(out.stats.tile_chunks[0]))
  return row, out.rgb


def main():
  parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--sizes", type=int, nargs="+", default=[4096, 16384, 65536, 262144])
  parser.add_argument("--images", nargs="+", default=["256x256", "256x448"], help="HxW")
  parser.add_argument("--scale-range", type=float, nargs=2, default=[0.005, 0.04])
  parser.add_argument("--repeats", type=int, default=3)
  parser.add_argument("--sweep", action="store_true", help="runtime vs error over the speed knobs")
  parser.add_argument("--out", default="benchmarks/render.json")
  args = parser.parse_args()

  rows = []
  print(f"{'N':>7} {'image':>8} {'knobs':>22} {'fwd s':>7} {'fwd+bwd s':>9} {'rss GiB':>7} "
        f"{'isects':>8} {'budget':>8} {'chunks':>7} {'max err':>8}")
  for image in args.images:
    height, width = map(int, image.split("x"))
    for num in args.sizes:
      gaussians = make_scene(num, args.scale_range)
      exact = RenderConfig()
      variants = [("default", exact)]
      if args.sweep:
        variants += [(f"chunk={c}", RenderConfig(chunk_size=c)) for c in (16, 64)]
        variants += [(f"tiles/step={t}", RenderConfig(tiles_per_step=t)) for t in (32, 128)]
        variants += [(f"isect/gauss={b}", RenderConfig(intersections_per_gaussian=b)) for b in (4, 2, 1)]
        variants += [("bf16 inputs", exact)]
      reference = None
      for name, config in variants:
        scene = gaussians
        if name == "bf16 inputs":
          scene = jax.tree.map(lambda x: x.astype(jnp.bfloat16), gaussians)
        row, rgb = measure(scene, height, width, config, args.repeats)
        if reference is None:
          reference = rgb
        row.update(num=num, image=image, knobs=name,
                   max_error=float(jnp.max(jnp.abs(rgb - reference))))
        rows.append(row)
        print(f"{num:>7} {image:>8} {name:>22} {row['forward_s']:>7.3f} {row['forward_backward_s']:>9.3f} "
              f"{row['peak_rss_gib']:>7.2f} {row['intersections']:>8} {row['budget']:>8} "
              f"{row['tile_chunks']:>7} {row['max_error']:>8.1e}", flush=True)
  with open(args.out, "w") as f:
    json.dump(dict(device=str(jax.devices()[0]), scale_range=args.scale_range, rows=rows), f, indent=1)


if __name__ == "__main__":
  main()
