"""Process-wide settings, in one place: every entry point calls `setup` once, first.

The experiments' command lines, the studies, the browser viewer, the benchmarks and the tests'
`conftest.py` all start with `setup`, so a run's JAX settings do not depend on which of them
launched it:

- the persistent XLA compilation cache (`$TOKENGS_JAX_CACHE`, default `.jax_cache`): on CPU,
  compiling the training step and the renderer takes longer than a short run itself. It is
  capped (`COMPILE_CACHE_MAX_BYTES`, least recently used entries evicted), which is also what
  makes JAX lock it across processes (below);
- the host memory policy below (`retain_freed_memory`), where the computations run on XLA:CPU;
- optionally, the number of virtual CPU devices (the tests' sharding cases use 4).

Shared cache folder: pytest-xdist workers and experiments run side by side share one folder. With
JAX's default `jax_compilation_cache_max_size` (-1: no cap) its file cache neither locks nor writes
atomically (`path.write_bytes`), so a process can read another's half-written entry: measured, 20 of
165 reads of 8 MB entries being written (`benchmarks/compile_cache_race.py entries`). Such a read
never reaches XLA: the zstd frame records its length, so a cut entry fails to decompress, and JAX
warns ("Error reading persistent compilation cache entry") and compiles again (docs/robustness.md,
"Processes"). A cap turns on JAX's cross-process lock (the `filelock` package) around every read
and write: 0 torn reads of 122 in the same stress. A capped cache keeps an `-atime` file beside
each entry and reads all of them when it writes; folders written without a cap lack them, so
`setup` gives each entry that has none its modification time (else every write would fail).

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
still dispatched asynchronously.

Where the computations run on an accelerator the policy buys nothing (their temporaries live in
device memory) and only costs: the process would keep the high-water mark of its host heap (the
data pipeline's buffers, a checkpoint's arrays) for the life of the run. So `setup(host_memory="auto")`, the default, applies it only for XLA:CPU, decided
without creating a JAX client (`setup` precedes the first computation, and a client made here
would be too early for `jax.distributed` and for the dispatch setting itself):

- `jax_platforms` (`$JAX_PLATFORMS`) set: its first platform is the one JAX prefers, so "cpu" there
  retains and anything else does not;
- otherwise XLA:CPU unless an accelerator PJRT plugin is installed and its hardware is present,
  found the way JAX's own discovery (`xla_bridge.discover_pjrt_plugins`) finds plugins, without
  importing them: modules of the `jax_plugins` namespace package, `jax_plugins` entry points,
  `$PJRT_NAMES_AND_LIBRARY_PATHS`, `libtpu` or `$TPU_LIBRARY_PATH`, and the CUDA / ROCm plugin
  packages. A CUDA plugin counts where an NVIDIA device node exists and TPU's where a TPU chip is
  on the PCI bus (JAX skips them otherwise and falls back to XLA:CPU); any other plugin counts.

"retain" and "default" force either setting; `setup` returns the one in force and why.
"""

from __future__ import annotations

import argparse
import ctypes
import importlib.metadata
import importlib.util
import os
import pkgutil
import sys
import threading
import time
import warnings

import jax
from jax._src import hardware_utils  # private: the device checks JAX's backend start-up makes
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


HOST_MEMORY_POLICIES = ("auto", "retain", "default")
# Accelerator plugin packages that live outside the `jax_plugins` namespace (their PJRT halves live
# inside it, so these are a second look, not the main one).
_PLUGIN_PACKAGES = (
  "jax_cuda12_plugin",
  "jax_cuda13_plugin",
  "jax_rocm60_plugin",
  "jax_rocm7_plugin",
  "libtpu",
)


def _installed_plugins() -> list[str]:
  """The accelerator PJRT plugins JAX would load, by module or library name, found as
  `xla_bridge.discover_pjrt_plugins` finds them but without importing them (an import runs the
  plugin's start-up; this must leave JAX untouched)."""
  found = set()
  namespace = xla_bridge.jax_plugins  # the `jax_plugins` namespace package, None without one
  if namespace is not None:
    found |= {name for _, name, _ in pkgutil.iter_modules(namespace.__path__, "jax_plugins.")}
  found |= {entry.value for entry in importlib.metadata.entry_points(group="jax_plugins")}
  for pair in filter(None, os.environ.get("PJRT_NAMES_AND_LIBRARY_PATHS", "").split(",")):
    found.add(pair.split(":" if os.name != "nt" else ";")[0])
  if os.environ.get("TPU_LIBRARY_PATH"):
    found.add("libtpu")
  found |= {name for name in _PLUGIN_PACKAGES if importlib.util.find_spec(name) is not None}
  return sorted(found)


def _has_hardware(plugin: str) -> bool:
  """Whether JAX would start `plugin`: it skips CUDA without an NVIDIA device node, and TPU's
  client fails (quietly, falling back to XLA:CPU) without a TPU chip."""
  if "cuda" in plugin:
    return hardware_utils.has_visible_nvidia_gpu()
  if "tpu" in plugin:
    return hardware_utils.num_available_tpu_chips_and_device_id()[0] > 0
  return True


