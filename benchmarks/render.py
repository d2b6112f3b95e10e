"""Renderer benchmark: forward and forward+backward time, peak memory, and runtime vs error.

    python benchmarks/render.py --out benchmarks/render.json            # full grid
    python benchmarks/render.py --sizes 65536 --images 256x256 --sweep  # one point + knob sweep
    python benchmarks/render.py --scene tokengs --sizes 65536 262144 --budget-check
    python benchmarks/render.py --sizes 65536 --images 256x256 --stages --repeats 5
    python benchmarks/render.py --sizes 65536 --images 256x256 --repeats 5   # headline figure
    python benchmarks/render.py --sizes 20000 --images 256x256 --scale-range 0.03 0.25 --repeats 0
        # default-budget error on the gsplat-like non-saturating scene (issue 11)

Scenes. "fine": N Gaussians uniform in [-1.6,1.6]x[-1.2,1.2]x[-1,1], scales uniform in
[smin, smax] (default 0.005-0.04), opacities 0.2-0.95. "tokengs": TokenGS-like, centres spread
over the view (10% margin) at depths log-uniform in [0.5, 4] (TokenGS rescales scenes to mean depth
~1), per-axis scales log-uniform in [smin, smax] with smax at the model's 0.075 cap, opacities
0.05-1. Both: random rotations and colours, one camera on the z axis with fx = fy = 0.9 W.
Errors are max |rgb| differences against the same scene rendered exactly (chunk 32, a budget that
holds every intersection). Times are the min over repeats of wall time (and process CPU time).
"""

from __future__ import annotations

import argparse
import json
import resource
import time

import jax
import jax.numpy as jnp
import numpy as np

from tokengs_jax import process
from tokengs_jax.gaussians import Gaussians
from tokengs_jax.splatting import RenderConfig, pipeline, rasterize, render


def make_scene(num, scale_range, seed=0):
  rng = np.random.default_rng(seed)
  return Gaussians(
    means=jnp.asarray(rng.uniform([-1.6, -1.2, -1.0], [1.6, 1.2, 1.0], (num, 3)), jnp.float32),
    opacities=jnp.asarray(rng.uniform(0.2, 0.95, num), jnp.float32),
    scales=jnp.asarray(rng.uniform(*scale_range, (num, 3)), jnp.float32),
    quats=jnp.asarray(rng.normal(size=(num, 4)), jnp.float32),
    colors=jnp.asarray(rng.uniform(0, 1, (num, 3)), jnp.float32),
  )


def make_tokengs_scene(num, scale_range, height, width, seed=0):
  rng = np.random.default_rng(seed)
  focal = 0.9 * width
  depth = np.exp(rng.uniform(np.log(0.5), np.log(4.0), num))
  u = rng.uniform(-0.1, 1.1, num) * width
  v = rng.uniform(-0.1, 1.1, num) * height
  # make_camera's camera sits 4 units before the world origin: camera z = world z + 4.
  means = np.stack(
    [(u - width / 2) / focal * depth, (v - height / 2) / focal * depth, depth - 4.0], -1
  )
  log_scales = rng.uniform(*np.log(scale_range), (num, 3))
  return Gaussians(
    means=jnp.asarray(means, jnp.float32),
    opacities=jnp.asarray(rng.uniform(0.05, 1.0, num), jnp.float32),
    scales=jnp.asarray(np.exp(log_scales), jnp.float32),
    quats=jnp.asarray(rng.normal(size=(num, 4)), jnp.float32),
    colors=jnp.asarray(rng.uniform(0, 1, (num, 3)), jnp.float32),
  )


def make_camera(height, width):
  w2c = np.eye(4, dtype=np.float32)
  w2c[2, 3] = 4.0
  intr = np.array([0.9 * width, 0.9 * width, width / 2, height / 2], np.float32)
  return jnp.asarray(w2c[None]), jnp.asarray(intr[None])


def best_time(fn, *args, repeats):
  """(min wall s, min process CPU s) over repeats, after one compiling call."""
  jax.block_until_ready(fn(*args))
  walls, cpus = [], []
  for _ in range(repeats):
    start, cpu_start = time.perf_counter(), time.process_time()
    jax.block_until_ready(fn(*args))
    walls.append(time.perf_counter() - start)
    cpus.append(time.process_time() - cpu_start)
  return min(walls), min(cpus)


def exact_config(num_intersections):
  """A budget that holds every intersection: the exact render the knobs are compared with."""
  return RenderConfig(max_intersections=max(4096, int(num_intersections)))


