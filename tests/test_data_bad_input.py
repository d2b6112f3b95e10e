"""Bad input (issue 16): each damaged input raises its reader's own error type and, with
`skip_bad`, costs only itself: every good scene next to it is kept, and the rejection is counted
and logged. Nothing hangs (a SIGALRM guard fails a test instead of letting it wait forever)."""

import contextlib
import dataclasses
import json
import logging
import os
import pickle
import resource
import signal
import struct
import time
import zipfile

import numpy as np
import pytest

from tokengs_jax.data import (
  BadExampleError,
  BoundedSamplerConfig,
  ChunkedSceneSource,
  ExampleConfig,
  InputPipeline,
  NoUsableExamplesError,
  chunks,
  make_example,
  write_chunk,
)
from tokengs_jax.data.chunks import ChunkError, UnsafeChunkError

SAMPLER = BoundedSamplerConfig(2, 1, 2, 4, 0, 0, 2, 4)
CONFIG = ExampleConfig((8, 8), SAMPLER, 0.25)


@contextlib.contextmanager
def _deadline(seconds):
  """Fails (instead of hanging) if the block takes longer than `seconds`."""

  def expire(*_):
    raise TimeoutError(f"still running after {seconds} s: a hang")

  previous = signal.signal(signal.SIGALRM, expire)
  signal.alarm(seconds)
  try:
    yield
  finally:
    signal.alarm(0)
    signal.signal(signal.SIGALRM, previous)


def _scene(key, frames=5, seed=0, size=8):
  rng = np.random.default_rng(seed)
  c2w = np.tile(np.eye(4), (frames, 1, 1))
  c2w[:, :3, 3] = np.cumsum(rng.normal(scale=0.1, size=(frames, 3)), axis=0)
  intrinsics = np.tile([10.0, 10.0, size / 2, size / 2], (frames, 1))
  images = rng.integers(0, 255, (frames, size, size, 3), dtype=np.uint8)
  return {"key": key, "c2w": c2w, "intrinsics": intrinsics, "images": images}


def _records(keys, **kwargs):
  return [
    chunks.scenes._scene_to_record(_scene(key, seed=i, **kwargs), 90) for i, key in enumerate(keys)
  ]


def _index(root, mapping):
  (root / "index.json").write_text(json.dumps(mapping))


# ---- 1. per-scene rejection, counted and logged


def test_one_nan_camera_drops_only_its_scene(tmp_path, caplog):
  records = _records([f"s{i:02d}" for i in range(50)], frames=3)
  records[17]["cameras"][1, 8] = np.nan
  chunks.save_tensor_archive(tmp_path / "000000.torch", records)
  (tmp_path / "000001.torch").write_bytes(b"PK\x03\x04 a truncated chunk")
  with pytest.raises(ChunkError, match=r"000000\.torch scene 's17'.*NaN"):
    ChunkedSceneSource(tmp_path, skip_bad=False)
  with caplog.at_level(logging.WARNING, logger="tokengs_jax.data"):
    source = ChunkedSceneSource(tmp_path, skip_bad=True)
  assert len(source) == 49 and "s17" not in {e.key for e in source.entries}
  assert source.rejections.counts == {"bad_scene": 1, "bad_chunk": 1}
  assert any("s17" in r.getMessage() and "bad_scene" in r.getMessage() for r in caplog.records)
  assert any(
    "000001.torch" in r.getMessage() and "bad_chunk" in r.getMessage() for r in caplog.records
  )
  summary = InputPipeline(
    source, CONFIG, batch_size=1, shard_index=0, shard_count=1
  ).rejection_summary()
  assert (
    "source: 2 rejected (bad_chunk 1, bad_scene 1)" in summary and "pipeline: nothing" in summary
  )
  # scenes after the bad one in the same chunk are still addressable and correct
  assert (
    source[source.entries.index(next(e for e in source.entries if e.key == "s18"))]["key"] == "s18"
  )


def test_bad_camera_scenes_by_key_are_counted_once(tmp_path):
  records = _records(["good", "nanpose", "negfocal"])
  records[1]["cameras"][0, 7] = np.inf
  records[2]["cameras"][:, 0] *= -1  # fx < 0
  chunks.save_tensor_archive(tmp_path / "000000.torch", records)
  _index(tmp_path, {"good": "000000.torch", "nanpose": "000000.torch", "negfocal": "000000.torch"})
  source = ChunkedSceneSource(tmp_path, keys=["negfocal", "good", "nanpose"], skip_bad=True)
  assert [e.key for e in source.entries] == ["good"]
  assert source.rejections.counts == {"bad_scene": 2}
  assert any("'negfocal'" in m and "focal" in m for m in source.rejections.messages)


