"""Our network against the official PyTorch TokenGS, same weights, same minute, same machine.

    python benchmarks/official_side_by_side.py --torch-python TORCH_VENV/bin/python \\
        --official ../shared/reference/tokengs-official --size small --rounds 3

Each round times, block after block: the official `forward_reconstruction` in float32, ours in
float32, the official one under `torch.autocast("cpu", torch.bfloat16)`, ours with bf16 matmuls.
The official model runs in one child process with the torch environment of
`../shared/tools/README.md` for the whole run (it writes the random weights it drew first). Ours
runs on exactly those weights (`config_from_official`, `load_official_checkpoint`, placed on the
device once), jitted `predict_gaussians` in float32 and with `matmul_dtype="bfloat16"`: its
kernels rounded once (`cast_matmul_kernels`, the inference path; torch's autocast caches its
weight casts inside the timed block) and, beside it, in every call ("bfloat16 per call").

Each figure is the median of `--repeats` calls after a warm-up (compilation apart). The table
gives each side's median over rounds, their ratio official / ours (> 1: ours faster), and the
median, least and greatest of the rounds' own ratios. Blocks of well under a second (small)
alternate, so a change in machine load falls on both sides. Torch is not a dependency of this
project; only the child process imports it.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import pathlib
import statistics
import subprocess
import sys
import tempfile
import time

# H W views enc dec dim heads tokens (the issue-11 sizes of benchmarks/model.py)
SIZES = {"small": (128, 128, 2, 2, 4, 256, 4, 256), "mid": (256, 256, 2, 6, 6, 512, 8, 1024)}

# A child process with torch: builds the official model on random weights, writes them (and its
# options) for ours to load, says "ready", then answers each line "float32" / "bfloat16" with the
# median ms of `reps` forward calls in that precision.
_TORCH_SERVER = r"""
import json, os, statistics, sys, time, types
import torch
src, out, reps = sys.argv[1], sys.argv[2], int(sys.argv[3])
H, W, V, E, D, C, NH, T = map(int, sys.argv[4:12])
sys.path.insert(0, src)
sys.modules.setdefault("lpips", types.SimpleNamespace(LPIPS=None))  # LPIPS is off; no torchvision
from safetensors.torch import save_file
from tokengs.options import Options
from tokengs.models.tokengs import TokenGS
from tokengs.models.input_types import ModelInput, ModelInputDecoder, ModelInputEncoder
opt = Options(img_size=(H, W), patch_size=8, enc_depth=E, dec_depth=D, enc_embed_dim=C,
              enc_num_heads=NH, num_gs_tokens=T, token_dim=C, num_input_views=V, num_views=V + 1,
              lambda_lpips=0.0, lambda_ssim=0.0, lambda_visibility=0.0, random_reflect=False)
torch.manual_seed(0)
model = TokenGS(opt).eval()
eye = torch.eye(4).repeat(1, V, 1, 1)
encoder = ModelInputEncoder(images_rgb=torch.randn(1, V, 3, H, W), plucker=torch.randn(1, V, 6, H, W),
                            rays_os=torch.zeros(1, V, 3, H, W), rays_ds=torch.zeros(1, V, 3, H, W),
                            intrinsics_input=torch.ones(1, V, 4), cam_to_world_input=eye)
inputs = ModelInput(encoder=encoder, decoder=ModelInputDecoder(cam_view=eye, intrinsics=torch.ones(1, V, 4)))
def median_ms(bf16):
    with torch.no_grad(), torch.autocast("cpu", torch.bfloat16, enabled=bf16):
        model.forward_reconstruction(inputs)
        times = []
        for _ in range(reps):
            start = time.perf_counter(); model.forward_reconstruction(inputs)
            times.append(time.perf_counter() - start)
    return statistics.median(times) * 1e3
os.makedirs(out, exist_ok=True)
save_file({k: v.contiguous() for k, v in model.state_dict().items()}, os.path.join(out, "weights.safetensors"))
json.dump({k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(opt).items()
           if isinstance(v, (int, float, str, bool, tuple, type(None)))},
          open(os.path.join(out, "options.json"), "w"), default=str)
print(json.dumps({"ready": True, "threads": torch.get_num_threads()}), flush=True)
for line in sys.stdin:
    print(json.dumps({"ms": median_ms(line.strip() == "bfloat16")}), flush=True)
