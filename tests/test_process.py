"""`process`: the settings `setup` applies, where "auto" applies the host memory policy, and
`retain_freed_memory`: a repeated XLA:CPU run stops page-faulting its temporaries.

Each case runs in a fresh interpreter: the policy is process-wide and must precede the first
computation, and this test process has long since run many.
"""

import json
import os
import subprocess
import sys
import textwrap

import pytest

from tokengs_jax import process

_PROBE = textwrap.dedent(
  """
  import json, resource, sys
  import jax, jax.numpy as jnp
  from tokengs_jax import process

  applied = process.retain_freed_memory() if sys.argv[1] == "retain" else None
  # sin(x) feeds a dot, so XLA materialises it: a 64 MB temporary buffer per run.
  program = jax.jit(lambda x: jnp.sin(x) @ jnp.ones((x.shape[1],), x.dtype))
  x = jnp.full((4096, 4096), 0.5, jnp.float32)
  temp_mb = program.lower(x).compile().memory_analysis().temp_size_in_bytes / 2**20
  for _ in range(2):
    program(x).block_until_ready()
  faults = []
  for _ in range(10):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    program(x).block_until_ready()
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
  print(json.dumps(dict(applied=applied, temp_mb=temp_mb, faults=faults)))
  """
)


def _probe(mode: str) -> dict:
  done = subprocess.run(
    [sys.executable, "-c", _PROBE, mode], capture_output=True, text=True, timeout=300, check=True
  )
  return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt is Linux-only")
def test_repeated_runs_reuse_their_temporary_buffer():
  default, retained = _probe("default"), _probe("retain")
  assert default["temp_mb"] >= 64 and retained["temp_mb"] >= 64
  # 64 MB of 4 kB pages is 16,384 faults; with transparent huge pages it can be as few as 32.
  assert min(default["faults"]) >= 32, default
  assert retained["applied"] is True
  # Mostly none: about one run in ten still gets fresh pages (measured 4 of 36 runs), when a run
  # allocates before the previous run's buffer is back in the heap.
  assert sum(faults < 16 for faults in retained["faults"]) >= 5, retained


def test_a_late_call_says_the_dispatch_setting_cannot_apply():
  late = textwrap.dedent(
    """
    import warnings
    import jax.numpy as jnp
    from tokengs_jax import process

    jnp.zeros(1).block_until_ready()  # creates the CPU client
    with warnings.catch_warnings(record=True) as caught:
      warnings.simplefilter("always")
      process.retain_freed_memory()
    print([str(w.message) for w in caught])
    """
  )
  done = subprocess.run([sys.executable, "-c", late], capture_output=True, text=True, check=True)
  assert "after the first JAX computation" in done.stdout


def test_setup_applies_its_settings_once_and_the_first_call_wins(tmp_path):
  script = textwrap.dedent(
    f"""
    import json
    import jax
    from tokengs_jax import process

    first = process.setup(compile_cache={str(tmp_path)!r}, host_memory="default", cpu_devices=3)
    again = process.setup(compile_cache="elsewhere", cpu_devices=1)
    print(json.dumps(dict(
      first=first, again=again, devices=jax.device_count(),
      cache=jax.config.jax_compilation_cache_dir,
      dispatch=jax.config.read("jax_cpu_enable_async_dispatch"),
    )))
    """
  )
  done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
  seen = json.loads(done.stdout.strip().splitlines()[-1])
  assert seen["first"] == {
    "compile_cache": str(tmp_path),
    "compile_cache_max_bytes": process.COMPILE_CACHE_MAX_BYTES,
    "host_memory": "default",
    "host_memory_reason": "requested",
    "cpu_devices": 3,
  }
  assert seen["again"] == seen["first"]
  assert seen["devices"] == 3 and seen["cache"] == str(tmp_path)
  assert seen["dispatch"] is True  # "default" leaves JAX's asynchronous dispatch on