# ---- 2. no hang: nothing usable, and index entries that are not plain files in the root


def test_all_bad_examples_raise_promptly_instead_of_hanging(tmp_path):
  write_chunk(tmp_path / "000000.torch", [_scene(f"short{i}", frames=10, seed=i) for i in range(3)])
  long_gaps = ExampleConfig((8, 8), BoundedSamplerConfig(2, 1, 45, 135, 0, 0, 45, 135), 0.25)
  pipeline = InputPipeline(
    ChunkedSceneSource(tmp_path),
    long_gaps,
    batch_size=2,
    shard_index=0,
    shard_count=1,
    skip_bad=True,
  )  # num_epochs=None: repeats forever
  start = time.perf_counter()
  with (
    _deadline(60),
    pytest.raises(NoUsableExamplesError, match=r"(?s)256 examples.*NotEnoughFramesError 256"),
  ):
    next(iter(pipeline))
  assert time.perf_counter() - start < 30
  assert pipeline.rejections.counts == {"NotEnoughFramesError": 256}


def test_good_examples_between_bad_ones_are_all_kept(tmp_path):
  scenes = [_scene(f"good{i}", seed=i) for i in range(4)] + [
    _scene(f"short{i}", frames=2) for i in range(3)
  ]
  write_chunk(tmp_path / "000000.torch", scenes)
  pipeline = InputPipeline(
    ChunkedSceneSource(tmp_path),
    CONFIG,
    batch_size=1,
    shard_index=0,
    shard_count=1,
    skip_bad=True,
    num_epochs=1,
    max_consecutive_bad=4,
  )
  assert sorted(int(b["scene_index"][0]) for b in pipeline) == [0, 1, 2, 3]
  assert pipeline.rejections.counts == {"NotEnoughFramesError": 3}


def test_an_empty_source_is_an_error_not_an_endless_wait(tmp_path):
  (tmp_path / "000000.torch").write_bytes(b"garbage")
  source = ChunkedSceneSource(tmp_path, skip_bad=True)
  with pytest.raises(NoUsableExamplesError, match="source has 0.*bad_chunk 1"):
    InputPipeline(source, CONFIG, batch_size=1, shard_index=0, shard_count=1)


def test_index_entries_must_be_regular_files_inside_the_root(tmp_path):
  root, outside = tmp_path / "root", tmp_path / "elsewhere"
  root.mkdir()
  outside.mkdir()
  write_chunk(root / "000000.torch", [_scene("good")])
  write_chunk(outside / "000000.torch", [_scene("escaped")])
  os.mkfifo(root / "fifo.torch")
  os.symlink("/dev/zero", root / "zero.torch")
  os.symlink(outside / "000000.torch", root / "link.torch")
  _index(
    root,
    {
      "good": "000000.torch",
      "escaped": "../elsewhere/000000.torch",
      "zero": "/dev/zero",
      "fifo": "fifo.torch",
      "zerolink": "zero.torch",
      "link": "link.torch",
      "dir": ".",
      "number": 7,
    },
  )
  keys = ["escaped", "zero", "fifo", "zerolink", "link", "dir", "number", "good"]
  with _deadline(30):
    with pytest.raises(ChunkError, match="outside the data root"):
      ChunkedSceneSource(root, keys=keys)
    source = ChunkedSceneSource(root, keys=keys, skip_bad=True)
    assert [e.key for e in source.entries] == ["good"]
    # outside the root: escaped, /dev/zero, zero.torch -> /dev/zero, link.torch -> elsewhere;
    # 7 is not a name; the FIFO and "." (the root directory) are refused when opened
    assert source.rejections.counts == {"bad_index_entry": 5, "bad_chunk": 2}
    assert any("fifo.torch" in m and "not a regular file" in m for m in source.rejections.messages)
    scanned = ChunkedSceneSource(root, skip_bad=True)  # no index: every *.torch in the root
    assert [e.key for e in scanned.entries] == ["good"]
    assert scanned.rejections.counts == {"bad_chunk": 3}


# ---- 4. the safe unpickler: no state on shared globals, allocation bounded, own error type


