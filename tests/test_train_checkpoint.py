"""Checkpoints (`train.checkpoint`): per-array checksums, restore walking back past damaged steps
with a log line, data states saved and restored per process, the parameters' moving average with
or without one saved."""

import json
import logging
import shutil

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from checkpoints import flip_one_bit, largest_array_file, state_at, truncate_json

from tokengs_jax.train import Checkpointer, OptimConfig, create_train_state, make_optimizer
from tokengs_jax.train.checkpoint import (
  ChecksumError,
  UnusableCheckpointError,
  array_checksums,
  data_state_file,
  data_state_handler,
  verify_checksums,
)


@pytest.fixture
def saved(tmp_path):
  """A directory with good checkpoints at steps 2 and 4."""
  directory = tmp_path / "run"
  checkpointer = Checkpointer(directory, async_save=True)
  for step in (2, 4):
    checkpointer.save(state_at(step), {"position": step})
  checkpointer.wait()
  checkpointer.close()
  return directory


def empty_directory(step_dir):
  for path in step_dir.iterdir():
    shutil.rmtree(path) if path.is_dir() else path.unlink()


def remove_array_metadata(step_dir):
  (step_dir / "state" / "_METADATA").unlink()


def truncate_array_file(step_dir):
  path = largest_array_file(step_dir)
  assert path.stat().st_size > 100_000
  path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def change_a_digit_in_the_json(step_dir):
  path = step_dir / "data" / "process_0-of-1.json"
  text = path.read_text()
  assert '"position": 4' in text or '"position":4' in text
  path.write_text(text.replace("4", "5"))


# (damage, a fragment of the logged reason)
DAMAGE = {
  "json_digit_changed": (
    change_a_digit_in_the_json,
    "checksum mismatch in data/process_0-of-1.json",
  ),
  "emptied": (empty_directory, "FileNotFoundError"),
  "array_metadata_removed": (remove_array_metadata, "pytree structure"),
  "json_truncated": (truncate_json, "JSONDecodeError"),
  "array_file_truncated": (truncate_array_file, "reading array"),
  "bit_flip": (flip_one_bit, "ChecksumError: checksum mismatch in 1 array(s): .params['big']"),
}


@pytest.mark.parametrize("case", DAMAGE)
# When one shard read of a damaged step fails, orbax abandons the step's other reads; their
# coroutines are collected unawaited, sometimes during this test, which pytest reports as an
# unraisable exception. The walk-back itself is what the test checks.
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_restore_walks_back_past_a_damaged_latest_step(saved, case, caplog):
  damage, reason = DAMAGE[case]
  damage(saved / "4")
  checkpointer = Checkpointer(saved)
  assert checkpointer.latest_step() == 4
  with caplog.at_level(logging.WARNING, logger="tokengs_jax.train.checkpoint"):
    state, data_state = checkpointer.restore(state_at(0))
  checkpointer.close()
  assert int(state.step) == 2 and data_state == {"position": 2}
  chex.assert_trees_all_equal(jax.device_get(state), jax.device_get(state_at(2)))
  skipped = [r.getMessage() for r in caplog.records if "unusable, skipped" in r.getMessage()]
  assert len(skipped) == 1 and "step 4" in skipped[0] and reason in skipped[0], skipped
  # set aside for inspection, invisible to orbax: the step number can be saved again
  assert (saved / "4.unusable" / "UNUSABLE.txt").is_file()
  assert Checkpointer(saved).all_steps() == [2]


def test_missing_step_metadata_alone_still_restores_the_latest_step(saved, caplog):
  """orbax's _CHECKPOINT_METADATA is bookkeeping: the arrays still verify, so step 4 is used."""
  (saved / "4" / "_CHECKPOINT_METADATA").unlink()
  with caplog.at_level(logging.WARNING, logger="tokengs_jax.train.checkpoint"):
    state, data_state = Checkpointer(saved).restore(state_at(0))
  assert int(state.step) == 4 and data_state == {"position": 4}
  assert not [r for r in caplog.records if "unusable" in r.getMessage()]


def test_no_usable_step_is_a_clear_error_naming_the_directory(saved):
  flip_one_bit(saved / "4")
  truncate_json(saved / "2")
  with pytest.raises(
    UnusableCheckpointError,
    match=(
      rf"no usable checkpoint in {saved}.*\n  step 4: ChecksumError.*\n  step 2: JSONDecodeError"
    ),
  ):
    Checkpointer(saved).restore(state_at(0))


def test_checksums_detect_a_changed_value_and_name_the_array():
  state = state_at(3)
  sums = array_checksums(state)
  assert sums[".params['big']"] == {"0:64,0:1024": sums[".params['big']"]["0:64,0:1024"]}
  assert verify_checksums(state, sums) == len(jax.tree.leaves(state))
  one_ulp = np.nextafter(np.float32(3), np.float32(4))  # the smallest change of one element
  changed = state.replace(params={**state.params, "bias": state.params["bias"].at[1].set(one_ulp)})
  with pytest.raises(ChecksumError, match=r"\.params\['bias'\]\[0:3\]"):
    verify_checksums(changed, sums)


