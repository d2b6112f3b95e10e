"""The code-size limits the project keeps (issue 13): no source file over 500 lines outside tests,
no function over 80 lines, and one evaluation code path."""

import ast
import pathlib
import re

REPO = pathlib.Path(__file__).resolve().parent.parent
SOURCE_DIRS = ("tokengs_jax", "experiments", "benchmarks")
MAX_FILE_LINES = 500
MAX_FUNCTION_LINES = 80


def _sources():
  return sorted(p for d in SOURCE_DIRS for p in (REPO / d).rglob("*.py"))


def test_no_source_file_is_over_the_line_limit():
  long = {
    str(p.relative_to(REPO)): n
    for p in _sources()
    if (n := len(p.read_text().splitlines())) > MAX_FILE_LINES
  }
  assert not long, f"files over {MAX_FILE_LINES} lines: {long}"


def test_no_function_is_over_the_line_limit():
  long = {}
  for path in _sources():
    for node in ast.walk(ast.parse(path.read_text())):
      if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
        lines = node.end_lineno - node.lineno + 1
        if lines > MAX_FUNCTION_LINES:
          long[f"{path.relative_to(REPO)}:{node.name}"] = lines
  assert not long, f"functions over {MAX_FUNCTION_LINES} lines: {long}"


def _free_functions_and_classes(tree: ast.AST):
  """Every function that is not a method (at any depth) and every class of a module."""
  methods = {
    id(child)
    for node in ast.walk(tree)
    if isinstance(node, ast.ClassDef)
    for child in node.body
    if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef))
  }
  for node in ast.walk(tree):
    if isinstance(node, ast.ClassDef) or (
      isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and id(node) not in methods
    ):
      yield node


def test_one_evaluation_code_path():
  """Only `tokengs_jax/evaluation.py` defines an evaluator or a scorer (at any depth: a nested
  `def evaluate` or a `class MyScorer` counts), and only `tokengs_jax/metrics.py` writes the PSNR
  formula (10 log10 of an error), so no second harness can score on its own terms."""
  evaluator = re.compile(r"^(evaluate\w*|\w*Scorer\w*)$")
  defining = {
    str(path.relative_to(REPO))
    for path in _sources()
    for node in _free_functions_and_classes(ast.parse(path.read_text()))
    if evaluator.match(node.name)
  }
  assert defining == {"tokengs_jax/evaluation.py"}, defining
  formula = re.compile(r"10(\.0*)?\s*\*\s*[\w.]*log10\(")
  writing = {str(p.relative_to(REPO)) for p in _sources() if formula.search(p.read_text())}
  assert writing == {"tokengs_jax/metrics.py"}, writing


def test_every_entry_point_sets_the_process_up():
  """Every runnable module that uses JAX starts with `tokengs_jax.process.setup` (itself, or
  through `experiments.cli.main`), so no entry point runs on other JAX settings."""
  uses_jax = re.compile(r"^(import jax|from (jax|tokengs_jax|experiments)\b)", re.M)
  skipping = {
    str(path.relative_to(REPO))
    for path in _sources()
    if '__name__ == "__main__"' in (text := path.read_text())
    and uses_jax.search(text)
    and "process.setup(" not in text
    and "from experiments.cli import main" not in text
  }
  assert not skipping, f"entry points without process.setup: {skipping}"
