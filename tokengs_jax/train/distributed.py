"""Process setup, the device mesh, and placing host data on it (single- or multi-host).

Launch on N hosts (each with its local accelerators): run the same command on every host with

    TOKENGS_COORDINATOR=host0:1234 TOKENGS_NUM_PROCESSES=N TOKENGS_PROCESS_ID=i \
        python -m experiments.re10k ...

or, on one machine, `python -m experiments.launch --processes N -- python -m experiments.re10k ...`
(sets those variables); on SLURM, Cloud TPU, Open MPI and Kubernetes set TOKENGS_DISTRIBUTED=1
and `jax.distributed.initialize()` reads the scheduler's variables (docs/multihost.md).
Every process then builds the same mesh over all global devices, reads its own shard of the data
(`process_index` / `process_count` pick the shard), and turns its local batch into one global
array with `shard_batch`. Each process's local batch is `global_batch / process_count` examples.
"""

from __future__ import annotations

import itertools
import os

import jax
import numpy as np
import orbax.checkpoint as ocp
from jax.sharding import AxisType, Mesh, NamedSharding
from jax.sharding import PartitionSpec as P


def initialize() -> None:
  """Calls `jax.distributed.initialize` when a multi-process run is configured, else nothing.

  Reads TOKENGS_COORDINATOR / TOKENGS_NUM_PROCESSES / TOKENGS_PROCESS_ID when set; on managed
  clusters (TPU pods, SLURM, Open MPI, Kubernetes JobSet) TOKENGS_DISTRIBUTED=1 lets JAX
  auto-detect them. TOKENGS_HEARTBEAT_TIMEOUT (seconds, jax's default 100) bounds how long the
  survivors wait before aborting when a process dies without a launcher to stop them. CPU
  processes talk through gloo collectives (jax's default). Must run before any other JAX call.
  """
  coordinator = os.environ.get("TOKENGS_COORDINATOR")
  if coordinator is None and os.environ.get("TOKENGS_DISTRIBUTED") != "1":
    return
  timeouts = {}
  if "TOKENGS_HEARTBEAT_TIMEOUT" in os.environ:
    timeouts["heartbeat_timeout_seconds"] = int(os.environ["TOKENGS_HEARTBEAT_TIMEOUT"])
  if coordinator is not None:
    jax.distributed.initialize(
      coordinator_address=coordinator,
      num_processes=int(os.environ["TOKENGS_NUM_PROCESSES"]),
      process_id=int(os.environ["TOKENGS_PROCESS_ID"]),
      **timeouts,
    )
  else:
    jax.distributed.initialize(**timeouts)
  print(
    f"[distributed] process {jax.process_index()} of {jax.process_count()}: "
    f"{jax.local_device_count()} local of {jax.device_count()} devices",
    flush=True,
  )


_BARRIER_CALLS = itertools.count()


def barrier(name: str, timeout_s: int = 1800) -> None:
  """Waits until every process reaches `barrier(name)` (coordination service; no collective).

  On CPU, gloo sets up a communicator the first time a compiled program runs a collective and
  gives up when the processes arrive more than 30 s apart (`GetKeyValue() timed out`), which
  uneven compile times on a loaded machine exceed; meeting here right before that first run keeps
  them together. No-op on one process. Every process must make the same sequence of calls (a
  call count makes the coordination service's barrier ids unique).
  """
  if jax.process_count() > 1:
    ocp.multihost.get_barrier_sync_fn()(
      key=f"{name}_{next(_BARRIER_CALLS)}", timeout_ms=timeout_s * 1000
    )


def make_mesh(data: int | None = None, model: int = 1, devices=None) -> Mesh:
  """A ("data", "model") mesh with Auto axes (GSPMD propagation; jax 0.10 defaults to Explicit).

  Args:
    data: size of the data axis; default all devices / model.
    model: size of the model axis (1 until parameters are sharded).
    devices: devices to use; default `jax.devices()` (all processes).
  """
  devices = jax.devices() if devices is None else list(devices)
  data = len(devices) // model if data is None else data
  return jax.make_mesh(
    (data, model),
    ("data", "model"),
    axis_types=(AxisType.Auto,) * 2,
    devices=devices[: data * model],
  )


def shard_batch(local_batch: dict, mesh: Mesh) -> dict:
  """Global arrays sharded over "data" from each process's local examples `[B_local, ...]`."""
  sharding = NamedSharding(mesh, P("data"))
  return jax.tree.map(
    lambda x: jax.make_array_from_process_local_data(sharding, np.asarray(x)), local_batch
  )


def replicate(tree, mesh: Mesh):
  """Places a host pytree (identical on every process) replicated over `mesh`."""
  sharding = NamedSharding(mesh, P())

  def place(x):
    x = np.asarray(x)
    return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])

  return jax.tree.map(place, tree)
