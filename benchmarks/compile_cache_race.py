"""Several processes sharing one persistent compilation cache folder at once (as pytest-xdist
workers and side-by-side experiments do): do they read each other's half-written entries, and
what reaches XLA? Run by hand; not part of the test suite (docs/robustness.md, "Processes").

    python benchmarks/compile_cache_race.py entries   # LRUCache.get racing LRUCache.put, 8 MB entries
    python benchmarks/compile_cache_race.py jit       # real jit compiles, 4 processes, shuffled order
    python benchmarks/compile_cache_race.py truncated # a real entry cut short: what loading it does

Each mode runs twice by default: with JAX's own default cache (`jax_compilation_cache_max_size`
-1: unlocked, no eviction) and with what `tokengs_jax.process.setup` configures (`--only` picks
one). A read is "torn" when the bytes `LRUCache.get` returned do not decompress (JAX then warns
"Error reading persistent compilation cache entry" and compiles again).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import random
import shutil
import subprocess
import sys
import tempfile
import time

CONFIGS = ("jax-default", "setup")


def _configure(config: str, folder: str) -> None:
  import jax

  from tokengs_jax import process

  if config == "jax-default":
    jax.config.update("jax_compilation_cache_dir", folder)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
  else:
    process.setup(compile_cache=folder, min_compile_seconds=0, host_memory="default")
  jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def _count_torn_reads(stats: dict) -> None:
  """Wraps JAX's file cache (private: the stress measures it, nothing else uses this)."""
  from jax._src import compilation_cache, lru_cache

  get = lru_cache.LRUCache.get

  def checked(self, key):
    value = get(self, key)
    stats["gets"] += 1
    if value is not None:
      stats["hits"] += 1
      try:
        compilation_cache.decompress_executable(value)
      except Exception:
        stats["torn"] += 1
    return value

  lru_cache.LRUCache.get = checked


def entries_worker(role: str, config: str, folder: str, index: int, start: float) -> dict:
  """Writers put 20 fresh 8 MB entries each; readers get every key in a loop for 6 s."""
  import jax
  from jax._src import compilation_cache, lru_cache

  _configure(config, folder)
  cache = lru_cache.LRUCache(folder, max_size=jax.config.jax_compilation_cache_max_size)
  stats = dict(gets=0, hits=0, torn=0)
  while time.time() < start:
    time.sleep(0.001)
  if role == "writer":
    for i in range(20):
      cache.put(f"w{index}-{i}", compilation_cache.compress_executable(os.urandom(8 << 20)))
    return stats
  _count_torn_reads(stats)
  end = time.time() + 6
  while time.time() < end:
    for key in (f"w{w}-{i}" for w in range(2) for i in range(20)):
      cache.get(key)
  return stats


def jit_worker(config: str, folder: str, index: int, start: float) -> dict:
  """Compiles 12 distinct programs in a shuffled order, 4 rounds (jax.clear_caches between, so
  rounds after the first read the folder back); every result must equal a fixed reference."""
  import warnings

  import jax
  import jax.numpy as jnp

  _configure(config, folder)
  stats = dict(gets=0, hits=0, torn=0, read_warnings=0, wrong=0)
  _count_torn_reads(stats)

  def program(k):
    def f(x):
      for i in range(25 + k):
        x = jnp.tanh(x @ x.T * 0.01 + i * k)
      return x.sum()

    return f

  x = jnp.ones((48, 48), jnp.float32)
  rng = random.Random(index)
  while time.time() < start:
    time.sleep(0.001)
  results = {}
  with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    for _ in range(4):
      order = list(range(12))
      rng.shuffle(order)
      for k in order:
        value = float(jax.jit(program(k))(x))
        if results.setdefault(k, value) != value:
          stats["wrong"] += 1
      jax.clear_caches()
  stats["read_warnings"] = sum(
    "reading persistent compilation cache" in str(w.message) for w in caught
  )
  stats["results"] = [results[k] for k in range(12)]
  return stats


