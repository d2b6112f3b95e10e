"""Counting, logging and summarising the data a run rejected, so nothing is dropped silently.

Every source and the input pipeline record each scene, chunk or example they refuse in a
`Rejections` log: a count per reason, the last messages, and a warning on the
`tokengs_jax.data` logger (the first few per reason, then at every power of ten, so a dataset with
many bad scenes cannot flood the output). `InputPipeline.rejection_summary()` merges the
pipeline's log with its source's for the end-of-run report.
"""

from __future__ import annotations

import collections
import logging

__all__ = ["Rejections", "summarize_rejections"]

LOGGER = logging.getLogger("tokengs_jax.data")
_LOGGED_PER_REASON = 5  # then only at counts 10, 100, 1000, ...


class Rejections:
  """Counts and messages of rejected data, by reason.

  Attributes:
    counts: reason -> number rejected.
    messages: the last `max_messages` messages (each names the file and scene).
  """

  def __init__(self, where: str, max_messages: int = 100):
    self.where = where
    self.counts: collections.Counter = collections.Counter()
    self.messages: collections.deque = collections.deque(maxlen=max_messages)

  def add(self, reason: str, message: str) -> None:
    self.counts[reason] += 1
    self.messages.append(message)
    count = self.counts[reason]
    if count <= _LOGGED_PER_REASON or _is_power_of_ten(count):
      LOGGER.warning("[%s] rejected (%s, %d so far): %s", self.where, reason, count, message)

  def total(self) -> int:
    return sum(self.counts.values())

  def __bool__(self) -> bool:
    return bool(self.counts)

  def summary(self) -> str:
    return summarize_rejections({self.where: self})


def _is_power_of_ten(count: int) -> bool:
  while count >= 10 and count % 10 == 0:
    count //= 10
  return count == 1


def summarize_rejections(logs: dict[str, Rejections]) -> str:
  """One human-readable paragraph: per log, the total and the count of every reason.

  logs: name -> Rejections (e.g. {"source": ..., "pipeline": ...}).
  """
  lines = []
  for name, log in logs.items():
    if not log:
      lines.append(f"{name}: nothing rejected")
      continue
    reasons = ", ".join(f"{reason} {count}" for reason, count in sorted(log.counts.items()))
    lines.append(f"{name}: {log.total()} rejected ({reasons}); last: {log.messages[-1]}")
  return "\n".join(lines)