def test_setup_locks_the_shared_compile_cache_and_can_use_a_folder_written_unlocked(tmp_path):
  # JAX's default (no cap) neither locks its cache folder nor writes atomically: processes sharing
  # it read each other's half-written entries (benchmarks/compile_cache_race.py). A cap turns the
  # lock on; the entry below has no `-atime` file, as an uncapped cache leaves, and would make every
  # capped write fail ("Error writing persistent compilation cache entry") unless setup adds one.
  old = tmp_path / "jit_old-0123456789abcdef-cache"
  old.write_bytes(b"an entry an uncapped cache wrote")
  os.utime(old, ns=(1_000_000_000, 1_000_000_000))
  script = textwrap.dedent(
    f"""
    import json, os, warnings
    import jax, jax.numpy as jnp
    from tokengs_jax import process

    settings = process.setup(compile_cache={str(tmp_path)!r}, min_compile_seconds=0,
                             host_memory="default")
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    with warnings.catch_warnings(record=True) as caught:
      warnings.simplefilter("always")
      jax.jit(lambda x: jnp.sin(x) @ x.T)(jnp.ones((32, 32))).block_until_ready()
    print(json.dumps(dict(
      settings=settings, max_size=jax.config.jax_compilation_cache_max_size,
      warnings=[str(w.message) for w in caught], files=sorted(os.listdir({str(tmp_path)!r})),
    )))
    """
  )
  done = subprocess.run(
    [sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=True
  )
  seen = json.loads(done.stdout.strip().splitlines()[-1])
  assert seen["max_size"] == process.COMPILE_CACHE_MAX_BYTES > 0
  assert seen["settings"]["compile_cache_max_bytes"] == process.COMPILE_CACHE_MAX_BYTES
  assert seen["warnings"] == []
  assert ".lockfile" in seen["files"]  # JAX's cross-process lock was taken
  entries = [name.removesuffix("-cache") for name in seen["files"] if name.endswith("-cache")]
  assert len(entries) >= 2 and all(f"{key}-atime" in seen["files"] for key in entries), seen
  stamp = (tmp_path / "jit_old-0123456789abcdef-atime").read_bytes()
  assert int.from_bytes(stamp, "little") == 1_000_000_000  # its modification time: oldest first


def test_setup_rejects_an_unknown_memory_policy():
  script = "from tokengs_jax import process; process.setup(host_memory='keep')"
  done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
  assert done.returncode != 0 and "host_memory must be one of" in done.stderr


# `setup` with the policy given on the command line, in a process where glibc's `mallopt` is
# recorded (and still called) and whose NVIDIA device check answers as told: what was applied.
_SETUP = textwrap.dedent(
  """
  import ctypes, json, sys
  import jax
  from jax._src import xla_bridge
  from tokengs_jax import process

  real = ctypes.CDLL("libc.so.6").mallopt
  real.argtypes, real.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
  calls = []

  class Mallopt:
    def __call__(self, param, value):
      calls.append([param, value])
      return real(param, value)

  class LibC:
    def __init__(self, name):
      self.mallopt = Mallopt()

  ctypes.CDLL = LibC
  process.hardware_utils.has_visible_nvidia_gpu = lambda: sys.argv[2] == "gpu"
  settings = process.setup(host_memory=sys.argv[1])
  print(json.dumps(dict(
    settings=settings, mallopt=calls,
    dispatch=jax.config.read("jax_cpu_enable_async_dispatch"),
    backends=xla_bridge.backends_are_initialized(),
  )))
  """
)
_RETAINED = [[process._M_MMAP_MAX, 0], [process._M_TRIM_THRESHOLD, process._NEVER_TRIM]]


def _setup(tmp_path, host_memory="auto", gpu=False, platforms=None, plugins=()) -> dict:
  """Runs `_SETUP` with only the given platform setting and fake plugins (`jax_plugins`
  namespace modules on the path, which JAX would import and start only at its first
  computation): none of the host's own platform settings."""
  env = {
    key: value
    for key, value in os.environ.items()
    if key not in ("JAX_PLATFORMS", "PJRT_NAMES_AND_LIBRARY_PATHS", "TPU_LIBRARY_PATH")
  }
  if platforms is not None:
    env["JAX_PLATFORMS"] = platforms
  for plugin in plugins:
    folder = tmp_path / "jax_plugins" / plugin
    folder.mkdir(parents=True)
    (folder / "__init__.py").write_text("def initialize():\n  pass\n")
  env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(tmp_path), env.get("PYTHONPATH")]))
  argv = [sys.executable, "-c", _SETUP, host_memory, "gpu" if gpu else "none"]
  done = subprocess.run(argv, capture_output=True, text=True, env=env, timeout=120, check=True)
  seen = json.loads(done.stdout.strip().splitlines()[-1])
  assert seen["backends"] is False, "setup created a JAX client"
  return seen


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt is Linux-only")
@pytest.mark.skipif(
  bool(process._installed_plugins()), reason="this host has an accelerator plugin"
)
def test_auto_retains_freed_memory_on_a_host_without_accelerator_plugins(tmp_path):
  seen = _setup(tmp_path)
  assert seen["settings"]["host_memory"] == "retain"
  assert seen["settings"]["host_memory_reason"].startswith("auto: cpu")
  assert seen["mallopt"] == _RETAINED and seen["dispatch"] is False


@pytest.mark.parametrize(
  "case",
  [
    dict(platforms="cuda"),
    dict(platforms="tpu,cpu"),
    dict(plugins=["xla_fake_accelerator"]),
    dict(plugins=["xla_cuda12"], gpu=True),
  ],
  ids=["jax_platforms=cuda", "jax_platforms=tpu,cpu", "plugin", "cuda-plugin-with-gpu"],
)
def test_auto_leaves_the_defaults_where_computations_run_on_an_accelerator(tmp_path, case):
  seen = _setup(tmp_path, **case)
  assert seen["settings"]["host_memory"] == "default", seen
  assert seen["settings"]["host_memory_reason"].startswith("auto: accelerator"), seen
  assert seen["mallopt"] == [] and seen["dispatch"] is True


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt is Linux-only")
@pytest.mark.parametrize(
  "case",
  [
    dict(platforms="cpu", plugins=["xla_fake_accelerator"]),
    dict(plugins=["xla_cuda12"], gpu=False),
  ],
  ids=["jax_platforms=cpu-over-a-plugin", "cuda-plugin-without-gpu"],
)
def test_auto_retains_where_jax_would_fall_back_to_or_is_told_cpu(tmp_path, case):
  seen = _setup(tmp_path, **case)
  assert seen["settings"]["host_memory"] == "retain", seen
  assert seen["mallopt"] == _RETAINED and seen["dispatch"] is False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt is Linux-only")
def test_an_explicit_choice_wins_over_the_platform(tmp_path):
  retained = _setup(tmp_path, "retain", platforms="cuda")
  assert retained["settings"]["host_memory"] == "retain"
  assert retained["settings"]["host_memory_reason"] == "requested"
  assert retained["mallopt"] == _RETAINED and retained["dispatch"] is False
  left = _setup(tmp_path, "default", platforms="cpu")
  assert left["settings"]["host_memory"] == "default" and left["mallopt"] == []
  assert left["dispatch"] is True
