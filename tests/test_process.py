"""`process`: the settings `setup` applies, and `retain_freed_memory`: a repeated XLA:CPU run stops
page-faulting its temporaries.

Each case runs in a fresh interpreter: the policy is process-wide and must precede the first
computation, and this test process has long since run many.
"""

import json
import subprocess
import sys
import textwrap

import pytest

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
    "host_memory": "default",
    "cpu_devices": 3,
  }
  assert seen["again"] == seen["first"]
  assert seen["devices"] == 3 and seen["cache"] == str(tmp_path)
  assert seen["dispatch"] is True  # "default" leaves JAX's asynchronous dispatch on


def test_setup_rejects_an_unknown_memory_policy():
  script = "from tokengs_jax import process; process.setup(host_memory='keep')"
  done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
  assert done.returncode != 0 and "host_memory must be one of" in done.stderr