def _archive_with_pickle(path, payload, extra=()):
  with zipfile.ZipFile(path, "w") as archive:
    archive.writestr(f"{path.stem}/data.pkl", payload)
    for name, data in extra:
      archive.writestr(f"{path.stem}/{name}", data)


BUILD_ON_STORAGE = b"\x80\x02ctorch\nFloatStorage\n}X\x05\x00\x00\x00dtypeX\x04\x00\x00\x00int8sb."
BUILD_SLOTSTATE = b"\x80\x02ctorch\nFloatStorage\nN}X\x05\x00\x00\x00dtypeK\x01s\x86b."
BUILD_ON_FUNCTION = b"\x80\x02ctorch._utils\n_rebuild_tensor_v2\n}X\x01\x00\x00\x00xK\x01sb."


@pytest.mark.parametrize("payload", [BUILD_ON_STORAGE, BUILD_SLOTSTATE, BUILD_ON_FUNCTION])
def test_build_opcode_is_refused_and_leaves_the_shared_globals_alone(tmp_path, payload):
  _archive_with_pickle(tmp_path / "evil.torch", payload)
  with pytest.raises(UnsafeChunkError, match=r"evil\.torch.*BUILD"):
    chunks.load_tensor_archive(tmp_path / "evil.torch")
  storage = chunks.unpickler._TensorUnpickler._GLOBALS[("torch", "FloatStorage")]
  assert storage.dtype == np.float32 and not hasattr(chunks.storage._rebuild_tensor, "x")
  write_chunk(tmp_path / "good.torch", [_scene("after")])  # later chunks still read
  assert chunks.read_chunk(tmp_path / "good.torch")[0]["key"] == "after"


def test_build_on_a_rebuilt_tensor_is_refused(tmp_path):
  chunks.save_tensor_archive(tmp_path / "t.torch", np.arange(4, dtype=np.float32))
  with zipfile.ZipFile(tmp_path / "t.torch") as archive:
    records = {n: archive.read(n) for n in archive.namelist()}
  state = b"(K\x01K\x02\x85ctorch\nFloatStorage\n\x89C\x08" + b"\x00" * 8 + b"tb"
  records["t/data.pkl"] = records["t/data.pkl"][:-1] + state + b"."
  with zipfile.ZipFile(tmp_path / "t.torch", "w") as archive:
    for name, data in records.items():
      archive.writestr(name, data)
  with pytest.raises(UnsafeChunkError, match="BUILD"):
    chunks.load_tensor_archive(tmp_path / "t.torch")


@pytest.mark.parametrize(
  "payload, message",
  [
    (b"\x80\x02]q\x00(K\x01", "truncated"),  # no STOP
    (b"\x80\x02e.", "malformed"),  # APPENDS with no mark
    (b"\x80\x02](K\x01K\x02u.", "malformed"),  # SETITEMS on a list
    (b"\x80\x02\xff.", "opcode"),  # unknown opcode
    (b"\x80\x02X\xff\xff\xff\x7fabc.", "truncated|malformed"),  # string longer than the data
    (b"\x80\x02ctorch\nFloatStorage\n)R.", "refusing to call"),  # calling a storage type
  ],
)
def test_malformed_pickles_raise_chunk_errors(tmp_path, payload, message):
  _archive_with_pickle(tmp_path / "bad.torch", payload)
  with pytest.raises(ChunkError, match=rf"bad\.torch.*({message})"):
    chunks.load_tensor_archive(tmp_path / "bad.torch")


def _set_declared_size(path, member, size):
  """Rewrites `member`'s uncompressed size in the local header and the central directory."""
  with zipfile.ZipFile(path) as archive:
    offset = archive.getinfo(member).header_offset
  data = bytearray(path.read_bytes())
  struct.pack_into("<I", data, offset + 22, size)
  central = data.rfind(b"PK\x01\x02" + data[offset + 4 : offset + 8])  # same version/flags prefix
  while data[central + 46 : central + 46 + len(member)] != member.encode():
    central = data.rfind(b"PK\x01\x02", 0, central)
  struct.pack_into("<I", data, central + 24, size)
  path.write_bytes(bytes(data))


