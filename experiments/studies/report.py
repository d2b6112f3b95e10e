"""The studies' report (`docs/studies.md`): seeds aggregated, a verdict per claim, one Markdown file.

Pure pieces, no JAX: `verdict` (the rule), `aggregate` (per-seed rows -> mean ± std rows),
`Plot`, `Claim` (one section) and `write_report`.

The verdict rule: a claim compares two quantities measured on the same seeds (e.g. TokenGS's
PSNR drop and the pixel-aligned baseline's, each trained and scored on one seed's scenes). Per
seed, the difference claimed - other (sign turned where lower is better). The claim "holds"
where the mean difference exceeds the spread, the differences' sample standard deviation over
seeds; it "fails" where it is below minus the spread; otherwise (or with fewer than two seeds,
where there is no spread) it is "not shown at this scale": a difference inside one seed-to-seed
standard deviation is what another seed could undo. Paired, because a seed draws its own scenes:
their difficulty moves both sides of a comparison alike, so the tables' ± (of each side alone)
hold that variation and the differences do not.
"""

from __future__ import annotations

import dataclasses
import pathlib
from collections.abc import Iterable, Sequence

import numpy as np

from experiments import figures
from experiments.results import markdown_table

FIGURES = "studies"  # the plots' folder, beside the report
HOLDS = "holds"
FAILS = "fails"
NOT_SHOWN = "not shown at this scale"

VERDICT_RULE = (
  "per seed, the difference between the side a claim says is better and the other (the same "
  "seed's scenes and recipe for both); a claim **holds** where the mean difference exceeds its "
  "spread (the sample standard deviation of the differences over seeds), **fails** where it is "
  "below minus the spread, and is otherwise **not shown at this scale** (so too with one seed). "
  "Paired, because a seed draws its own scenes, whose difficulty moves both sides alike: the "
  "tables' ± (of each side alone) include that variation, the differences do not. With 2 seeds "
  "(the quick form) it is a weak test; the full run uses 3."
)
QUICK_BANNER = (
  "**Quick form (`--quick`): verdicts are a smoke test, not findings.** Models trained for a "
  "few dozen steps on a handful of scenes; the tables show that the machinery runs."
)


def spread(values: Sequence[float]) -> float:
  """Sample standard deviation (ddof 1); NaN for fewer than two values."""
  values = np.asarray(values, np.float64)
  return float(np.std(values, ddof=1)) if values.size > 1 else float("nan")


def differences(claimed: Sequence[float], other: Sequence[float], higher_is_better=True):
  """Per-seed differences claimed - other (other - claimed where lower is better)."""
  claimed, other = np.asarray(claimed, np.float64), np.asarray(other, np.float64)
  if claimed.shape != other.shape:
    raise ValueError(f"unpaired seeds: {claimed.size} values vs {other.size}")
  return (claimed - other) * (1.0 if higher_is_better else -1.0)


def verdict(claimed: Sequence[float], other: Sequence[float], higher_is_better: bool = True) -> str:
  """The rule of the module docstring. claimed / other: per-seed values (same seed order) of the
  side the claim says is better and of the side it is compared with."""
  d = differences(claimed, other, higher_is_better)
  if d.size < 2:
    return NOT_SHOWN
  mean, margin = float(d.mean()), spread(d)
  if mean > margin:
    return HOLDS
  if mean < -margin:
    return FAILS
  return NOT_SHOWN


def difference(claimed: Sequence[float], other: Sequence[float], digits: int = 2) -> str:
  """The per-seed differences claimed - other as "m ± s", for the evidence lines."""
  d = differences(claimed, other)
  return ("+" if d.mean() >= 0 else "") + mean_std(d, digits)


def no_worse(claimed: Sequence[float], other: Sequence[float], higher_is_better=True) -> str:
  """A "no loss" claim: holds unless the claimed side is worse by more than the spread."""
  return FAILS if verdict(claimed, other, higher_is_better) == FAILS else HOLDS


def all_of(verdicts: Iterable[str]) -> str:
  """A claim made of parts: fails if any part fails, holds if every part holds."""
  verdicts = list(verdicts)
  if FAILS in verdicts:
    return FAILS
  return HOLDS if verdicts and all(v == HOLDS for v in verdicts) else NOT_SHOWN


def mean_std(values: Sequence[float], digits: int = 2) -> str:
  """ "m ± s" over seeds (s: the sample standard deviation; "m" alone for one value)."""
  values = np.asarray(values, np.float64)
  if values.size < 2:
    return f"{float(values.mean()):.{digits}f}" if values.size else ""
  return f"{float(values.mean()):.{digits}f} ± {spread(values):.{digits}f}"