"""


@contextlib.contextmanager
def official_model(args, size: tuple, out: str):
  """A function precision -> median ms of the official forward, served by one torch process that
  lives for the whole run (so its calls can alternate with ours block by block)."""
  command = [args.torch_python, "-c", _TORCH_SERVER, args.official, out, str(args.repeats)]
  with subprocess.Popen(
    command + [str(v) for v in size], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
  ) as child:

    def answer() -> dict:
      line = child.stdout.readline()
      if not line:
        raise RuntimeError(f"the official model's process ended (exit code {child.wait()})")
      return json.loads(line)

    answer()  # ready: the weights are written

    def median_ms(precision: str) -> float:
      child.stdin.write(precision + "\n")
      child.stdin.flush()
      return answer()["ms"]

    try:
      yield median_ms
    finally:
      child.stdin.close()


# Our variants: name -> (matmul dtype, which is also the official precision timed beside it;
# kernels rounded once). "bfloat16" is the inference path, its kernels rounded once by
# `cast_matmul_kernels`; "bfloat16 per call" rounds them in every call.
OUR_VARIANTS = {
  "float32": ("float32", False),
  "bfloat16": ("bfloat16", True),
  "bfloat16 per call": ("bfloat16", False),
}


def our_timers(folder: pathlib.Path, size: tuple, repeats: int) -> dict:
  """Variant -> a function returning the median ms of our jitted forward on the official weights."""
  import jax
  import numpy as np

  from tokengs_jax import model

  options = json.loads((folder / "options.json").read_text())
  height, width, views = size[:3]
  rng = np.random.default_rng(0)
  images = jax.numpy.asarray(rng.normal(size=(1, views, height, width, 3)), jax.numpy.float32)
  plucker = jax.numpy.asarray(rng.normal(size=(1, views, height, width, 6)), jax.numpy.float32)
  # the same float32 tree for every variant: the matmul dtype changes no parameter
  weights = model.load_official_checkpoint(
    folder / "weights.safetensors", model.config_from_official(options)
  )
  timers = {}
  for name, (matmul_dtype, cast_once) in OUR_VARIANTS.items():
    config = model.config_from_official(options, matmul_dtype=matmul_dtype)
    params = model.cast_matmul_kernels(weights, config) if cast_once else weights
    # On the device once, as the official model holds its weights: numpy leaves would be copied
    # in at every call.
    params = jax.device_put(params)
    forward = jax.jit(lambda p, i, q, c=config: model.predict_gaussians(p, i, q, c))
    jax.block_until_ready(forward(params, images, plucker))  # compile and warm up

    def median_ms(forward=forward, params=params):
      times = []
      for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(forward(params, images, plucker))
        times.append(time.perf_counter() - start)
      return statistics.median(times) * 1e3

    timers[name] = median_ms
  return timers


def main() -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--torch-python", required=True, help="python of a torch 2.13 environment")
  parser.add_argument("--official", required=True, help="the official TokenGS source folder")
  parser.add_argument("--size", choices=sorted(SIZES), default="small")
  parser.add_argument("--rounds", type=int, default=3)
  parser.add_argument("--repeats", type=int, default=15)
  args = parser.parse_args()
  from tokengs_jax import process

  process.setup()
  size = SIZES[args.size]
  rounds = []
  with tempfile.TemporaryDirectory() as scratch, official_model(args, size, scratch) as official:
    timers = our_timers(pathlib.Path(scratch), size, args.repeats)
    for _ in range(args.rounds):
      times = {}
      for precision in ("float32", "bfloat16"):  # each side's block right after the other's
        times[f"official {precision}"] = official(precision)
        for name, (matmul_dtype, _) in OUR_VARIANTS.items():
          if matmul_dtype == precision:
            times[f"ours {name}"] = timers[name]()
      rounds.append(times)
      print(json.dumps({k: round(v, 1) for k, v in times.items()}), flush=True)
  print(f"\n{args.size}: median ms over {args.rounds} rounds (each a median of {args.repeats})")
  print("official/ours: the ratio of the medians; per round: median [min, max] of each round's")
  for name, (matmul_dtype, _) in OUR_VARIANTS.items():
    theirs = [r[f"official {matmul_dtype}"] for r in rounds]
    ours = [r[f"ours {name}"] for r in rounds]
    ratios = [t / o for t, o in zip(theirs, ours)]
    print(
      f"{name:17s} official {statistics.median(theirs):8.1f}  ours {statistics.median(ours):8.1f}"
      f"  official/ours {statistics.median(theirs) / statistics.median(ours):.2f}x"
      f"  per round {statistics.median(ratios):.2f}x [{min(ratios):.2f}, {max(ratios):.2f}]"
    )
  return 0


if __name__ == "__main__":
  sys.exit(main())
