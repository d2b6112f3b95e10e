"""TokenGS network speed: reconstruct latency and a train-step-shaped forward+backward.

    python benchmarks/model.py      # tiny:8, dl3dv_2view:1, dl3dv_2view:1:128x224:1024
    python benchmarks/model.py --case tiny:8 --repeats 5 --out /tmp/model_bench.json
    python benchmarks/model.py --case tiny:8 --compare-plain-attention   # A/B vs the old attention
    python benchmarks/model.py --case small:1 --case mid:1 --torch --repeats 7   # vs PyTorch
    python benchmarks/model.py --case small:1 --variant tiled --variant bf16dot   # f32 vs bf16 dots

Each case is PRESET:BATCH[:HxW[:TOKENS]]; views come from the preset (--views overrides),
resolution and Gaussian-token count from the preset unless given. PRESET is a model preset or
one of BENCHMARK_CONFIGS ("small", "mid": the two sizes of the PyTorch comparison in issue 11).
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
float32 matmul peak (--peak-size square matmul) measured inside the same timing rounds: this
machine is shared, so every round times the matmuls (5 times) and then each stage, and each
figure is the minimum over rounds (train steps take part in the first max(1, repeats // 2) rounds).
The bf16 x bf16 -> f32 matmul peak is measured in the same rounds.
Each --variant compiles every stage once and is timed in the same rounds (interleaved A/B):
  tiled    the default model (float32, tiled attention)
  plain    the plain attention that materialises all logits (--compare-plain-attention)
  bf16dot  ModelConfig.matmul_dtype="bfloat16": bf16-operand, float32-result matmuls
Every variant after the first also reports its accuracy against the first: max |difference| of
the reconstructed Gaussians and the PSNR between the two Gaussian sets' renders (`render_exact`,
the first scene's first input camera).
--torch also times `benchmarks/torch_reference.py` (our own PyTorch forward of the same
architecture and weights, not the official code; `pip install torch`) against the network
alone (`predict_gaussians`, stage "network") in the same rounds, after checking that both give
the same Gaussians.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import json
import time
from unittest import mock

import jax
import jax.numpy as jnp
import numpy as np

from tokengs_jax import process
from tokengs_jax.camera import plucker_rays
from tokengs_jax.metrics import psnr
from tokengs_jax.model import decoder as model_decoder
from tokengs_jax.model import layers as model_layers
from tokengs_jax.model import matmul as model_matmul
from tokengs_jax.model import (
  ModelConfig,
  count_params,
  decode,
  encode,
  init_params,
  normalize_images,
  predict_gaussians,
  preset,
  reconstruct,
)
from tokengs_jax.splatting import render_exact

# Variant -> the ModelConfig fields it changes ("plain" also swaps the attention, see below).
VARIANTS = {"tiled": {}, "plain": {}, "bf16dot": {"matmul_dtype": "bfloat16"}}

# The two sizes of issue 11's PyTorch comparison (2 views; head_dim 64 for "small", whose head
# count the issue does not give).
BENCHMARK_CONFIGS = {
  "small": dict(
    enc_embed_dim=256,
    enc_num_heads=4,
    enc_depth=2,
    dec_depth=4,
    num_gs_tokens=256,
    image_size=(128, 128),
    num_input_views=2,
  ),
  "mid": dict(
    enc_embed_dim=512,
    enc_num_heads=8,
    enc_depth=6,
    dec_depth=6,
    num_gs_tokens=1024,
    image_size=(256, 256),
    num_input_views=2,
  ),
}


def case_config(name: str, dtype: str):
  """A model preset, or a BENCHMARK_CONFIGS entry (on the tiny preset's patch sizes)."""
  if name in BENCHMARK_CONFIGS:
    return preset("tiny", dtype=dtype, **BENCHMARK_CONFIGS[name])
  return preset(name, dtype=dtype)


def compile_fn(fn, *args):
  """Ahead-of-time compiled program of a jitted function (so no timed run pays compilation)."""
  return fn.lower(*args).compile()


def timed(compiled, *args) -> np.ndarray:
  """[wall seconds, process CPU seconds] of one run of a compiled program.

  On a shared machine the CPU time (all threads) is the steadier figure: it does not count the
  time the process waits for a core. On an idle machine wall = CPU / threads kept busy.
  """
  start, start_cpu = time.perf_counter(), time.process_time()
  jax.block_until_ready(compiled(*args))
  return np.array([time.perf_counter() - start, time.process_time() - start_cpu])


def flop_count(program) -> float:
  """XLA's FLOP count of a lowered or compiled program."""
  analysis = program.cost_analysis()
  if isinstance(analysis, list):  # older jax returned one dict per program
    analysis = analysis[0]
  return float(analysis["flops"])


def throughput(seconds: float, flops: float, peak_gflops: float) -> dict:
  gflops = flops / seconds / 1e9
  return {
    "ms": seconds * 1e3,
    "gflop": flops / 1e9,
    "gflops_per_s": gflops,
    "fraction_of_peak": gflops / peak_gflops,
  }


def matmul_program(size: int, dtype=jnp.float32):
  """A compiled [size, size] @ [size, size] on `dtype` operands with a float32 result, and its
  operands."""
  a = jax.random.normal(jax.random.key(0), (size, size), dtype)
  b = jax.random.normal(jax.random.key(1), (size, size), dtype)
  product = functools.partial(jnp.matmul, preferred_element_type=jnp.float32)
  return compile_fn(jax.jit(product), a, b), (a, b)


def plain_attention(queries, keys, values, mask=None, matmul_dtype=None):
  """The attention before tiling: all [B, H, Nq, Nk] logits at once, autodiff backward."""
  operand_dtype = queries.dtype if matmul_dtype is None else matmul_dtype
  logits = model_matmul.einsum("bhqd,bhkd->bhqk", queries, keys, operand_dtype)
  logits = logits * queries.shape[-1] ** -0.5
  if mask is not None:
    logits = jnp.where(mask, logits, -jnp.inf)
  weights = jax.nn.softmax(logits, axis=-1)
  return model_matmul.einsum("bhqk,bhkd->bhqd", weights, values, operand_dtype).astype(values.dtype)


@contextlib.contextmanager
def attention_variant(name: str):
  """Traces the model with `plain_attention` for variant "plain", with the tiled `attend` else."""
  if name != "plain":
    yield
    return
  with (
    mock.patch.object(model_layers, "attend", plain_attention),
    mock.patch.object(model_decoder, "attend", plain_attention),
  ):
    yield


def scene_inputs(batch: int, views: int, height: int, width: int):
  key_img, key_pos = jax.random.split(jax.random.key(0))
  images = jax.random.uniform(key_img, (batch, views, height, width, 3))
  c2w = jnp.broadcast_to(jnp.eye(4), (batch, views, 4, 4))
  c2w = c2w.at[..., :3, 3].set(jax.random.normal(key_pos, (batch, views, 3)) * 0.3)
  intrinsics = jnp.broadcast_to(
    jnp.array([width * 0.9, width * 0.9, width / 2, height / 2]), (batch, views, 4)
  )
  return images, c2w, intrinsics


def torch_program(params, config, normalised, plucker, network):
  """Our PyTorch reference forward as a timed callable, its inputs, and its largest deviation
  from our compiled `network` (predict_gaussians) on the same inputs."""
  import torch
  from torch_reference import TorchTokenGS

  reference = TorchTokenGS(params, config)
  inputs = (torch.from_numpy(np.array(normalised)), torch.from_numpy(np.array(plucker)))
  ours = np.asarray(network(params, normalised, plucker))
  deviation = float(np.abs(reference.forward(*inputs).numpy() - ours).max())
  return lambda *a: jnp.asarray(reference.forward(*a).numpy()), inputs, deviation


@dataclasses.dataclass(frozen=True)
class Case:
  """One PRESET:BATCH[:HxW[:TOKENS]] case: its model, initial weights and random scene inputs."""

  name: str
  config: ModelConfig
  params: dict
  images: jax.Array  # [B, V, H, W, 3] in [0, 1]
  c2w: jax.Array
  intrinsics: jax.Array

  @classmethod
  def parse(cls, case: str, views: int | None, dtype: str) -> Case:
    name, batch, *rest = case.split(":")
    config = case_config(name, dtype)
    size = tuple(int(n) for n in rest[0].split("x")) if rest else None
    if len(rest) > 1:
      config = config.replace(num_gs_tokens=int(rest[1]))
    height, width = size or config.image_size
    images, c2w, intrinsics = scene_inputs(
      int(batch), views or config.num_input_views, height, width
    )
    return cls(name, config, init_params(jax.random.key(0), config), images, c2w, intrinsics)

  def describe(self, dtype: str) -> dict:
    """The case's sizes, as the first entries of its result row."""
    batch, views, height, width, _ = self.images.shape
    return {
      "preset": self.name,
      "batch": batch,
      "views": views,
      "height": height,
      "width": width,
      "dtype": dtype,
      "params_m": count_params(self.config) / 1e6,
      "gaussians": self.config.num_gaussians,
      "image_tokens": views * height * width // self.config.patch_size**2,
    }

  def loss(self, params):
    """A loss on the flat Gaussians, so that the train step differentiates the whole network."""
    flat = reconstruct(params, self.images, self.c2w, self.intrinsics, config=self.config)
    return jnp.mean(jnp.square(flat.to_flat() - 0.5))

  def stage_args(self) -> dict:
    """Stage -> the arguments of its function (decode's cached keys/values are zeros)."""
    _, _, height, width, _ = self.images.shape
    plucker = plucker_rays(self.c2w, self.intrinsics, height, width)
    normalised = normalize_images(self.images)
    encoded = jax.eval_shape(
      functools.partial(encode, config=self.config), self.params, normalised, plucker
    )
    encoded = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), encoded)
    return {
      "encode": (self.params, normalised, plucker),
      "decode": (self.params, encoded),
      "reconstruct": (self.params, self.images, self.c2w, self.intrinsics),
      "train_step": (self.params,),
      "network": (self.params, normalised, plucker),
    }

  def stage_functions(self, with_torch: bool, variant: str = "tiled") -> dict:
    """Fresh jitted functions (jit caches traces per function object, so one set per variant)."""
    variant_case = dataclasses.replace(self, config=self.config.replace(**VARIANTS[variant]))
    config = variant_case.config
    stages = {
      "encode": jax.jit(functools.partial(encode, config=config)),
      "decode": jax.jit(functools.partial(decode, config=config)),
      "reconstruct": jax.jit(functools.partial(reconstruct, config=config)),
      "train_step": jax.jit(jax.value_and_grad(variant_case.loss)),
    }
    if with_torch:  # the network alone, as the PyTorch reference computes it
      stages["network"] = jax.jit(functools.partial(predict_gaussians, config=config))
    return stages


