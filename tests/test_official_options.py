"""docs/official_options.md against the official `tokengs/options.py` and our command lines
(issue 26): every official field has its row, under its official group and with its official
default; every official preset has its row; every flag and preset the page cites exists.

The official checkout (`../shared/reference/tokengs-official`, beside the repository) is only
parsed with `ast`, never imported; the tests that need it skip, saying so, where it is absent.
Our flags are read from the `--help` of every preset of the three entry points, in-process.
"""

from __future__ import annotations

import ast
import contextlib
import importlib
import io
import pathlib
import re
from collections import Counter

import pytest

REPO = pathlib.Path(__file__).resolve().parent.parent
PAGE = REPO / "docs" / "official_options.md"
OFFICIAL_OPTIONS = (
  REPO.parent / "shared" / "reference" / "tokengs-official" / "tokengs" / "options.py"
)
ENTRY_POINTS = ("re10k", "dl3dv", "kubric")
FIELD_STATUSES = ("same", "deviation", "not supported")
PRESET_STATUSES = ("same", "deviation", "missing")
FIELDS_HEADING = "`Options` fields"
PRESETS_HEADING = "Presets"
OUR_FLAG = re.compile(r"--[a-z][a-z0-9]*(?:[.-][a-z0-9]+)*")
# an option line of tyro's help: plain ("  --a, --b TYPE") or boxed ("│ --a TYPE")
HELP_OPTION_LINE = re.compile(r"^(?:│ |  )(--[^\s,]+(?:, --[^\s,]+)*)")
ANSI = re.compile(r"\x1b\[[0-9;]*m")


# ----- the official file -------------------------------------------------------------------------


def _official_source() -> str:
  if not OFFICIAL_OPTIONS.is_file():
    pytest.skip(
      f"{OFFICIAL_OPTIONS} is absent (../shared/reference/tokengs-official is not beside the "
      "repository): nothing to check the table against"
    )
  return OFFICIAL_OPTIONS.read_text()


def _is_dataclass(node: ast.ClassDef) -> bool:
  names = {ast.unparse(d.func if isinstance(d, ast.Call) else d) for d in node.decorator_list}
  return bool(names & {"dataclass", "dataclasses.dataclass"})


def official_fields(source: str) -> dict[str, tuple[str, str]]:
  """name -> (group, default as written) of every field of the official options dataclasses;
  the group is the `# --- <group>` comment above the field."""
  lines = source.splitlines()
  fields = {}
  for node in ast.parse(source).body:
    if not (isinstance(node, ast.ClassDef) and _is_dataclass(node)):
      continue
    group, previous = None, node.lineno
    for statement in node.body:
      if not isinstance(statement, ast.AnnAssign):
        continue
      for line in lines[previous : statement.lineno - 1]:
        match = re.match(r"\s*# --- (.+?)\s*$", line)
        if match:
          group = match.group(1)
      previous = statement.lineno
      assert group is not None, f"official field {statement.target.id} has no group comment"
      default = ast.get_source_segment(source, statement.value) if statement.value else None
      fields[statement.target.id] = (group, default)
  return fields


def _bind(target: ast.expr, value, env: dict) -> None:
  if isinstance(target, ast.Name):
    env[target.id] = value
  else:
    for element, item in zip(target.elts, value, strict=True):
      _bind(element, item, env)


def _string(node: ast.expr, env: dict) -> str:
  """A constant, a name bound earlier, or an f-string of names (formatted without eval)."""
  if isinstance(node, ast.Constant):
    return node.value
  if isinstance(node, ast.Name):
    return env[node.id]
  if isinstance(node, ast.JoinedStr):
    parts = []
    for value in node.values:
      if isinstance(value, ast.Constant):
        parts.append(value.value)
      else:
        assert value.format_spec is None and value.conversion == -1, ast.unparse(node)
        parts.append(str(_string(value.value, env)))
    return "".join(parts)
  raise AssertionError(f"cannot read a preset name from {ast.unparse(node)}")


