"""tokengs_jax.data.rejections: counts per reason, the last messages, throttled warnings, summary."""

import logging

from tokengs_jax.data import Rejections, summarize_rejections


def test_counts_each_reason_and_keeps_the_last_messages():
  log = Rejections("source", max_messages=3)
  assert not log and log.total() == 0
  for i in range(4):
    log.add("ChunkError", f"chunk {i}")
  log.add("BadExampleError", "scene 'x'")
  assert log and log.total() == 5
  assert log.counts == {"ChunkError": 4, "BadExampleError": 1}
  assert list(log.messages) == ["chunk 2", "chunk 3", "scene 'x'"]  # the oldest dropped


def test_warns_for_the_first_five_of_a_reason_then_at_powers_of_ten(caplog):
  log = Rejections("pipeline")
  with caplog.at_level(logging.WARNING, logger="tokengs_jax.data"):
    for i in range(1, 1001):
      log.add("BadExampleError", f"scene {i}")
    log.add("ChunkError", "chunk 0")  # another reason has its own first five
  logged = [r.getMessage() for r in caplog.records]
  counts = [int(m.split(", ")[1].split()[0]) for m in logged[:-1]]
  assert counts == [1, 2, 3, 4, 5, 10, 100, 1000]
  assert logged[0] == "[pipeline] rejected (BadExampleError, 1 so far): scene 1"
  assert logged[-1] == "[pipeline] rejected (ChunkError, 1 so far): chunk 0"
  assert log.counts["BadExampleError"] == 1000  # every one counted, logged or not


def test_summary_names_totals_reasons_and_the_last_message():
  source, pipeline = Rejections("source"), Rejections("pipeline")
  pipeline.add("ChunkError", "chunk 7: truncated")
  pipeline.add("BadExampleError", "scene 'a'")
  pipeline.add("BadExampleError", "scene 'b'")
  assert summarize_rejections({"source": source, "pipeline": pipeline}) == (
    "source: nothing rejected\n"
    "pipeline: 3 rejected (BadExampleError 2, ChunkError 1); last: scene 'b'"
  )
  assert pipeline.summary() == summarize_rejections({"pipeline": pipeline})
