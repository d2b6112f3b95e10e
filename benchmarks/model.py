"""TokenGS network speed: reconstruct latency and a train-step-shaped forward+backward.

    python benchmarks/model.py      # tiny:8, dl3dv_2view:1, dl3dv_2view:1:128x224:1024
    python benchmarks/model.py --case tiny:8 --repeats 5 --out /tmp/model_bench.json

Each case is PRESET:BATCH[:HxW[:TOKENS]]; views come from the preset (--views overrides),
resolution and Gaussian-token count from the preset unless given.
For each case it times, after compilation (min over --repeats runs):
  encode      images + Plücker -> shared keys/values (the encoder transformer)
  decode      cached keys/values -> Gaussians (the decoder transformer + head)
  reconstruct the whole `reconstruct` ([0, 1] images and cameras -> Gaussians)
  train step  value_and_grad of a loss on the flat Gaussians w.r.t. all parameters (the network
              part of a training step; the renderer is benchmarked separately). A stage whose
              compiled program needs more than --max-temp-gb of temporary memory (XLA's
              memory analysis) is reported and skipped.
FLOPs are XLA's cost analysis of the forward program; the train step is counted as 3x forward
("model FLOPs": rematerialised recomputation is not credited). GFLOP/s are compared with a
measured float32 matmul peak (a square matmul of the model's width-sized operands).
"""

from __future__ import annotations

import argparse
import functools
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

from tokengs_jax.camera import plucker_rays
from tokengs_jax.model import (
  count_params,
  decode,
  encode,
  init_params,
  normalize_images,
  preset,
  reconstruct,
)


def compile_fn(fn, *args):
  """Ahead-of-time compiled program of a jitted function (so no timed run pays compilation)."""
  return fn.lower(*args).compile()


def best_time(compiled, *args, repeats: int) -> float:
  """Seconds of the fastest of `repeats` runs of a compiled program."""
  times = []
  for _ in range(repeats):
    start = time.perf_counter()
    jax.block_until_ready(compiled(*args))
    times.append(time.perf_counter() - start)
  return min(times)


def flop_count(compiled) -> float:
  """XLA's FLOP count of a compiled program."""
  analysis = compiled.cost_analysis()
  if isinstance(analysis, list):  # older jax returned one dict per program
    analysis = analysis[0]
  return float(analysis["flops"])


def throughput(seconds: float, flops: float, peak_gflops: float) -> dict:
  gflops = flops / seconds / 1e9
  return {"ms": seconds * 1e3, "gflop": flops / 1e9, "gflops_per_s": gflops,
          "fraction_of_peak": gflops / peak_gflops}


def matmul_peak(size: int, repeats: int) -> float:
  """Measured float32 matmul GFLOP/s for [size, size] @ [size, size]."""
  a = jax.random.normal(jax.random.key(0), (size, size), jnp.float32)
  b = jax.random.normal(jax.random.key(1), (size, size), jnp.float32)
  seconds = best_time(compile_fn(jax.jit(jnp.matmul), a, b), a, b, repeats=repeats)
  return 2 * size ** 3 / seconds / 1e9


def scene_inputs(batch: int, views: int, height: int, width: int):
  key_img, key_pos = jax.random.split(jax.random.key(0))
  images = jax.random.uniform(key_img, (batch, views, height, width, 3))
  c2w = jnp.broadcast_to(jnp.eye(4), (batch, views, 4, 4))
  c2w = c2w.at[..., :3, 3].set(jax.random.normal(key_pos, (batch, views, 3)) * 0.3)
  intrinsics = jnp.broadcast_to(jnp.array([width * 0.9, width * 0.9, width / 2, height / 2]),
                                (batch, views, 4))
  return images, c2w, intrinsics