def official_presets(source: str) -> list[str]:
  """Every key assigned to `config_defaults[...]` at module level, the loops' f-string names
  expanded over their literal ranges."""
  names = []

  def run(statements, env):
    for statement in statements:
      if isinstance(statement, ast.For):
        for value in ast.literal_eval(statement.iter):
          scope = dict(env)
          _bind(statement.target, value, scope)
          run(statement.body, scope)
      elif isinstance(statement, ast.Assign):
        for target in statement.targets:
          if isinstance(target, ast.Name) and isinstance(
            statement.value, (ast.Constant, ast.JoinedStr)
          ):
            env[target.id] = _string(statement.value, env)
          elif (
            isinstance(target, ast.Subscript)
            and isinstance(target.value, ast.Name)
            and target.value.id == "config_defaults"
          ):
            names.append(_string(target.slice, env))

  run(ast.parse(source).body, {})
  return names


# ----- the page --------------------------------------------------------------------------------


def _page() -> str:
  return PAGE.read_text()


def _section(text: str, heading: str) -> str:
  """The body of `## heading` up to the next `## `."""
  match = re.search(rf"^## {re.escape(heading)}\s*$(.*?)(?=^## |\Z)", text, re.M | re.S)
  assert match, f"{PAGE.name} has no section '## {heading}'"
  return match.group(1)


def _rows(body: str) -> list[list[str]]:
  """The cells of every table row whose first cell is a code span (header rows are not)."""
  rows = []
  for line in body.splitlines():
    if re.match(r"^\| `[^`]+` \|", line):
      cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
      assert len(cells) == 4, f"a row of {PAGE.name} does not have 4 cells: {line}"
      rows.append(cells)
  return rows


def page_fields() -> dict[str, tuple[str, list[str]]]:
  """name -> (### group it is listed under, cells) of the options table rows."""
  rows = {}
  group = None
  for line in _section(_page(), FIELDS_HEADING).splitlines():
    if line.startswith("### "):
      group = line.removeprefix("### ").strip()
    for cells in _rows(line):
      name = cells[0].strip("`")
      assert name not in rows, f"{name} has two rows in {PAGE.name}"
      rows[name] = (group, cells)
  return rows


def page_presets() -> dict[str, list[str]]:
  rows = {}
  for cells in _rows(_section(_page(), PRESETS_HEADING)):
    name = cells[0].strip("`")
    assert name not in rows, f"preset {name} has two rows in {PAGE.name}"
    rows[name] = cells
  return rows


def _status(cell: str, statuses: tuple[str, ...]) -> str:
  match = re.match("|".join(map(re.escape, statuses)), cell)
  assert match, f"status {cell!r} does not start with one of {statuses}"
  return match.group(0)


# ----- our command lines -----------------------------------------------------------------------


def _help_flags(cli, presets, preset: str) -> set[str]:
  out = io.StringIO()
  with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
    with pytest.raises(SystemExit) as exit_info:
      cli.parse(["run", preset, "--help"], presets, preset, "prog")
  assert exit_info.value.code in (0, None), out.getvalue()
  flags = set()
  for line in ANSI.sub("", out.getvalue()).splitlines():
    match = HELP_OPTION_LINE.match(line)
    if match:
      flags.update(match.group(1).split(", "))
  # a change of tyro's help layout must fail here, not pass every flag or none
  assert {"--seed", "--output-dir", "--train.steps", "--model.enc-depth"} <= flags, sorted(flags)
  return flags


@pytest.fixture(scope="module")
def our_cli():
  """(entry point -> presets, (entry point, preset) -> the flags its `run` accepts)."""
  from experiments import cli

  with pytest.MonkeyPatch.context() as patch:
    patch.setenv("COLUMNS", "80")  # tyro's one-column help, whatever the terminal
    presets, flags = {}, {}
    for entry in ENTRY_POINTS:
      presets[entry] = importlib.import_module(f"experiments.{entry}").PRESETS
      for preset in presets[entry]:
        flags[entry, preset] = _help_flags(cli, presets[entry], preset)
  return presets, flags


def _code_spans(text: str) -> list[str]:
  return re.findall(r"`([^`\n]+)`", text)


# ----- tests -----------------------------------------------------------------------------------


