"""Test-wide JAX setup: 4 virtual CPU devices (sharding tests) and a persistent compile cache.

Both must be configured before any JAX computation runs, hence here and at import time. The
host memory policy stays JAX's and glibc's own: `tests/test_process.py` compares both in fresh
interpreters.
"""

import os
import pathlib

import jax
import pytest
from PIL import ImageFile

from tokengs_jax import process

# The suite is compile-bound on a fresh machine (cold cache: two thirds of its time is XLA:CPU
# compiling). The backend's lowest optimisation level compiles about 1.5x faster; its programs
# run slower (a tiny model's 3 tuning steps: 214 against 56 ms), which the tests' few steps do
# not feel. Results stay within the tests' tolerances (docs/benchmarks.md, "Test suite"). The
# flags are read when the backend starts, after this line; a caller's own XLA_FLAGS are kept.
os.environ.setdefault(
  "XLA_FLAGS", "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
)

process.setup(
  compile_cache=os.environ.get(
    "TOKENGS_JAX_CACHE", pathlib.Path(__file__).parent.parent / ".jax_cache"
  ),
  min_compile_seconds=0.5,
  host_memory="default",
  cpu_devices=4,
)

FIXTURES = pathlib.Path(__file__).resolve().parent.parent.parent / "shared" / "fixtures"
OFFICIAL_OPTIONS = FIXTURES.parent / "reference" / "tokengs-official" / "tokengs" / "options.py"


def reference_fixture(*parts: str) -> pathlib.Path:
  """A file of the reference fixtures (numbers produced by the official code and gsplat, kept in
  `../shared/fixtures` beside the repository); skips the calling test, saying which file and
  why, where that folder is not there (e.g. a bare clone)."""
  path = FIXTURES.joinpath(*parts)
  if not path.exists():
    pytest.skip(f"reference fixture {path} is absent (../shared/fixtures is not beside the repo)")
  return path


@pytest.fixture(scope="session")
def official():
  """The official `tokengs/options.py` module, imported (its presets and defaults are what the
  presets here are checked against); skips where `../shared/reference` is absent."""
  import importlib.util
  import sys

  if not OFFICIAL_OPTIONS.exists():
    pytest.skip(f"the official options {OFFICIAL_OPTIONS} are absent (no ../shared/reference)")
  spec = importlib.util.spec_from_file_location("official_tokengs_options", OFFICIAL_OPTIONS)
  module = importlib.util.module_from_spec(spec)
  sys.modules[spec.name] = module  # dataclasses look their module up while building
  spec.loader.exec_module(module)
  return module


@pytest.fixture(scope="session")
def tiny():
  """(config, params) of the `tiny` model preset, initialised once per test session."""
  from tokengs_jax.model import init_params, preset

  config = preset("tiny")
  return config, init_params(jax.random.PRNGKey(0), config)


@pytest.fixture
def no_pixel_decoding(monkeypatch):
  """Fails a test that decodes pixels (and spares the memory a refused header would have cost)."""

  def decode(image):
    raise AssertionError(f"{image.size[0]}x{image.size[1]} pixels decoded")

  monkeypatch.setattr(ImageFile.ImageFile, "load", decode)


# XLA:CPU maps each loaded executable (compiled or read from the compile cache) as 3 memory
# mappings, held until the executable is freed, and the jit caches keep every program a test
# compiled: a pytest-xdist worker of the default suite reached 48,300 mappings. At the kernel's
# per-process limit (`vm.max_map_count`, 65,530 by default) LLVM's JIT fails to map the next
# executable ("LLVM compilation error: Cannot allocate memory") and XLA then segfaults, in
# `backend_compile_and_load` or, for a cache hit, `get_executable_and_time`: the worker
# segfaults seen in about one warm run in two (docs/benchmarks.md, "Test suite"). So after a test
# module, a process past a quarter of the limit clears JAX's caches (freeing those executables;
# they come back from the compile cache where needed).
_MAPS, _MAX_MAPS = pathlib.Path("/proc/self/maps"), pathlib.Path("/proc/sys/vm/max_map_count")


@pytest.fixture(scope="module", autouse=True)
def _bounded_memory_mappings():
  yield
  if _MAPS.exists() and _MAX_MAPS.exists():
    with _MAPS.open("rb") as maps:
      mappings = sum(1 for _ in maps)
    if mappings > int(_MAX_MAPS.read_text()) // 4:
      jax.clear_caches()
