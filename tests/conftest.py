"""Test-wide JAX setup: 4 virtual CPU devices (sharding tests) and a persistent compile cache.

Both must be configured before any JAX computation runs, hence here and at import time.
"""

import os
import pathlib

import jax
import pytest

jax.config.update("jax_num_cpu_devices", 4)
_CACHE = pathlib.Path(
  os.environ.get("TOKENGS_JAX_CACHE", pathlib.Path(__file__).parent.parent / ".jax_cache")
)
jax.config.update("jax_compilation_cache_dir", str(_CACHE))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)

FIXTURES = pathlib.Path(__file__).resolve().parent.parent.parent / "shared" / "fixtures"


def reference_fixture(*parts: str) -> pathlib.Path:
  """A file of the reference fixtures (numbers produced by the official code and gsplat, kept in
  `../shared/fixtures` beside the repository); skips the calling test, saying which file and
  why, where that folder is not there (e.g. a bare clone)."""
  path = FIXTURES.joinpath(*parts)
  if not path.exists():
    pytest.skip(f"reference fixture {path} is absent (../shared/fixtures is not beside the repo)")
  return path


@pytest.fixture(scope="session")
def tiny():
  """(config, params) of the `tiny` model preset, initialised once per test session."""
  from tokengs_jax.model import init_params, preset

  config = preset("tiny")
  return config, init_params(jax.random.PRNGKey(0), config)