def test_every_official_field_has_its_row_group_and_default():
  official = official_fields(_official_source())
  listed = page_fields()
  assert len(official) >= 80, "the official options file was not read"
  missing = sorted(set(official) - set(listed))
  assert not missing, f"official options without a row in {PAGE.name}: {missing}"
  extra = sorted(set(listed) - set(official))
  assert not extra, f"rows of {PAGE.name} that are no official option: {extra}"
  for name, (group, default) in official.items():
    page_group, (_, page_default, equivalent, status) = listed[name]
    assert page_group == group, f"{name} is under '### {page_group}', official group '{group}'"
    assert page_default == f"`{default}`", (
      f"{name}: official default {default}, page {page_default}"
    )
    assert equivalent, f"{name}: no equivalent given"
    _status(status, FIELD_STATUSES)


def test_every_official_preset_has_its_row():
  official = official_presets(_official_source())
  listed = page_presets()
  assert len(official) >= 20 and len(set(official)) == len(official), official
  assert sorted(listed) == sorted(official), (
    f"missing: {sorted(set(official) - set(listed))}, not official: "
    f"{sorted(set(listed) - set(official))}"
  )
  for cells in listed.values():
    _status(cells[3], PRESET_STATUSES)


def test_the_counts_are_the_tables():
  fields = Counter(_status(cells[3], FIELD_STATUSES) for _, cells in page_fields().values())
  presets = Counter(_status(cells[3], PRESET_STATUSES) for cells in page_presets().values())
  text = " ".join(_page().split())
  expected = (
    f"Counts: {sum(fields.values())} fields, of which {fields['same']} are the same, "
    f"{fields['deviation']} deviate and {fields['not supported']} are not supported. "
    f"{sum(presets.values())} official presets, of which {presets['same']} are the same, "
    f"{presets['deviation']} deviate and {presets['missing']} are missing."
  )
  assert expected in text, f"{PAGE.name} should say: {expected}"


def test_every_cited_flag_and_preset_exists(our_cli, tmp_path):
  """A code span `[entry point] [command [preset]] [--flag value ...]` (the entry point also as
  `python -m experiments.<entry point>`): the preset must exist and each flag be accepted by
  that preset's `run`; without a preset, by every preset of the entry point; without an entry
  point, by every preset of all three."""
  from experiments import cli
  from experiments.tasks import COMMANDS

  presets, flags = our_cli
  checked = 0
  for span in _code_spans(_page()):
    tokens = span.removeprefix("python -m experiments.").split()
    entry = tokens.pop(0) if tokens[0] in ENTRY_POINTS else None
    scope = [(e, p) for e, p in flags if e == entry] if entry else list(flags)
    if tokens and tokens[0] in COMMANDS:
      tokens.pop(0)
      if entry and tokens and not tokens[0].startswith("-"):
        preset = tokens.pop(0)
        assert preset in presets[entry], f"`{span}`: {entry} has no preset {preset}"
        scope = [(entry, preset)]
        checked += 1
    for flag in (token for token in tokens if token.startswith("--")):
      assert OUR_FLAG.fullmatch(flag), f"`{span}`: {flag} is not spelt as our flags are"
      checked += 1
      if flag == "--from-run":  # read before tyro (`experiments.cli.parse`), so not in --help
        for entry_name in {e for e, _ in scope}:
          with pytest.raises(SystemExit, match="no metrics.json"):
            run_dir = ["eval", "--from-run", str(tmp_path)]
            cli.parse(run_dir, presets[entry_name], next(iter(presets[entry_name])), "prog")
        continue
      refusing = [f"{e} {p}" for e, p in scope if flag not in flags[e, p]]
      assert not refusing, f"`{span}`: {flag} is not accepted by {refusing}"
  assert checked >= 100, f"only {checked} flags and presets found in {PAGE.name}"


def test_every_cited_section_exists():
  cited = re.findall(r"\b([\w]+)\.md \"([^\"]+)\"", " ".join(_page().split()))
  assert len(cited) >= 10
  for page, heading in cited:
    path = REPO / "docs" / f"{page}.md"
    assert path.is_file(), f"{PAGE.name} cites {page}.md, which is not in docs/"
    headings = [
      line.lstrip("#").strip() for line in path.read_text().splitlines() if line.startswith("#")
    ]
    assert any(h.startswith(heading) for h in headings), f"{page}.md has no section '{heading}'"