def truncated(config: str, folder: str) -> list[dict]:
  """Compiles one program into `folder`, then reloads it in fresh processes with its entry cut
  to 0, 1, 10%, 50%, 99% of its bytes and with a valid zstd frame around a truncated executable."""
  from jax._src import compilation_cache

  probe = (
    "import sys, warnings, json; sys.path.insert(0, %r)\n"
    "from benchmarks.compile_cache_race import _configure\n"
    "_configure(sys.argv[1], sys.argv[2])\n"
    "import jax, jax.numpy as jnp\n"
    "f = lambda x: [x := jnp.sin(x) @ x.T + i for i in range(30)][-1].sum()\n"
    "with warnings.catch_warnings(record=True) as w:\n"
    "  warnings.simplefilter('always')\n"
    "  v = float(jax.jit(f)(jnp.ones((64, 64)) * 0.01))\n"
    "print(json.dumps(dict(value=v, warnings=[str(m.message)[:120] for m in w])))\n"
  ) % str(pathlib.Path(__file__).resolve().parent.parent)

  def load():
    done = subprocess.run(
      [sys.executable, "-c", probe, config, folder], capture_output=True, text=True, timeout=300
    )
    last = done.stdout.strip().splitlines()[-1] if done.returncode == 0 else done.stderr[-200:]
    return done.returncode, last

  print("populate:", load())
  entry = max(pathlib.Path(folder).glob("jit_*-cache"), key=lambda p: p.stat().st_size)
  whole = entry.read_bytes()
  raw = compilation_cache.decompress_executable(whole)
  cases = {f"cut to {n} of {len(whole)} bytes": whole[:n] for n in (0, 1, len(whole) // 10)}
  cases |= {f"cut to {n} of {len(whole)} bytes": whole[:n] for n in (len(whole) // 2,)}
  cases[f"cut to {len(whole) - 1} bytes"] = whole[:-1]
  half = raw[: len(raw) // 2] + raw[-8:]  # keeps the trailing compile time
  cases["valid zstd frame, executable cut in half"] = compilation_cache.compress_executable(half)
  rows = []
  for name, blob in cases.items():
    entry.write_bytes(blob)
    rc, last = load()
    rows.append(dict(case=name, rc=rc, result=last))
    print(f"  {name}: rc {rc}: {last}")
  entry.write_bytes(whole)
  return rows


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("mode", choices=("entries", "jit", "truncated"))
  parser.add_argument("--only", choices=CONFIGS)
  parser.add_argument("--processes", type=int, default=4)
  parser.add_argument("--worker", nargs=4, help=argparse.SUPPRESS)
  args = parser.parse_args()
  if args.worker:
    role, config, folder, index = args.worker
    start = float(os.environ["RACE_START"])
    if args.mode == "entries":
      stats = entries_worker(role, config, folder, int(index), start)
    else:
      stats = jit_worker(config, folder, int(index), start)
    print(json.dumps(stats))
    return
  for config in [args.only] if args.only else CONFIGS:
    folder = tempfile.mkdtemp(prefix=f"cache_race_{config}_")
    try:
      if args.mode == "truncated":
        print(config)
        truncated(config, folder)
        continue
      env = dict(os.environ, RACE_START=str(time.time() + 4))
      roles = (
        ["writer", "writer", "reader", "reader"]
        if args.mode == "entries"
        else ["p"] * args.processes
      )
      began = time.perf_counter()
      procs = [
        subprocess.Popen(
          [sys.executable, __file__, args.mode, "--worker", role, config, folder, str(i)],
          stdout=subprocess.PIPE,
          text=True,
          env=env,
        )
        for i, role in enumerate(roles)
      ]
      outs = [p.communicate()[0].strip().splitlines() for p in procs]
      seconds = time.perf_counter() - began - 4
      stats = [
        json.loads(out[-1]) if p.returncode == 0 and out else None for p, out in zip(procs, outs)
      ]
      total = {k: sum(s[k] for s in stats if s) for k in ("gets", "hits", "torn")}
      extra = ""
      if args.mode == "jit":
        done = [s for s in stats if s]
        extra = (
          f", read warnings {sum(s['read_warnings'] for s in done)}, wrong results "
          f"{sum(s['wrong'] for s in done)}, processes agree: "
          f"{len({tuple(s['results']) for s in done}) == 1}"
        )
      print(
        f"{config}: exit codes {[p.returncode for p in procs]}, {total['gets']} gets, "
        f"{total['hits']} hits, {total['torn']} torn{extra}; {seconds:.1f} s"
      )
    finally:
      shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
  sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent))
  main()