def test_zip_bomb_storage_is_refused_before_it_is_inflated(tmp_path):
  declared = 1_700_000_000
  path = tmp_path / "bomb.torch"
  chunks.save_tensor_archive(path, [np.zeros(4, np.uint8)])
  with zipfile.ZipFile(path) as archive:
    records = {n: archive.read(n) for n in archive.namelist()}
  # the pickle's storage claims `declared` elements, its record is deflated zeros claiming as much
  records["bomb/data.pkl"] = records["bomb/data.pkl"].replace(
    b"K\x04tQ", b"J" + struct.pack("<i", declared) + b"tQ"
  )
  with zipfile.ZipFile(path, "w") as archive:
    for name, data in records.items():
      compress = zipfile.ZIP_DEFLATED if name == "bomb/data/0" else zipfile.ZIP_STORED
      archive.writestr(
        zipfile.ZipInfo(name),
        data if compress == zipfile.ZIP_STORED else b"\0" * (1 << 20),
        compress_type=compress,
      )
  _set_declared_size(path, "bomb/data/0", declared)
  before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
  with pytest.raises(ChunkError, match=r"bomb\.torch.*would inflate to 1700000000"):
    chunks.load_tensor_archive(path)
  # and a record whose size disagrees with its storage is refused unread, lazily too
  _set_declared_size(path, "bomb/data/0", 8 << 20)
  (lazy,) = chunks.load_tensor_archive(path, lazy=True)
  with pytest.raises(ChunkError, match=r"declares 8388608 bytes, expected 1700000000"):
    lazy.load()
  assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 200_000  # KiB: < 200 MB


def test_unreadable_chunks_are_skipped_and_the_good_one_kept(tmp_path):
  write_chunk(tmp_path / "000000.torch", [_scene("good")])
  _archive_with_pickle(tmp_path / "000001.torch", BUILD_ON_STORAGE)
  _archive_with_pickle(tmp_path / "000002.torch", b"\x80\x02e.")
  _archive_with_pickle(
    tmp_path / "000003.torch",
    pickle.dumps([{"key": "x", "images": [10**12], "cameras": 1}], protocol=2),
  )
  source = ChunkedSceneSource(tmp_path, skip_bad=True)
  assert [e.key for e in source.entries] == ["good"]
  assert source.rejections.counts == {"bad_chunk": 2, "bad_scene": 1}


# ---- 3. intrinsics enter the library checked


def test_negative_focal_length_and_bad_frames_are_rejected_per_example():
  scene = _scene("s")
  record = {**scene, "height": 8, "width": 8}
  views = (np.array([0, 2]), np.array([1]))
  make_example(record, CONFIG, np.random.default_rng(0), views=views)  # the good one builds
  negative = {**record, "intrinsics": record["intrinsics"] * [-1, 1, 1, 1]}
  with pytest.raises(BadExampleError, match="fx, fy > 0"):
    make_example(negative, CONFIG, np.random.default_rng(0), views=views)
  for images, what in [
    (scene["images"].astype(np.float32), "float32"),
    (scene["images"][..., :1], r"\[8, 8, 1\]"),
  ]:
    with pytest.raises(BadExampleError, match=f"uint8 .*{what}"):
      make_example({**record, "images": images}, CONFIG, np.random.default_rng(0), views=views)
  pipeline = InputPipeline(
    [record, negative, record],
    CONFIG,
    batch_size=1,
    shard_index=0,
    shard_count=1,
    skip_bad=True,
    num_epochs=1,
    shuffle=False,
  )
  assert [int(b["scene_index"][0]) for b in pipeline] == [0, 2]
  assert pipeline.rejections.counts == {"BadExampleError": 1}


# ---- 5. Kubric: every failure is a KubricError; a bad scene costs only itself


def _kubric_view(path, frames=4, size=8, sensor_width=32.0, resolution=None):
  from tokengs_jax.data.synthetic.generate import write_kubric_view

  path.parent.mkdir(parents=True, exist_ok=True)
  positions = [[0.3 * f, 0.0, 5.0] for f in range(frames)]
  metadata = {
    "metadata": {"resolution": resolution or [size, size]},
    "camera": {
      "focal_length": 35.0,
      "sensor_width": sensor_width,
      "positions": positions,
      "quaternions": [[1.0, 0.0, 0.0, 0.0]] * frames,
    },
  }
  images = np.random.default_rng(0).integers(0, 255, (frames, size, size, 3), dtype=np.uint8)
  write_kubric_view(path, metadata, images, np.full((frames, size, size), 5.0, np.float32))


