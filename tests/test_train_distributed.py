"""`train.distributed` in one process over the 4 virtual CPU devices (tests/conftest.py): the mesh
shapes, a local batch split over "data" in order, replication, and the multi-process set-up calls
that one process skips or makes with the variables it was given."""

import jax
import numpy as np
import pytest
from jax.sharding import AxisType
from jax.sharding import PartitionSpec as P

from tokengs_jax.train import distributed


def test_the_mesh_spans_every_device_on_data_unless_told():
  assert jax.device_count() == 4
  mesh = distributed.make_mesh()
  assert dict(mesh.shape) == {"data": 4, "model": 1}
  assert mesh.axis_types == (AxisType.Auto, AxisType.Auto)
  assert dict(distributed.make_mesh(model=2).shape) == {"data": 2, "model": 2}
  two = distributed.make_mesh(data=2)
  assert dict(two.shape) == {"data": 2, "model": 1}
  assert list(two.devices.flat) == jax.devices()[:2]
  one = distributed.make_mesh(devices=jax.devices()[3:])
  assert dict(one.shape) == {"data": 1, "model": 1} and list(one.devices.flat) == jax.devices()[3:]


def test_shard_batch_splits_the_examples_over_data_in_order():
  mesh = distributed.make_mesh()
  local = {"x": np.arange(24, dtype=np.float32).reshape(8, 3), "meta": {"i": np.arange(8)}}
  batch = distributed.shard_batch(local, mesh)
  x = batch["x"]
  assert x.shape == (8, 3) and x.sharding.spec == P("data")
  np.testing.assert_array_equal(x, local["x"])
  np.testing.assert_array_equal(batch["meta"]["i"], np.arange(8))
  # device k holds examples 2k and 2k + 1
  shards = {s.device: np.asarray(s.data) for s in x.addressable_shards}
  for k, device in enumerate(mesh.devices.flat):
    np.testing.assert_array_equal(shards[device], local["x"][2 * k : 2 * k + 2])


def test_replicate_puts_the_whole_array_on_every_device():
  mesh = distributed.make_mesh()
  tree = distributed.replicate({"w": np.arange(6.0).reshape(2, 3)}, mesh)
  assert tree["w"].sharding.spec == P() and len(tree["w"].addressable_shards) == 4
  for shard in tree["w"].addressable_shards:
    np.testing.assert_array_equal(shard.data, np.arange(6.0).reshape(2, 3))


def test_one_process_initialises_and_meets_at_barriers_without_a_coordinator(monkeypatch):
  def refuse(*args, **kwargs):
    raise AssertionError("called in a single-process run")

  for name in ("TOKENGS_COORDINATOR", "TOKENGS_DISTRIBUTED"):
    monkeypatch.delenv(name, raising=False)
  monkeypatch.setattr(jax.distributed, "initialize", refuse)
  monkeypatch.setattr(distributed.ocp.multihost, "get_barrier_sync_fn", refuse)
  distributed.initialize()
  distributed.barrier("start")


@pytest.mark.parametrize("coordinator", [True, False])
def test_initialize_passes_the_launch_variables_to_jax(monkeypatch, coordinator):
  calls = []
  monkeypatch.setattr(jax.distributed, "initialize", lambda **kwargs: calls.append(kwargs))
  monkeypatch.setenv("TOKENGS_HEARTBEAT_TIMEOUT", "30")
  if coordinator:
    monkeypatch.setenv("TOKENGS_COORDINATOR", "host0:1234")
    monkeypatch.setenv("TOKENGS_NUM_PROCESSES", "3")
    monkeypatch.setenv("TOKENGS_PROCESS_ID", "2")
  else:  # a managed cluster: jax reads the scheduler's variables
    monkeypatch.delenv("TOKENGS_COORDINATOR", raising=False)
    monkeypatch.setenv("TOKENGS_DISTRIBUTED", "1")
  distributed.initialize()
  expected = {"heartbeat_timeout_seconds": 30}
  if coordinator:
    expected |= {"coordinator_address": "host0:1234", "num_processes": 3, "process_id": 2}
  assert calls == [expected]
