"""Our network against the official PyTorch TokenGS, same weights, same minute, same machine.

    python benchmarks/official_side_by_side.py --torch-python TORCH_VENV/bin/python \\
        --official ../shared/reference/tokengs-official --size small --rounds 3

Each round times, one after the other: the official `forward_reconstruction` in float32 and under
`torch.autocast("cpu", torch.bfloat16)` (a child process with the torch environment of
`../shared/tools/README.md`; it also writes the random weights it drew), then ours on exactly those
weights (`config_from_official`, `load_official_checkpoint`), jitted `predict_gaussians` in float32
and with `matmul_dtype="bfloat16"`. Each figure is the median of `--repeats` calls after a warm-up
(compilation apart); the table gives each implementation's median over rounds and the ratio
official / ours (> 1: ours faster). Alternating rounds spreads a change in machine load over both
sides. Torch is not a dependency of this project; only the child process imports it.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import statistics
import subprocess
import sys
import tempfile
import time

# H W views enc dec dim heads tokens (the issue-11 sizes of benchmarks/model.py)
SIZES = {"small": (128, 128, 2, 2, 4, 256, 4, 256), "mid": (256, 256, 2, 6, 6, 512, 8, 1024)}

_TORCH_TIMING = r"""
import json, statistics, sys, time, types
import torch
src, out, reps = sys.argv[1], sys.argv[2], int(sys.argv[3])
H, W, V, E, D, C, NH, T = map(int, sys.argv[4:12])
sys.path.insert(0, src)
sys.modules.setdefault("lpips", types.SimpleNamespace(LPIPS=None))  # LPIPS is off; no torchvision
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
result = {"float32": median_ms(False), "bfloat16": median_ms(True), "threads": torch.get_num_threads()}
if out != "-":
    import os
    from safetensors.torch import save_file
    os.makedirs(out, exist_ok=True)
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, os.path.join(out, "weights.safetensors"))
    json.dump({k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(opt).items()
               if isinstance(v, (int, float, str, bool, tuple, type(None)))},
              open(os.path.join(out, "options.json"), "w"), default=str)
print(json.dumps(result))
"""


def official_times(args, size: tuple, out: str) -> dict:
  """{"float32", "bfloat16"} median ms of the official forward (a child process with torch)."""
  command = [args.torch_python, "-c", _TORCH_TIMING, args.official, out, str(args.repeats)]
  done = subprocess.run(
    command + [str(v) for v in size], capture_output=True, text=True, check=True
  )
  return json.loads(done.stdout.strip().splitlines()[-1])


def our_timers(folder: pathlib.Path, size: tuple, repeats: int) -> dict:
  """Precision -> a function returning the median ms of our jitted forward on the official weights."""
  import jax
  import numpy as np

  from tokengs_jax import model

  options = json.loads((folder / "options.json").read_text())
  height, width, views = size[:3]
  rng = np.random.default_rng(0)
  images = jax.numpy.asarray(rng.normal(size=(1, views, height, width, 3)), jax.numpy.float32)
  plucker = jax.numpy.asarray(rng.normal(size=(1, views, height, width, 6)), jax.numpy.float32)
  timers = {}
  for name, matmul_dtype in (("float32", None), ("bfloat16", "bfloat16")):
    config = model.config_from_official(options, matmul_dtype=matmul_dtype)
    params = model.load_official_checkpoint(folder / "weights.safetensors", config)
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
  rows = {f"{impl} {p}": [] for impl in ("official", "ours") for p in ("float32", "bfloat16")}
  with tempfile.TemporaryDirectory() as scratch:
    for round_index in range(args.rounds):
      official = official_times(args, size, scratch if round_index == 0 else "-")
      if round_index == 0:
        timers = our_timers(pathlib.Path(scratch), size, args.repeats)
      for precision in ("float32", "bfloat16"):
        rows[f"official {precision}"].append(official[precision])
        rows[f"ours {precision}"].append(timers[precision]())
      print(json.dumps({k: round(v[-1], 1) for k, v in rows.items()}), flush=True)
  print(f"\n{args.size}: median ms over {args.rounds} rounds (each a median of {args.repeats})")
  for precision in ("float32", "bfloat16"):
    theirs = statistics.median(rows[f"official {precision}"])
    ours = statistics.median(rows[f"ours {precision}"])
    print(
      f"{precision:9s} official {theirs:8.1f}  ours {ours:8.1f}  official/ours {theirs / ours:.2f}x"
    )
  return 0


if __name__ == "__main__":
  sys.exit(main())
