"""The Gaussian scene representation shared by the model, the renderer and the exporters."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

# Channel layout of the official flat tensor: [xyz 3, opacity 1, scale 3, quat 4 (wxyz), rgb 3].
FLAT_SPLITS = (3, 4, 7, 11)
FLAT_CHANNELS = 14
# Trailing shape of each field after its [..., N] axes.
_FIELD_TAILS = {"means": (3,), "opacities": (), "scales": (3,), "quats": (4,), "colors": (3,)}


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Gaussians:
  """A set of 3D Gaussians with activated parameters (a pytree: jit, vmap and grad see every field).

  Attributes:
    means: [..., N, 3] world-space centres.
    opacities: [..., N] in [0, 1].
    scales: [..., N, 3] linear standard deviations along the local axes.
    quats: [..., N, 4] rotations (w, x, y, z); need not be normalised (the renderer normalises).
    colors: [..., N, 3] linear RGB.
  """

  means: jax.Array
  opacities: jax.Array
  scales: jax.Array
  quats: jax.Array
  colors: jax.Array

  @classmethod
  def from_flat(cls, flat: jax.Array) -> "Gaussians":
    """From the official flat layout.  flat: [..., N, 14] -> Gaussians with batch shape [...]."""
    if flat.shape[-1] != FLAT_CHANNELS:
      raise ValueError(f"expected {FLAT_CHANNELS} channels, got shape {flat.shape}")
    means, opacities, scales, quats, colors = jnp.split(flat, FLAT_SPLITS, axis=-1)
    return cls(means=means, opacities=opacities[..., 0], scales=scales, quats=quats, colors=colors)

  def to_flat(self) -> jax.Array:
    """To the official flat layout.  -> [..., N, 14]."""
    return jnp.concatenate(
      [self.means, self.opacities[..., None], self.scales, self.quats, self.colors], axis=-1
    )

  def validate(self) -> tuple[int, ...]:
    """Checks the field shapes and dtypes (trace time: shapes only); returns the batch shape [...].

    Every field must be real-valued with the trailing shape of its docstring and the same N; the
    batch shapes must broadcast. Raises ValueError naming the field and the expected shape.
    """
    num = None
    batches = []
    for name, tail in _FIELD_TAILS.items():
      value = getattr(self, name)
      shape, dtype = jnp.shape(value), jnp.result_type(value)
      if not (jnp.issubdtype(dtype, jnp.floating) or jnp.issubdtype(dtype, jnp.integer)):
        raise ValueError(f"Gaussians.{name} must be real numbers, got dtype {dtype}")
      expected = "[..., N" + "".join(f", {d}" for d in tail) + "]"
      if len(shape) < 1 + len(tail) or shape[len(shape) - len(tail) :] != tail:
        raise ValueError(f"Gaussians.{name} must be {expected}, got shape {shape}")
      field_num = shape[len(shape) - len(tail) - 1]
      if num is not None and field_num != num:
        raise ValueError(f"Gaussians.{name} has N = {field_num}, Gaussians.means has N = {num}")
      num = field_num
      batches.append(shape[: len(shape) - len(tail) - 1])
    try:
      return jnp.broadcast_shapes(*batches)
    except ValueError:
      raise ValueError(
        f"Gaussians fields have batch shapes that do not broadcast: "
        f"{dict(zip(_FIELD_TAILS, batches))}"
      ) from None

  @property
  def num_gaussians(self) -> int:
    return self.means.shape[-2]

  @property
  def batch_shape(self) -> tuple[int, ...]:
    return self.means.shape[:-2]

  def static_and_dynamic(self, num_static: int) -> tuple["Gaussians", "Gaussians"]:
    """(Gaussians [..., :num_static], Gaussians [..., num_static:]) of every set: those of the
    static tokens and those of the dynamic ones, which a model emits after the static ones
    (`ModelConfig.num_static_gaussians`)."""
    return self._subset(slice(None, num_static)), self._subset(slice(num_static, None))

  def _subset(self, part: slice) -> "Gaussians":
    """The Gaussians `part` of the N axis of every set."""
    return Gaussians(
      **{
        name: getattr(self, name)[(..., part) + (slice(None),) * len(tail)]
        for name, tail in _FIELD_TAILS.items()
      }
    )

  def first_set(self) -> "Gaussians":
    """The set at index 0 of every batch axis (e.g. [1] or [1, T] -> fields [N, ...])."""
    index = (0,) * len(self.batch_shape)
    return jax.tree.map(lambda x: x[index], self)