def _truncate(path):
  path.write_bytes(path.read_bytes()[: path.stat().st_size * 2 // 3])


@pytest.mark.parametrize(
  "damage, message",
  [
    (lambda p: _truncate(p), "truncated|not a readable tar"),
    (lambda p: _kubric_view(p, sensor_width=0.0), "sensor_width 0.0"),
    (
      lambda p: _kubric_view(p, resolution=[32, 32]),
      r"is \[8, 8\], metadata.json resolution is \[32, 32\]",
    ),
  ],
)
def test_damaged_kubric_views_raise_kubric_errors(tmp_path, damage, message):
  from tokengs_jax.data import kubric

  path = tmp_path / "output_000.tar"
  _kubric_view(path)
  damage(path)
  with pytest.raises(kubric.KubricError, match=rf"output_000\.tar.*({message})"):
    kubric.read_kubric_view(path, load_depth=True)


def test_kubric_pipeline_keeps_the_good_scene_and_counts_the_bad_ones(tmp_path):
  from tokengs_jax.data import DATASET_PRESETS, kubric

  _kubric_view(tmp_path / "v0" / "a_good" / "output_000.tar")
  _kubric_view(tmp_path / "v0" / "b_truncated" / "output_000.tar")
  _truncate(tmp_path / "v0" / "b_truncated" / "output_000.tar")
  _kubric_view(tmp_path / "v0" / "c_sensor" / "output_000.tar", sensor_width=0.0)
  _kubric_view(tmp_path / "v0" / "d_resolution" / "output_000.tar", resolution=[32, 32])
  config = dataclasses.replace(DATASET_PRESETS["kubric"], image_shape=(8, 8))
  pipeline = InputPipeline(
    kubric.KubricSceneSource(tmp_path, ["v0"], num_cameras=1),
    config,
    batch_size=1,
    shard_index=0,
    shard_count=1,
    num_epochs=1,
    shuffle=False,
    skip_bad=True,
    select_views=kubric.kubric_view_selector(2, 1, 1, 3),
  )
  with _deadline(60):
    assert [int(b["scene_index"][0]) for b in pipeline] == [0]
  counts = dict(pipeline.rejections.counts)
  # the truncation cuts the tar index or a frame the metadata lists (KubricError on parse); the
  # 4x-wrong intrinsics are caught where a decoded frame meets the metadata's resolution, in the
  # reader (KubricError naming the tar and member)
  assert counts == {"KubricError": 3}
  assert any(
    "d_resolution" in m and "member ./rgba_" in m and "[8, 8]" in m and "[32, 32]" in m
    for m in pipeline.rejections.messages
  )


# ---- 1 (and issue 15). an evaluation index is checked against the data before any work


def test_evaluation_index_is_validated_against_the_data(tmp_path, caplog):
  from tokengs_jax.data import (
    EvaluationIndexError,
    load_evaluation_index,
    validate_evaluation_index,
  )

  write_chunk(tmp_path / "000000.torch", [_scene("a"), _scene("b")])
  _index(tmp_path, {"a": "000000.torch", "b": "000000.torch"})
  (tmp_path / "eval.json").write_text(
    json.dumps(
      {
        "a": {"context": [0, 4], "target": [2]},
        "gone": {"context": [0, 1], "target": [1]},
        "b": {"context": [0, 3], "target": [1]},
      }
    )
  )
  index = load_evaluation_index(tmp_path / "eval.json")
  source = ChunkedSceneSource(tmp_path, keys=list(index), skip_bad=True)
  with caplog.at_level(logging.WARNING, logger="tokengs_jax.data"):
    report = validate_evaluation_index(index, source.keys, where="eval.json")
  assert report.matched == ("a", "b") and report.missing == ("gone",)  # good ones all kept
  assert report.as_dict() == {"requested": 3, "evaluated": 2, "missing": ["gone"]}
  assert any("eval.json" in r.getMessage() and "'gone'" in r.getMessage() for r in caplog.records)
  assert source.rejections.counts == {"missing_index_entry": 1}  # the source reports it too
  with pytest.raises(EvaluationIndexError, match=r"missing 1: 'gone'"):
    validate_evaluation_index(index, source.keys, allow_missing=False)
  with pytest.raises(EvaluationIndexError, match=r"none of its 3 scenes.*'gone'.*data keys: 'x'"):
    validate_evaluation_index(index, ["x", "y"])
  frames = {key: 5 for key in source.keys}
  assert validate_evaluation_index(index, frames).matched == ("a", "b")
  with pytest.raises(EvaluationIndexError, match=r"'a': .*frame 4 of a 4-frame scene"):
    validate_evaluation_index(index, {"a": 4, "b": 5})