def run_case(case: str, views: int | None, repeats: int, dtype: str, peak: float,
             max_temp_gb: float) -> dict:
  name, batch, *rest = case.split(":")
  batch = int(batch)
  config = preset(name, dtype=dtype)
  size = tuple(int(n) for n in rest[0].split("x")) if rest else None
  if len(rest) > 1:
    config = config.replace(num_gs_tokens=int(rest[1]))
  views = views or config.num_input_views
  height, width = size or config.image_size
  params = init_params(jax.random.key(0), config)
  images, c2w, intrinsics = scene_inputs(batch, views, height, width)
  plucker = plucker_rays(c2w, intrinsics, height, width)
  normalised = normalize_images(images)

  enc = jax.jit(functools.partial(encode, config=config))
  dec = jax.jit(functools.partial(decode, config=config))
  rec = jax.jit(functools.partial(reconstruct, config=config))

  def loss(p):
    flat = reconstruct(p, images, c2w, intrinsics, config=config).to_flat()
    return jnp.mean(jnp.square(flat - 0.5))

  train = jax.jit(jax.value_and_grad(loss))
  encoded = jax.eval_shape(enc, params, normalised, plucker)  # decode is compiled for its shape
  encoded = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), encoded)
  row = {"preset": name, "batch": batch, "views": views, "height": height, "width": width,
         "dtype": dtype, "params_m": count_params(config) / 1e6,
         "gaussians": config.num_gaussians,
         "image_tokens": views * height * width // config.patch_size ** 2}
  stages = (("encode", enc, (params, normalised, plucker)),
            ("decode", dec, (params, encoded)),
            ("reconstruct", rec, (params, images, c2w, intrinsics)))
  forward_flops = {}
  for stage, fn, args in (*stages, ("train_step", train, (params,))):
    compiled = compile_fn(fn, *args)
    temp_gb = compiled.memory_analysis().temp_size_in_bytes / 1e9
    # the train step is credited with model FLOPs: 3x the forward
    flops = 3 * forward_flops["reconstruct"] if stage == "train_step" else flop_count(compiled)
    forward_flops[stage] = flops
    if temp_gb > max_temp_gb:
      row[stage] = {"skipped": f"needs {temp_gb:.1f} GB of temporaries", "gflop": flops / 1e9}
      continue
    seconds = best_time(compiled, *args, repeats=repeats if stage != "train_step" else
                        max(1, repeats // 2))
    row[stage] = {**throughput(seconds, flops, peak), "temp_gb": temp_gb}
  return row


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--case", action="append", help="PRESET:BATCH[:HxW[:TOKENS]] (repeatable)")
  parser.add_argument("--views", type=int, default=None)
  parser.add_argument("--max-temp-gb", type=float, default=14.0)
  parser.add_argument("--repeats", type=int, default=3)
  parser.add_argument("--dtype", default="float32", choices=["float32", "bfloat16"])
  parser.add_argument("--peak-size", type=int, default=2048)
  parser.add_argument("--out", default=None, help="write the results as JSON here")
  args = parser.parse_args()
  cases = args.case or ["tiny:8", "dl3dv_2view:1", "dl3dv_2view:1:128x224:1024"]

  peak = matmul_peak(args.peak_size, args.repeats)
  print(f"device: {jax.devices()[0].device_kind}  matmul peak ({args.peak_size}^3 f32): "
        f"{peak:.1f} GFLOP/s")
  results = {"device": jax.devices()[0].device_kind, "matmul_peak_gflops": peak, "cases": []}
  for case in cases:
    row = run_case(case, args.views, args.repeats, args.dtype, peak, args.max_temp_gb)
    results["cases"].append(row)
    print(f"\n{row['preset']}  B={row['batch']} V={row['views']} {row['height']}x{row['width']} "
          f"{row['dtype']}  {row['params_m']:.1f} M params, {row['image_tokens']} image tokens "
          f"-> {row['gaussians']} Gaussians")
    print(f"  {'stage':<12}{'ms':>10}{'GFLOP':>10}{'GFLOP/s':>10}{'of peak':>9}{'temp GB':>9}")
    for stage in ("encode", "decode", "reconstruct", "train_step"):
      s = row[stage]
      if "skipped" in s:
        print(f"  {stage:<12}{'-':>10}{s['gflop']:>10.2f}  skipped: {s['skipped']}")
        continue
      print(f"  {stage:<12}{s['ms']:>10.1f}{s['gflop']:>10.2f}{s['gflops_per_s']:>10.1f}"
            f"{s['fraction_of_peak']:>9.0%}{s['temp_gb']:>9.2f}")
  if args.out:
    with open(args.out, "w") as f:
      json.dump(results, f, indent=1)


if __name__ == "__main__":
  np.set_printoptions(precision=3)
  main()
