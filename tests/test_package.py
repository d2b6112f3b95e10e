"""The top-level package: every public name resolves, the documented entry points are there, and
`import tokengs_jax` stays cheap (its names are resolved lazily)."""

import subprocess
import sys

import tokengs_jax

ENTRY_POINTS = (
  "reconstruct",
  "encode_views",
  "decode",
  "decode_at_times",
  "render",
  "tune",
  "Gaussians",
)


def test_every_public_name_resolves():
  for name in tokengs_jax.__all__:
    assert getattr(tokengs_jax, name) is not None, name


def test_the_documented_entry_points_are_exported():
  assert set(ENTRY_POINTS) <= set(tokengs_jax.__all__)


def test_import_loads_neither_flax_optax_nor_orbax():
  """`import tokengs_jax` alone, in a fresh interpreter (the tests import them into this one), so
  that a user who only renders never pays for the network's, optimiser's or checkpointer's
  libraries."""
  modules = subprocess.run(
    [sys.executable, "-c", "import sys, tokengs_jax; print(*sys.modules)"],
    capture_output=True,
    text=True,
    check=True,
  ).stdout.split()
  loaded = {name.split(".")[0] for name in modules} & {"flax", "optax", "orbax"}
  assert not loaded, f"import tokengs_jax loaded {sorted(loaded)}"
