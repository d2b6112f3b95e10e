"""Process-wide settings, in one place: every entry point calls `setup` once, first.

The experiments' command lines, the studies, the browser viewer, the benchmarks and the tests'
`conftest.py` all start with `setup`, so a run's JAX settings do not depend on which of them
launched it:

- the persistent XLA compilation cache (`$TOKENGS_JAX_CACHE`, default `.jax_cache`): on CPU,
  compiling the training step and the renderer takes longer than a short run itself;
- the host memory policy below (`retain_freed_memory`);
- optionally, the number of virtual CPU devices (the tests' sharding cases use 4).

`exit_with_parent` is for the helper processes a run starts (the data pipeline's workers): they
end with the process that started them, however it ended.

Host memory: XLA:CPU allocates an executable's temporaries as one buffer per run (the `tiny`
preset's train step: 59 MB) and frees it at the end. glibc serves a block that large with fresh
`mmap` pages and unmaps them on free, so every step first-touches its whole temporary buffer
again: ~15,000 page faults, 15-20 ms of a 65 ms train step on the development CPU
(docs/benchmarks.md, "Host memory"). `retain_freed_memory` stops that in two settings:

- glibc's `mallopt`: no `mmap` for blocks of any size and no trimming of the heap's free top, so a
  freed buffer stays resident and the next run's equal-sized request reuses it (most runs: a
  repeated 64 MB program still got fresh pages in about one run in ten, apparently when it
  allocated before the previous run's buffer was back in the heap; the heap then grows once);
- JAX's CPU client runs single-device computations inline (`jax_cpu_enable_async_dispatch`
  off), so their temporaries come from the calling thread's heap. A dispatch thread's glibc arena
  cannot grow a heap past 64 MB and, depending on what else lives in it, `mmap`s blocks far
  smaller: measured, the tiny train step still faulted in 4 processes of 10 without this.

The cost is resident memory (the process keeps its heap's high-water mark) and that Python waits
for each single-device computation instead of queueing the next (the training loop's data
pipeline runs in its own threads, so steps are back to back anyway). Multi-device computations are
still dispatched asynchronously. Accelerators are not affected.
"""

from __future__ import annotations

import argparse
import ctypes
import os
import sys
import threading
import time
import warnings

import jax
from jax._src import xla_bridge  # private, as jax.distributed uses it: do JAX's clients exist yet

# glibc <malloc.h> mallopt parameters.
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_NEVER_TRIM = (1 << 31) - 1  # bytes of free heap top kept: the largest C int mallopt takes


def retain_freed_memory() -> bool:
  """Makes this process reuse freed host memory for XLA:CPU temporaries (see the module doc).

  Call once, before the first JAX computation (the CPU client reads the dispatch setting when it is
  created); the experiments' entry points do. Process-wide and not undone.

  Returns:
    True when glibc's allocator was set; False where there is no glibc `mallopt` (not Linux, or
    another C library such as musl): then only the dispatch setting applies.
  """
  if xla_bridge.backends_are_initialized():
    warnings.warn(
      "retain_freed_memory() after the first JAX computation: the CPU client already exists and "
      "keeps dispatching asynchronously; only the allocator setting applies",
      stacklevel=2,
    )
  jax.config.update("jax_cpu_enable_async_dispatch", False)
  if not sys.platform.startswith("linux"):
    return False
  try:
    mallopt = ctypes.CDLL("libc.so.6").mallopt
  except (OSError, AttributeError):
    return False
  mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
  return mallopt(_M_MMAP_MAX, 0) == 1 and mallopt(_M_TRIM_THRESHOLD, _NEVER_TRIM) == 1


HOST_MEMORY_POLICIES = ("retain", "default")
_settled: dict | None = None  # the first `setup`'s arguments: later calls keep them


def setup(
  *,
  compile_cache: str | os.PathLike | None = None,
  min_compile_seconds: float = 1.0,
  host_memory: str = "retain",
  cpu_devices: int | None = None,
) -> dict:
  """Applies this process's JAX settings; call before the first JAX computation.

  The first call wins: a later one (an experiment's `main` run inside the tests, whose
  `conftest.py` has set up already) changes nothing and returns the settings in force.

  Args:
    compile_cache: folder of the persistent compilation cache; None: `$TOKENGS_JAX_CACHE`, else
      `.jax_cache` under the working directory. A folder set earlier by the embedding program is
      kept.
    min_compile_seconds: programs that compile faster than this are not cached.
    host_memory: "retain" (`retain_freed_memory`, the experiments' policy) or "default" (glibc's
      and JAX's own settings, for comparisons).
    cpu_devices: virtual CPU devices to create (None: JAX's default, one).

  Returns:
    The settings in force: `compile_cache`, `host_memory`, `cpu_devices`.
  """
  global _settled
  if _settled is not None:
    return dict(_settled)
  if host_memory not in HOST_MEMORY_POLICIES:
    raise ValueError(f"host_memory must be one of {HOST_MEMORY_POLICIES}, got {host_memory!r}")
  if cpu_devices is not None:
    jax.config.update("jax_num_cpu_devices", cpu_devices)
  if not jax.config.jax_compilation_cache_dir:
    folder = compile_cache or os.environ.get("TOKENGS_JAX_CACHE", ".jax_cache")
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", min_compile_seconds)
  if host_memory == "retain":
    retain_freed_memory()
  _settled = dict(
    compile_cache=jax.config.jax_compilation_cache_dir,
    host_memory=host_memory,
    cpu_devices=cpu_devices,
  )
  return dict(_settled)


def add_arguments(parser: argparse.ArgumentParser) -> None:
  """The `--host-memory` flag of the benchmarks' command lines (pass its value to `setup`)."""
  parser.add_argument(
    "--host-memory",
    choices=HOST_MEMORY_POLICIES,
    default="retain",
    help="retain: tokengs_jax.process.retain_freed_memory() first, as the experiments do; "
    "default: glibc's and JAX's own settings",
  )


def exit_with_parent(poll_seconds: float = 0.5) -> None:
  """Ends this process within `poll_seconds` of its parent's end, however the parent ended.

  For worker processes: a parent that exits normally stops its workers itself, but one killed
  (SIGKILL, or SIGTERM without a handler) cannot, and its workers would live on as orphans
  holding their memory (a grain worker of the `smoke` preset: 260 MB) until someone kills them.
  A daemon thread polls the parent's pid (not `PR_SET_PDEATHSIG`, which fires when the thread that
  started the process ends: grain starts its workers from a thread pool).
  """
  parent = os.getppid()

  def watch() -> None:
    while os.getppid() == parent:
      time.sleep(poll_seconds)
    os._exit(1)  # no cleanup to wait for: the resource tracker frees the shared memory left

  threading.Thread(target=watch, name="exit_with_parent", daemon=True).start()