def model_flops(case: Case, stage_args: dict, with_torch: bool) -> dict:
  """Stage -> FLOPs of its forward program; the train step is credited with 3x reconstruct's."""
  # From the untiled program: XLA's cost analysis counts a loop body once, so the tiled
  # attention's scans would be under-counted.
  with attention_variant("plain"):
    flops = {
      stage: flop_count(fn.lower(*stage_args[stage]))
      for stage, fn in case.stage_functions(with_torch).items()
      if stage != "train_step"
    }
  flops["train_step"] = 3 * flops["reconstruct"]
  return flops


def compile_stages(
  case: Case,
  stage_args: dict,
  flops: dict,
  variants: tuple[str, ...],
  max_temp_gb: float,
  with_torch: bool,
) -> tuple[dict, list]:
  """Compiles and warms up every stage under each attention variant.

  Returns variant -> stage -> {gflop, temp_gb[, skipped]}, and the programs to time as
  (variant, stage, compiled, args); a program over `max_temp_gb` of temporaries is not run.
  """
  results, programs = {}, []
  for variant in variants:
    results[variant] = {}
    with attention_variant(variant):
      for stage, fn in case.stage_functions(with_torch, variant).items():
        args = stage_args[stage]
        compiled = compile_fn(fn, *args)
        temp_gb = compiled.memory_analysis().temp_size_in_bytes / 1e9
        results[variant][stage] = {"gflop": flops[stage] / 1e9, "temp_gb": temp_gb}
        if temp_gb > max_temp_gb:
          results[variant][stage]["skipped"] = f"needs {temp_gb:.1f} GB of temporaries"
        else:
          jax.block_until_ready(compiled(*args))  # warm-up
          programs.append((variant, stage, compiled, args))
  return results, programs