def measure(gaussians, height, width, config, repeats):
  w2c, intr = make_camera(height, width)
  forward = jax.jit(lambda g: render(g, w2c, intr, height=height, width=width, config=config))
  grad = jax.jit(
    jax.grad(lambda g: jnp.sum(render(g, w2c, intr, height=height, width=width, config=config).rgb))
  )
  out = forward(gaussians)
  row = dict(
    intersections=int(out.stats.num_intersections[0]),
    budget=int(out.stats.budget[0]),
    truncated=bool(out.stats.truncated[0]),
    overflow=bool(out.stats.overflow[0]),
    tile_chunks=int(out.stats.tile_chunks[0]),
  )
  if repeats:
    row["forward_s"], row["forward_cpu_s"] = best_time(forward, gaussians, repeats=repeats)
    row["forward_backward_s"], row["forward_backward_cpu_s"] = best_time(
      grad, gaussians, repeats=repeats
    )
    row["peak_rss_gib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
  return row, out.rgb


def stage_times(gaussians, height, width, config, repeats):
  """Times of each stage under jit: projection + binning (+ sub-tile split), compositing, and
  compositing fwd+bwd."""
  w2c, intr = make_camera(height, width)
  tiles = -(-height // config.tile_size) * -(-width // config.tile_size)
  ladder = config.budget_ladder(gaussians.num_gaussians, tiles)

  def project_and_bin(g):
    camera = jax.tree.map(
      lambda x: x[None],
      pipeline._project(
        g, w2c[0], intr[0], 0.025, 125.0, height=height, width=width, config=config
      ),
    )
    return camera._replace(
      bins=pipeline._bin(camera, height=height, width=width, config=config, ladder=ladder)
    )

  bin_one = jax.jit(project_and_bin)
  camera = bin_one(gaussians)
  tiling = rasterize.Tiling(
    height,
    width,
    config.subtile_size,
    -(-width // config.subtile_size),
    -(-height // config.subtile_size),
    1,
    config.chunk_size,
    config.tiles_per_step,
    config.max_alpha,
    config.alpha_threshold,
    config.transmittance_stop,
  )
  bins = jax.tree.map(lambda x: x[0], camera.bins)

  def composite(attrs):
    return rasterize.rasterize_tiles(
      attrs, bins.gaussian_ids, bins.tile_starts, bins.tile_ends, tiling, bins.shared_lists
    )

  attrs = camera.attrs[0]
  weights = jnp.asarray(np.random.default_rng(0).uniform(0, 1, (attrs.shape[-1] - 6,)), attrs.dtype)
  composite_grad = jax.jit(jax.grad(lambda a: jnp.sum(composite(a)[0] * weights)))
  for name, fn, arg in (
    ("project+bin", bin_one, gaussians),
    ("composite", jax.jit(composite), attrs),
    ("composite f+b", composite_grad, attrs),
  ):
    wall, cpu = best_time(fn, arg, repeats=repeats)
    print(f"{name:>14}: {wall:.3f} s wall, {cpu:.3f} s cpu", flush=True)


def parse_args() -> argparse.Namespace:
  parser = argparse.ArgumentParser(
    description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
  )
  parser.add_argument("--sizes", type=int, nargs="+", default=[4096, 16384, 65536, 262144])
  process.add_arguments(parser)
  parser.add_argument("--images", nargs="+", default=["256x256", "256x448"], help="HxW")
  parser.add_argument("--scene", choices=["fine", "tokengs"], default="fine")
  parser.add_argument(
    "--scale-range",
    type=float,
    nargs=2,
    default=None,
    help="default 0.005 0.04 (fine), 0.003 0.075 (tokengs)",
  )
  parser.add_argument("--repeats", type=int, default=3)
  parser.add_argument("--sweep", action="store_true", help="runtime vs error over the speed knobs")
  parser.add_argument(
    "--budget-check",
    action="store_true",
    help="error of the default budget only (no timing), for several scale ranges",
  )
  parser.add_argument("--stages", action="store_true", help="time each stage of the first point")
  parser.add_argument("--out", default="benchmarks/render.json")
  return parser.parse_args()


def knob_variants(sweep: bool) -> list[tuple[str, RenderConfig]]:
  """(name, config) of the default render and, with `sweep`, of each speed-knob setting."""
  default = RenderConfig()
  variants = [("default", default)]
  if sweep:
    variants += [(f"chunk={c}", RenderConfig(chunk_size=c)) for c in (16, 64)]
    variants += [(f"tiles/step={t}", RenderConfig(tiles_per_step=t)) for t in (64, 256)]
    variants += [(f"subtile={s}", RenderConfig(subtile_size=s)) for s in (4, 16)]
    variants += [("subtile=16 s32", RenderConfig(subtile_size=16, tiles_per_step=32))]
    variants += [
      (f"isect/gauss={b}", RenderConfig(intersections_per_gaussian=b)) for b in (32, 8, 4, 2)
    ]
    # 8-pixel tiles: fewer wasted pixel evaluations, ~3x the pairs (budget scaled to match)
    variants += [
      ("tile8 s64", RenderConfig(tile_size=8, tiles_per_step=64, intersections_per_gaussian=64))
    ]
    variants += [("gaussian-major", RenderConfig(pixel_major=False))]  # [S, P, K] blocks
    variants += [("rebin on ovfl", RenderConfig(rebin_on_overflow=True))]
    variants += [("bf16 inputs", default)]  # the default config on bfloat16 Gaussians
  return variants


def knob_results(gaussians, height, width, variants, repeats):
  """Yields (knob name, `measure` row, max |rgb| error against the exact render) per variant."""
  # the default render's intersection count sizes a budget that holds them all
  probe, _ = measure(gaussians, height, width, RenderConfig(), 0)
  _, exact_rgb = measure(gaussians, height, width, exact_config(probe["intersections"]), 0)
  for name, config in variants:
    scene = gaussians
    if name == "bf16 inputs":
      scene = jax.tree.map(lambda x: x.astype(jnp.bfloat16), gaussians)
    row, rgb = measure(scene, height, width, config, repeats)
    yield name, row, float(jnp.max(jnp.abs(rgb - exact_rgb)))


_TABLE_HEADER = (
  f"{'N':>7} {'image':>8} {'scales':>12} {'knobs':>14} {'fwd s':>6} {'cpu':>6} {'f+b s':>6} "
  f"{'cpu':>6} {'rss GiB':>7} {'isects':>8} {'budget':>8} {'trunc':>5} {'ovfl':>5} "
  f"{'chunks':>6} {'max err':>8}"
)


def print_row(row: dict) -> None:
  """One line of the table under _TABLE_HEADER (nan where a figure was not measured)."""
  timing = "".join(
    f"{row.get(k, float('nan')):>7.3f}"
    for k in ("forward_s", "forward_cpu_s", "forward_backward_s", "forward_backward_cpu_s")
  )
  scales = f"{row['scales'][0]:g}-{row['scales'][1]:g}"
  rss = row.get("peak_rss_gib", float("nan"))
  print(
    f"{row['num']:>7} {row['image']:>8} {scales:>12} {row['knobs']:>14}{timing} {rss:>7.2f} "
    f"{row['intersections']:>8} {row['budget']:>8} {row['truncated']!s:>5} "
    f"{row['overflow']!s:>5} {row['tile_chunks']:>6} {row['max_error']:>8.1e}",
    flush=True,
  )


def main():
  args = parse_args()
  process.setup(host_memory=args.host_memory)
  if args.stages:
    height, width = map(int, args.images[0].split("x"))
    scene = make_scene(args.sizes[0], tuple(args.scale_range or (0.005, 0.04)))
    stage_times(scene, height, width, RenderConfig(), args.repeats)
    return
  default_scales = (0.005, 0.04) if args.scene == "fine" else (0.003, 0.075)
  scale_ranges = [tuple(args.scale_range or default_scales)]
  if args.budget_check:
    scale_ranges = [default_scales, (0.01, 0.075), (0.0276, 0.0276), (0.075, 0.075)]
  variants = knob_variants(args.sweep)
  repeats = 0 if args.budget_check else args.repeats

  rows = []
  print(_TABLE_HEADER)
  for image in args.images:
    height, width = map(int, image.split("x"))
    for num in args.sizes:
      for scale_range in scale_ranges:
        if args.scene == "fine":
          gaussians = make_scene(num, scale_range)
        else:
          gaussians = make_tokengs_scene(num, scale_range, height, width)
        for name, row, error in knob_results(gaussians, height, width, variants, repeats):
          row.update(
            num=num,
            image=image,
            scales=list(scale_range),
            knobs=name,
            scene=args.scene,
            max_error=error,
          )
          rows.append(row)
          print_row(row)
  with open(args.out, "w") as f:
    json.dump(dict(device=str(jax.devices()[0]), scene=args.scene, rows=rows), f, indent=1)


if __name__ == "__main__":
  main()
