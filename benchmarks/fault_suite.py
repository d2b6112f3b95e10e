"""The bad-input and fault suite (issues 16, 28): the files that hold only such cases, and every
other test docs/robustness.md cites, run as one pytest call.

    python benchmarks/fault_suite.py            # count and wall time, pytest -n 2
    python benchmarks/fault_suite.py --list     # the files and node ids only

The cited tests are read from the doc's case tables, so a case added there with its test is
counted here: a cell's `test_x.py::test_name` names a test and `::test_name` another test of the
same file.
"""

from __future__ import annotations

import argparse
import pathlib
import re
import subprocess
import sys
import time

REPO = pathlib.Path(__file__).resolve().parent.parent
# Every test in these files is a bad-input, fault or numerical-stress case.
FAULT_FILES = (
  "tests/test_data_bad_input.py",
  "tests/test_data_memory.py",
  "tests/test_train_checkpoint_files.py",
  "tests/test_signals.py",
  "tests/test_splatting_checks.py",
  "tests/test_stress.py",
  "tests/test_viewer_security.py",
)
_NODE = re.compile(r"(test_\w+\.py)?::(test_\w+)")


def cited_tests(doc: pathlib.Path = REPO / "docs" / "robustness.md") -> list[str]:
  """Node ids (`tests/test_x.py::test_name`) in the order the doc cites them, each once."""
  ids, current = [], None
  for quoted in re.findall(r"`([^`]*)`", doc.read_text()):
    for part in re.split(r",\s*", quoted):
      match = _NODE.fullmatch(part.strip())
      if match:
        current = match.group(1) or current
        ids.append(f"tests/{current}::{match.group(2)}")
  return list(dict.fromkeys(ids))


def main() -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--list", action="store_true", help="print the node ids and stop")
  parser.add_argument("--workers", default="2", help="pytest-xdist workers (-n)")
  args = parser.parse_args()
  ids = list(FAULT_FILES) + [i for i in cited_tests() if not i.startswith(FAULT_FILES)]
  if args.list:
    print("\n".join(ids))
    return 0
  start = time.perf_counter()
  done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-n", args.workers, *ids], cwd=REPO)
  print(f"{time.perf_counter() - start:.0f} s wall (pytest's count above)")
  return done.returncode


if __name__ == "__main__":
  sys.exit(main())