def aggregate(
  per_seed: Sequence[Sequence[dict]], keys: Sequence[str], values: Sequence[str], digits: int = 2
) -> list[dict]:
  """One row per distinct `keys` tuple (in first-seen order), each value column as "m ± s" over
  the seeds that have it, plus `<column>_mean` / `<column>_seeds` (the per-seed numbers)."""
  groups: dict[tuple, dict] = {}
  for rows in per_seed:
    for row in rows:
      group = groups.setdefault(tuple(row[k] for k in keys), {k: row[k] for k in keys})
      for column in values:
        if column in row:
          group.setdefault(f"{column}_seeds", []).append(float(row[column]))
  for group in groups.values():
    for column in values:
      seeds = group.get(f"{column}_seeds", [])
      group[column] = mean_std(seeds, digits)
      group[f"{column}_mean"] = float(np.mean(seeds)) if seeds else float("nan")
  return list(groups.values())


def means(rows: Sequence[dict]) -> list[dict]:
  """`aggregate`'s rows with each value column back to a number, its mean over seeds."""
  return [
    {
      **{k: v for k, v in row.items() if not k.endswith(("_mean", "_seeds"))},
      **{k.removesuffix("_mean"): v for k, v in row.items() if k.endswith("_mean")},
    }
    for row in rows
  ]


def series(rows: Sequence[dict], x: str, names: Sequence[str]) -> dict[str, tuple[list, list]]:
  """Rows -> chart series: name -> (the rows' `x`, their column `name`)."""
  return {name: ([row[x] for row in rows], [row[name] for row in rows]) for name in names}


@dataclasses.dataclass(frozen=True)
class Plot:
  """A chart of `series` (name -> (x values, y values)): lines, or points with `scatter`."""

  name: str  # the PNG's file name, without ".png"
  title: str
  series: dict[str, tuple[Sequence[float], Sequence[float]]]
  xlabel: str
  ylabel: str = "PSNR (dB)"
  log_x: bool = False
  scatter: bool = False
  dashed: tuple[str, ...] = ()

  def draw(self, folder) -> pathlib.Path:
    """Writes `<folder>/<name>.png`."""
    path = pathlib.Path(folder) / f"{self.name}.png"
    texts = {"title": self.title, "xlabel": self.xlabel, "ylabel": self.ylabel}
    if self.scatter:
      return figures.scatter_plot(path, self.series, **texts)
    return figures.line_plot(path, self.series, **texts, log_x=self.log_x, dashed=self.dashed)


@dataclasses.dataclass(frozen=True)
class Claim:
  """One claim's section of the report.

  Attributes:
    key: a letter, as in issue 25 ("a" .. "g").
    title: short name.
    statement: what the paper claims, and what is compared here.
    rows / columns: the aggregated table (`aggregate`; cells "m ± s").
    verdict: `HOLDS`, `FAILS` or `NOT_SHOWN`.
    evidence: the numbers behind the verdict, one line.
    plot: drawn beside the report (`FIGURES`) and embedded in its section; None: no plot.
  """

  key: str
  title: str
  statement: str
  rows: list[dict]
  columns: Sequence[str]
  verdict: str
  evidence: str
  plot: Plot | None = None


def write_report(path, claims: Sequence[Claim], header: Sequence[str], quick: bool) -> pathlib.Path:
  """Writes the report: title, the quick-form banner, `header` lines, the verdict rule, the
  verdict table and one section per claim (table, plot, verdict line); the plots go to the
  folder `FIGURES` beside it, linked by relative paths."""
  path = pathlib.Path(path)
  lines = ["# The paper's claims, re-run (`python -m experiments.studies all`)", ""]
  if quick:
    lines += [QUICK_BANNER, ""]
  lines += [*header, "", f"Verdict rule: {VERDICT_RULE}", "", "## Verdicts", ""]
  lines.append(
    markdown_table(
      [
        {"claim": f"({c.key}) {c.title}", "verdict": f"**{c.verdict}**", "evidence": c.evidence}
        for c in claims
      ],
      ["claim", "verdict", "evidence"],
    ).rstrip("\n")
  )
  for claim in claims:
    lines += ["", f"## ({claim.key}) {claim.title}", "", claim.statement, ""]
    lines.append(markdown_table(claim.rows, claim.columns, float_format=".4g").rstrip("\n"))
    if claim.plot is not None:
      claim.plot.draw(path.parent / FIGURES)
      lines += ["", f"![{claim.title}]({FIGURES}/{claim.plot.name}.png)"]
    lines += ["", f"**Verdict: {claim.verdict}.** {claim.evidence}"]
  path.parent.mkdir(parents=True, exist_ok=True)
  path.write_text("\n".join(lines) + "\n")
  return path