def test_checksums_of_sharded_arrays_are_per_shard():
  mesh = jax.make_mesh((4,), ("data",), axis_types=(jax.sharding.AxisType.Auto,))
  sharded = jax.device_put(
    jnp.arange(8.0), jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("data"))
  )
  assert sorted(array_checksums({"x": sharded})["['x']"]) == ["0:2", "2:4", "4:6", "6:8"]


def test_a_half_written_save_is_not_a_checkpoint(saved, caplog):
  """A process killed mid-save leaves orbax's temporary directory: never listed, never restored."""
  partial = saved / "6.orbax-checkpoint-tmp-1234567890"
  shutil.copytree(saved / "4", partial)
  truncate_array_file(partial)
  checkpointer = Checkpointer(saved)
  assert checkpointer.all_steps() == [2, 4]
  with caplog.at_level(logging.WARNING, logger="tokengs_jax.train.checkpoint"):
    state, _ = checkpointer.restore(state_at(0))
  assert int(state.step) == 4 and not caplog.records


def test_data_states_are_saved_and_restored_per_process(tmp_path):
  """Two simulated hosts: each process's iterator position goes to its own file of the step and
  comes back to that process only; another process count is refused with a clear message.

  One real process here: process 0 saves through the Checkpointer, and "process 1" writes its file
  into the same step the way orbax runs the data handler on every host."""
  params = {"w": jnp.arange(3.0)}
  state = create_train_state(params, make_optimizer(OptimConfig(schedule="constant")), seed=0)
  state = state.replace(step=jnp.asarray(4, jnp.int32))
  directory = tmp_path / "run"
  host0 = Checkpointer(directory, process_index=0, process_count=2, async_save=False)
  host0.save(state, {"position": 40})
  host0.wait()
  data_dir = directory / "4" / "data"
  import orbax.checkpoint as ocp

  data_state_handler(1, 2).save(data_dir, args=ocp.args.JsonSave({"iterator": {"position": 41}}))
  assert sorted(p.name for p in data_dir.glob("process_*")) == [
    data_state_file(0, 2),
    data_state_file(1, 2),
  ]
  assert json.loads((data_dir / data_state_file(0, 2)).read_text()) == {
    "iterator": {"position": 40}
  }

  for index, position in ((0, 40), (1, 41)):
    restored, data_state = Checkpointer(directory, process_index=index, process_count=2).restore(
      state
    )
    assert data_state == {"position": position} and int(restored.step) == 4
    np.testing.assert_array_equal(restored.params["w"], params["w"])
  with pytest.raises(FileNotFoundError, match=r"process 0 of 3 .*process_0-of-2\.json"):
    Checkpointer(directory, process_index=0, process_count=3).restore(state)


def _averaged(state):
  """`state` keeping a parameter average that differs from its params."""
  return state.replace(ema_params=jax.tree.map(lambda leaf: leaf * 0.5 - 1.0, state.params))


def test_the_parameter_average_round_trips_and_a_checkpoint_without_one_still_loads(
  tmp_path, caplog
):
  """Saved and restored with the state (checksummed as any array); a step saved without one
  restores into a state that keeps one with the average starting from the restored params; a run
  that keeps none drops a saved one. Both logged."""
  directory = tmp_path / "run"
  with Checkpointer(directory, async_save=False) as checkpointer:
    checkpointer.save(state_at(2), {"position": 2})  # written without an average
    checkpointer.save(_averaged(state_at(4)), {"position": 4})
  like = _averaged(state_at(0))
  with Checkpointer(directory) as checkpointer, caplog.at_level(logging.WARNING):
    restored, data_state = checkpointer.restore(like)
    assert int(restored.step) == 4 and data_state == {"position": 4} and not caplog.records
    chex.assert_trees_all_equal(jax.device_get(restored), jax.device_get(_averaged(state_at(4))))

    restored, _ = checkpointer.restore(like, step=2)
    chex.assert_trees_all_equal(
      jax.device_get(restored.ema_params), jax.device_get(restored.params)
    )
    chex.assert_trees_all_equal(jax.device_get(restored.params), jax.device_get(state_at(2).params))
    assert "step 2" in caplog.text and "holds no parameter average" in caplog.text
    caplog.clear()

    restored, _ = checkpointer.restore(state_at(0))  # a run without an average
    assert restored.ema_params is None and int(restored.step) == 4
    chex.assert_trees_all_equal(jax.device_get(restored.params), jax.device_get(state_at(4).params))
    assert "holds a parameter average this run does not keep: dropped" in caplog.text


def test_a_damaged_average_is_caught_by_its_checksum(tmp_path, caplog):
  directory = tmp_path / "run"
  with Checkpointer(directory, async_save=False) as checkpointer:
    checkpointer.save(_averaged(state_at(2)), {"position": 2})
    checkpointer.save(_averaged(state_at(4)), {"position": 4})
  manifest = directory / "4" / "checksums" / data_state_file(0, 1)
  sums = json.loads(manifest.read_text())
  name = next(key for key in sums if key.startswith(".ema_params") and "big" in key)
  sums[name] = {key: crc ^ 1 for key, crc in sums[name].items()}
  manifest.write_text(json.dumps(sums))
  with caplog.at_level(logging.WARNING):
    restored, _ = Checkpointer(directory).restore(_averaged(state_at(0)))
  assert int(restored.step) == 2 and "checksum mismatch in 1 array(s): .ema_params['big']" in (
    caplog.text
  )