def best_times(programs: list, peak_size: int, repeats: int) -> dict:
  """Minimum [wall, CPU] seconds of each program and of the peak matmul ("peak").

  Every round times the matmul and then each program, so that on a shared machine the peak and
  the stages see the same load; train steps take part in the first max(1, repeats // 2) rounds.
  """
  matmuls = {
    "peak": matmul_program(peak_size),
    "peak_bf16": matmul_program(peak_size, jnp.bfloat16),
  }
  never = np.full(2, np.inf)
  best = dict.fromkeys(matmuls, never)
  for round_index in range(repeats):
    # the matmuls are cheap: sample them several times per round so that their minima are as
    # representative of an unloaded moment as the stages' minima
    for _ in range(5):
      for name, (matmul, matmul_args) in matmuls.items():
        best[name] = np.minimum(best[name], timed(matmul, *matmul_args))
    for variant, stage, compiled, args in programs:
      if stage != "train_step" or round_index < max(1, repeats // 2):
        key = (variant, stage)
        best[key] = np.minimum(best.get(key, never), timed(compiled, *args))
  return best


def variant_accuracy(case: Case, programs: list) -> dict:
  """Variant -> {max |difference| of its reconstructed Gaussians from the first variant's, PSNR
  (dB) between the two sets' renders}, for every variant after the first."""
  outputs = {v: c(*args) for v, stage, c, args in programs if stage == "reconstruct"}
  if len(outputs) < 2:
    return {}
  _, _, height, width, _ = case.images.shape
  camera = (jnp.linalg.inv(case.c2w[0, :1]), case.intrinsics[0, :1])  # [1, 4, 4], [1, 4]

  def image(gaussians):
    first_scene = jax.tree.map(lambda x: x[0], gaussians)
    return render_exact(first_scene, *camera, height=height, width=width).rgb[0]

  (first, reference), *others = outputs.items()
  return {
    variant: {
      "max_abs_deviation": float(jnp.abs(gaussians.to_flat() - reference.to_flat()).max()),
      "render_psnr_db": float(psnr(image(gaussians), image(reference))),
      "against": first,
    }
    for variant, gaussians in others
  }


def run_case(
  case: str,
  views: int | None,
  repeats: int,
  dtype: str,
  peak_size: int,
  max_temp_gb: float,
  variants: tuple[str, ...],
  with_torch: bool = False,
) -> dict:
  setup = Case.parse(case, views, dtype)
  stage_args = setup.stage_args()
  flops = model_flops(setup, stage_args, with_torch)
  results, programs = compile_stages(setup, stage_args, flops, variants, max_temp_gb, with_torch)
  row = {**setup.describe(dtype), **results}
  if with_torch:
    network = next(c for v, stage, c, _ in programs if stage == "network")
    _, normalised, plucker = stage_args["network"]
    fn, args, deviation = torch_program(setup.params, setup.config, normalised, plucker, network)
    fn(*args)  # warm-up
    programs.append(("torch", "network", fn, args))
    row["torch"] = {
      "network": {"gflop": flops["network"] / 1e9, "temp_gb": 0.0, "max_abs_deviation": deviation}
    }
  row["accuracy"] = variant_accuracy(setup, programs)
  best = best_times(programs, peak_size, repeats)
  row["matmul_peak_gflops"] = peak = 2 * peak_size**3 / best["peak"][0] / 1e9
  row["matmul_peak_bf16_gflops"] = 2 * peak_size**3 / best["peak_bf16"][0] / 1e9
  row["matmul_peak_cpu_ms"] = best["peak"][1] * 1e3
  for variant, stage, _, _ in programs:
    wall, cpu = best[(variant, stage)]
    row[variant][stage].update(throughput(wall, flops[stage], peak), cpu_ms=cpu * 1e3)
  return row


def print_case(row: dict, variants: tuple[str, ...], peak_size: int, with_torch: bool) -> None:
  """The case's sizes and matmul peaks, a line per (variant, stage), accuracy, PyTorch ratios."""
  print(
    f"\n{row['preset']}  B={row['batch']} V={row['views']} {row['height']}x{row['width']} "
    f"{row['dtype']}  {row['params_m']:.1f} M params, {row['image_tokens']} image tokens "
    f"-> {row['gaussians']} Gaussians;  matmul peak ({peak_size}^3 f32, same rounds): "
    f"{row['matmul_peak_gflops']:.1f} GFLOP/s (bf16 x bf16 -> f32: "
    f"{row['matmul_peak_bf16_gflops']:.1f})"
  )
  print(
    f"  {'variant':<10}{'stage':<12}{'ms':>10}{'GFLOP':>10}{'GFLOP/s':>10}{'of peak':>9}"
    f"{'temp GB':>9}{'CPU ms':>9}  (matmul peak CPU ms {row['matmul_peak_cpu_ms']:.1f})"
  )
  for variant in (*variants, "torch") if with_torch else variants:
    for stage in ("network", "encode", "decode", "reconstruct", "train_step"):
      if stage not in row[variant]:
        continue
      s = row[variant][stage]
      if "skipped" in s:
        print(f"  {variant:<10}{stage:<12}{'-':>10}{s['gflop']:>10.2f}  skipped: {s['skipped']}")
        continue
      print(
        f"  {variant:<10}{stage:<12}{s['ms']:>10.1f}{s['gflop']:>10.2f}"
        f"{s['gflops_per_s']:>10.1f}{s['fraction_of_peak']:>9.0%}{s['temp_gb']:>9.2f}"
        f"{s['cpu_ms']:>9.1f}"
      )
  for variant, accuracy in row["accuracy"].items():
    print(
      f"  {variant} vs {accuracy['against']}: Gaussians max |difference| "
      f"{accuracy['max_abs_deviation']:.1e}, render PSNR {accuracy['render_psnr_db']:.1f} dB"
    )
  for variant in variants if with_torch else ():
    torch_row, ours = row["torch"]["network"], row[variant]["network"]
    print(
      f"  network: PyTorch reference / {variant} = {torch_row['ms'] / ours['ms']:.2f}x wall, "
      f"{torch_row['cpu_ms'] / ours['cpu_ms']:.2f}x CPU time "
      f"(reference vs {variants[0]}: Gaussians max |difference| "
      f"{torch_row['max_abs_deviation']:.1e})"
    )


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--case", action="append", help="PRESET:BATCH[:HxW[:TOKENS]] (repeatable)")
  parser.add_argument("--views", type=int, default=None)
  parser.add_argument("--max-temp-gb", type=float, default=14.0)
  parser.add_argument("--repeats", type=int, default=3)
  parser.add_argument("--dtype", default="float32", choices=["float32", "bfloat16"])
  parser.add_argument("--peak-size", type=int, default=2048)
  parser.add_argument(
    "--compare-plain-attention",
    action="store_true",
    help="also time every stage with the untiled attention (A/B); same as --variant plain",
  )
  parser.add_argument(
    "--variant", action="append", choices=list(VARIANTS), help="variants to time (repeatable)"
  )
  parser.add_argument(
    "--torch",
    action="store_true",
    help="also time our PyTorch forward (benchmarks/torch_reference.py)",
  )
  parser.add_argument("--out", default=None, help="write the results as JSON here")
  process.add_arguments(parser)
  args = parser.parse_args()
  process.setup(host_memory=args.host_memory)
  cases = args.case or ["tiny:8", "dl3dv_2view:1", "dl3dv_2view:1:128x224:1024"]
  variants = tuple(args.variant or ["tiled"])
  variants += ("plain",) if args.compare_plain_attention and "plain" not in variants else ()

  results = {"device": jax.devices()[0].device_kind, "cases": []}
  print(f"device: {results['device']}")
  for case in cases:
    row = run_case(
      case,
      args.views,
      args.repeats,
      args.dtype,
      args.peak_size,
      args.max_temp_gb,
      variants,
      args.torch,
    )
    results["cases"].append(row)
    print_case(row, variants, args.peak_size, args.torch)
  if args.out:
    with open(args.out, "w") as f:
      json.dump(results, f, indent=1)


if __name__ == "__main__":
  np.set_printoptions(precision=3)
  main()
