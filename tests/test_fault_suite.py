"""`benchmarks/fault_suite.py`: the suite it runs is the one docs/robustness.md cites, and every
cited test exists (a renamed or deleted test would silently drop out of the suite)."""

import importlib.util
import pathlib
import re

REPO = pathlib.Path(__file__).resolve().parent.parent


def _fault_suite():
  spec = importlib.util.spec_from_file_location("fault_suite", REPO / "benchmarks/fault_suite.py")
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module


def test_every_cited_test_and_fault_file_exists():
  suite = _fault_suite()
  cited = suite.cited_tests()
  assert len(cited) >= 40 and len(set(cited)) == len(cited)
  for node in cited:
    path, _, name = node.partition("::")
    source = (REPO / path).read_text()
    assert re.search(rf"^def {name}\(", source, re.MULTILINE), f"{node} is cited but not defined"
  for path in suite.FAULT_FILES:
    assert (REPO / path).is_file()


def test_a_continuation_cites_a_test_of_the_file_before_it(tmp_path):
  doc = tmp_path / "doc.md"
  doc.write_text("| a | `test_x.py::test_one`, `::test_two` | `test_y.py::test_three` |\n")
  assert _fault_suite().cited_tests(doc) == [
    "tests/test_x.py::test_one",
    "tests/test_x.py::test_two",
    "tests/test_y.py::test_three",
  ]