def computation_platform() -> tuple[str, str]:
  """Where this process's computations will run, "cpu" or "accelerator", and why; decided
  without initialising a JAX backend (see the module doc), so it can precede `jax.distributed`.

  A guess only where JAX's own choice depends on more than it reads up front (a plugin that fails
  to start): then JAX falls back to XLA:CPU and the policy is off where it would have paid.
  """
  if platforms := jax.config.jax_platforms:
    first = platforms.split(",")[0].strip().lower()
    return ("cpu" if first == "cpu" else "accelerator"), f"jax_platforms={platforms!r}"
  present = [plugin for plugin in _installed_plugins() if _has_hardware(plugin)]
  if present:
    return "accelerator", f"accelerator plugin {', '.join(present)}"
  return "cpu", "no accelerator plugin with its hardware"


def resolve_host_memory(host_memory: str) -> tuple[str, str]:
  """The policy `setup(host_memory=...)` applies, "retain" or "default", and why."""
  if host_memory not in HOST_MEMORY_POLICIES:
    raise ValueError(f"host_memory must be one of {HOST_MEMORY_POLICIES}, got {host_memory!r}")
  if host_memory != "auto":
    return host_memory, "requested"
  platform, why = computation_platform()
  return ("retain" if platform == "cpu" else "default"), f"auto: {platform} ({why})"


_settled: dict | None = None  # the first `setup`'s arguments: later calls keep them
COMPILE_CACHE_MAX_BYTES = 8 << 30  # the cap `setup` gives an uncapped cache (the repo's: ~0.2 GB)


def _add_missing_access_times(folder: str | os.PathLike) -> int:
  """Gives every entry of a compilation cache folder that has no `<key>-atime` file one holding
  its modification time (nanoseconds, little-endian: JAX's `lru_cache` format), so that a capped
  cache can use a folder an uncapped one wrote; returns how many it wrote."""
  written = 0
  try:
    entries = [entry for entry in os.scandir(folder) if entry.name.endswith("-cache")]
  except FileNotFoundError:
    return 0
  for entry in entries:
    atime = os.path.join(folder, entry.name.removesuffix("-cache") + "-atime")
    if os.path.exists(atime):
      continue
    try:
      stamp = entry.stat().st_mtime_ns
    except FileNotFoundError:  # evicted meanwhile by another process
      continue
    with open(atime, "wb") as file:
      file.write(stamp.to_bytes(8, "little"))
    written += 1
  return written


def setup(
  *,
  compile_cache: str | os.PathLike | None = None,
  min_compile_seconds: float = 1.0,
  host_memory: str = "auto",
  cpu_devices: int | None = None,
) -> dict:
  """Applies this process's JAX settings; call before the first JAX computation.

  The first call wins: a later one (an experiment's `main` run inside the tests, whose
  `conftest.py` has set up already) changes nothing and returns the settings in force.

  Args:
    compile_cache: folder of the persistent compilation cache; None: `$TOKENGS_JAX_CACHE`, else
      `.jax_cache` under the working directory. A folder set earlier by the embedding program is
      kept. An uncapped cache (JAX's default) is capped at `COMPILE_CACHE_MAX_BYTES`, which makes
      JAX lock it across the processes sharing the folder (see the module doc); a cap set earlier
      is kept.
    min_compile_seconds: programs that compile faster than this are not cached.
    host_memory: "auto" (`retain_freed_memory` where the computations run on XLA:CPU, glibc's and
      JAX's own settings elsewhere; see the module doc), "retain" (always) or "default" (never,
      for comparisons).
    cpu_devices: virtual CPU devices to create (None: JAX's default, one).

  Returns:
    The settings in force: `compile_cache`, `compile_cache_max_bytes` (JAX's
    `jax_compilation_cache_max_size`; -1, uncapped and unlocked, only without `filelock`),
    `host_memory` (the policy applied, "retain" or
    "default"), `host_memory_reason` ("requested", or what "auto" decided from), `cpu_devices`.
  """
  global _settled
  if _settled is not None:
    return dict(_settled)
  host_memory, reason = resolve_host_memory(host_memory)
  if cpu_devices is not None:
    jax.config.update("jax_num_cpu_devices", cpu_devices)
  if not jax.config.jax_compilation_cache_dir:
    folder = compile_cache or os.environ.get("TOKENGS_JAX_CACHE", ".jax_cache")
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", min_compile_seconds)
  if jax.config.jax_compilation_cache_max_size == -1:  # JAX's default: no cap, and no lock
    if importlib.util.find_spec("filelock") is None:
      warnings.warn(
        "the `filelock` package is missing: the compilation cache stays uncapped and unlocked, "
        "and processes sharing its folder can read each other's half-written entries",
        stacklevel=2,
      )
    else:
      jax.config.update("jax_compilation_cache_max_size", COMPILE_CACHE_MAX_BYTES)
  if jax.config.jax_compilation_cache_max_size > 0:
    _add_missing_access_times(jax.config.jax_compilation_cache_dir)
  if host_memory == "retain":
    retain_freed_memory()
  _settled = dict(
    compile_cache=jax.config.jax_compilation_cache_dir,
    compile_cache_max_bytes=jax.config.jax_compilation_cache_max_size,
    host_memory=host_memory,
    host_memory_reason=reason,
    cpu_devices=cpu_devices,
  )
  return dict(_settled)


def add_arguments(parser: argparse.ArgumentParser) -> None:
  """The `--host-memory` flag of the benchmarks' command lines (pass its value to `setup`)."""
  parser.add_argument(
    "--host-memory",
    choices=HOST_MEMORY_POLICIES,
    default="auto",
    help="auto: retain where the computations run on XLA:CPU, as the experiments do; retain: "
    "tokengs_jax.process.retain_freed_memory() first; default: glibc's and JAX's own settings",
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
