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


# Outside `tokengs_jax/evaluation.py`, the definitions whose names read as an evaluator or a scorer
# but are not one, each with what it is instead. A new one is a second evaluator until it is
# listed here with its reason.
NOT_EVALUATORS = {
  "tokengs_jax/objective/model_loss.py:_score_at_times": "the training objective's loss terms",
  "tokengs_jax/objective/model_loss.py:_scored_with_dynamic_aux": "the same, with the aux term",
  "tokengs_jax/scene_flow.py:score_scene": "the scene-flow metric of one scene (no render)",
  "tokengs_jax/train/loop.py:_MetricsLog.evaluation": "logs the scalars of the loop's eval_fn",
  "experiments/config.py:EvalSettings": "the evaluation's command-line settings",
  "experiments/tasks.py:Task.check_evaluation": "checks the index against the data, no scores",
  "experiments/kubric_task.py:KubricTask.check_evaluation": "the same, for Kubric",
  "experiments/tasks.py:run_eval": "the entry points' driver: scores with evaluation.evaluate_sets",
  "experiments/viewer/browser.py:_DevTools.evaluate": "Chrome DevTools' Runtime.evaluate (JS)",
}


def _words(name: str) -> list[str]:
  """A name's words, split at underscores, capitals and digits, lower case."""
  return [w.lower() for w in re.findall(r"[A-Z]+(?![a-z])|[A-Z]?[a-z]+|[0-9]+", name)]


def _reads_as_an_evaluator(name: str) -> bool:
  """A word that starts with "eval" or "scor" ("evaluate", "Evaluator", "eval", "Scorer",
  "scoring", "scores"), except "evaluation" as a modifier ("evaluation_views" names data an
  evaluation reads; "run_evaluation" ends with it and counts)."""
  words = _words(name)
  return words[-1:] in (["evaluation"], ["evaluations"]) or any(
    re.match("eval|scor", w) and w not in ("evaluation", "evaluations") for w in words
  )


def _definitions(tree: ast.AST, prefix: str = ""):
  """(qualified name, node) of every function, method and class of a module, at any depth."""
  for node in ast.iter_child_nodes(tree):
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
      yield prefix + node.name, node
      yield from _definitions(node, f"{prefix}{node.name}.")
    else:
      yield from _definitions(node, prefix)


def test_one_evaluation_code_path():
  """Only `tokengs_jax/evaluation.py` defines an evaluator or a scorer, whatever its spelling
  (`_evaluate`, `evaluate2`, `Evaluator`, `run_evaluation`, `eval_methods`, `make_scorer`,
  `Scoring`; a function, a method or a class, at any depth) but for the listed
  `NOT_EVALUATORS`, and only `tokengs_jax/metrics.py` writes the PSNR formula (10 log10 of an
  error), so no second harness can score on its own terms."""
  renamed = ["_evaluate", "evaluate2", "Evaluator", "run_evaluation", "eval_methods", "evalAll"]
  renamed += ["make_scorer", "HTTPScorer", "Scoring", "score_methods", "MethodScores"]
  assert all(_reads_as_an_evaluator(name) for name in renamed)
  assert not any(map(_reads_as_an_evaluator, ["evaluation_views", "EvaluationIndexError"]))
  defining = {}
  for path in _sources():
    for qualified, node in _definitions(ast.parse(path.read_text())):
      if _reads_as_an_evaluator(node.name):
        defining.setdefault(str(path.relative_to(REPO)), set()).add(qualified)
  assert {"evaluate", "evaluate_sets", "Scorer"} <= defining.pop("tokengs_jax/evaluation.py")
  others = {f"{path}:{name}" for path, names in defining.items() for name in names}
  assert others <= NOT_EVALUATORS.keys(), sorted(others - NOT_EVALUATORS.keys())
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


def _design_tree() -> dict[str, str]:
  """The layout block of docs/design.md (its first code block) as entry -> its text:
  "tokengs_jax/math.py", "tokengs_jax/model/" (a package: the modules it names), "experiments/"."""
  block = (REPO / "docs" / "design.md").read_text().split("```")[1]
  entries, top, key = {}, None, None
  for line in block.splitlines():
    if not line.strip():
      continue
    name = line.split()[0]
    if line.startswith("  ") and not line.startswith("   "):
      key = top + name
    elif not line.startswith(" "):
      top = key = name
    else:  # a continuation line of the entry above
      entries[key] += " " + line.strip()
      continue
    entries[key] = line.strip()[len(name) :]
  return entries


def test_design_and_the_experiments_docstring_name_every_module():
  """docs/design.md's layout describes the tree as it is: every module of `tokengs_jax/` has its
  line (a package's modules are named on the package's line) and every module of
  `experiments/` is named on its line; `experiments/__init__.py` names each of its modules.
  The studies are indexed where they live (`experiments/studies/__init__.py`)."""
  entries = _design_tree()
  assert {"tokengs_jax/math.py", "tokengs_jax/model/", "experiments/"} <= entries.keys()
  unnamed = []
  for package in ("tokengs_jax", "experiments"):
    for path in sorted((REPO / package).rglob("*.py")):
      parts = path.relative_to(REPO).parts
      if path.name in ("__init__.py", "__main__.py") or parts[:2] == ("experiments", "studies"):
        continue
      if package == "tokengs_jax" and len(parts) == 2:
        named = "/".join(parts) in entries
      else:
        entry = entries.get(
          f"{package}/{parts[1]}/" if package == "tokengs_jax" else "experiments/"
        )
        named = entry is not None and re.search(rf"\b{path.stem}\b", entry) is not None
      if not named:
        unnamed.append(str(path.relative_to(REPO)))
  assert not unnamed, f"modules docs/design.md's layout does not name: {unnamed}"
  doc = ast.get_docstring(ast.parse((REPO / "experiments" / "__init__.py").read_text()))
  children = [p for p in (REPO / "experiments").iterdir() if not p.name.startswith("__")]
  names = [
    p.stem if p.suffix == ".py" else f"{p.name}/" for p in children if p.suffix in (".py", "")
  ]
  missing = sorted(n for n in names if f"`{n}`" not in doc)
  assert not missing, f"experiments/__init__.py does not name: {missing}"
