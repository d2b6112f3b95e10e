"""Run time against error (issue 27, item 1): the choices a user makes, on one chart and table.

    python benchmarks/pareto.py                # every point, all 24 galleries -> docs/pareto.{png,md}
    python benchmarks/pareto.py --scenes 8     # the first 8 galleries
    python benchmarks/pareto.py --quick        # 2 galleries, 4 points (development)

Every point is the shipped RE10K default (`experiments/pretrained/re10k_synthetic/params.msgpack`,
the `synthetic-tiny` preset of `experiments/re10k.py`) with one choice changed, scored on its
out-of-distribution galleries (`ood_galleries`, written by `data.ensure_galleries` to the preset's
`synthetic_dir` when missing, the set `python -m experiments.re10k` scores) with the experiment's
own pieces: methods as `tasks.Task.methods` builds them (the tuning targets, steps and rates of
`--eval.tuning-*`, the run's objective and tuning loss), token counts as
`experiments.studies.token_count` resamples the trained table (`train.transplant_params`), and
scores, prediction and render times from `evaluation.evaluate`, the one evaluation code path.

The points: feed-forward; token tuning at 5 / 10 / 25 / 50 / 100 steps; Gaussian tuning and joint
tuning (tokens + Gaussians) at the default's 50 steps; 32 / 64 / 128 / 256 tokens (512 trained);
bf16 matmul operands (`ModelConfig.matmul_dtype="bfloat16"`) feed-forward and with 50 tuning
steps; the exact skips (`Method.compact`: `render_targets(compact=True)`, docs/benchmarks.md,
"Skipping what a scene does not need") feed-forward and with 50 tuning steps. The nearest input
view is listed as the copy a model must beat (not drawn: it renders nothing).

Seconds per scene: what a user pays for a scene's target images, the prediction (reconstruction
and any tuning; `MethodScores.predict_seconds`) plus the target render (`render_seconds`), scoring
left out, the median over the scenes of one timed pass that runs every point on a scene before
the next scene (so a change of the machine's load falls on all points alike), after one warm-up
scene per point. Compile seconds: the warm-up scene's prediction + render minus the same scene's
in the timed pass, so a point pays only for what no earlier point compiled (the warm-ups run in
the table's order; the persistent compilation cache is a fresh, empty folder for each run).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import pathlib
import platform
import sys
import tempfile
from collections.abc import Callable

import numpy as np

REPO = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))  # `python benchmarks/pareto.py` imports `experiments`

TUNING_STEPS = (5, 10, 25, 50, 100)
TOKEN_COUNTS = (32, 64, 128, 256)
QUICK_POINTS = ("feed-forward", "token tuning 5", "bf16 matmuls", "skips")
COPY = "nearest input view"


@dataclasses.dataclass(frozen=True)
class Point:
  """One measured choice: its name, its legend group, its label on the chart and
  `() -> evaluation.Method`."""

  name: str
  group: str
  label: str
  method: Callable


def _methods(task, experiment, params, **eval_changes) -> dict:
  """The run's methods (`tasks.Task.methods`) with `--eval.*` fields changed."""
  changed = dataclasses.replace(
    experiment, eval=dataclasses.replace(experiment.eval, **eval_changes)
  )
  return task.methods(changed, params, include_untrained=False)


def _tuned(task, experiment, params, target: str, steps: int):
  """The tuned method `--eval.tuning-target target --eval.tuning-steps steps` scores."""
  from tokengs_jax import evaluation

  methods = _methods(task, experiment, params, tuning_target=target, tuning_steps=steps)
  return methods[evaluation.TUNED_METHODS[target]]


def _tokens(task, experiment, params, count: int):
  """Feed-forward with the trained token table resampled to `count` rows (as the token-count
  study does it, no retraining)."""
  from experiments.studies.token_count import TokenCount, model_for

  config, resampled = model_for(
    TokenCount(experiment=experiment), experiment.model, params, count, out=None
  )
  changed = dataclasses.replace(experiment, model=config)
  return _methods(task, changed, resampled, tuning_steps=0)["trained"]


def points(task, experiment, params) -> list[Point]:
  """Every point, in measuring order (feed-forward first: it compiles the shared render)."""
  bf16 = dataclasses.replace(experiment, model=experiment.model.replace(matmul_dtype="bfloat16"))
  steps = experiment.eval.tuning_steps

  def compact(method):
    return dataclasses.replace(method, compact=True)

  tuned = lambda e=experiment, target="tokens", n=steps: _tuned(task, e, params, target, n)  # noqa: E731
  feed_forward = lambda e=experiment: _methods(task, e, params, tuning_steps=0)["trained"]  # noqa: E731
  found = [Point("feed-forward", "feed-forward", "ff", feed_forward)]
  found += [
    Point(f"token tuning {n}", "token tuning", f"tok {n}", lambda n=n: tuned(n=n))
    for n in TUNING_STEPS
  ]
  found += [
    Point(f"Gaussian tuning {steps}", "Gaussian / joint tuning", f"gs {steps}",
      lambda: tuned(target="gaussians")),
    Point(f"joint tuning {steps}", "Gaussian / joint tuning", f"joint {steps}",
      lambda: tuned(target="tokens+gaussians")),
  ]  # fmt: skip
  found += [
    Point(f"{k} tokens", "token count", f"{k} tk", lambda k=k: _tokens(task, experiment, params, k))
    for k in TOKEN_COUNTS
  ]
  found += [
    Point("bf16 matmuls", "bf16 matmuls", "bf16", lambda: feed_forward(bf16)),
    Point(f"bf16, token tuning {steps}", "bf16 matmuls", f"bf16 tok {steps}", lambda: tuned(bf16)),
    Point("skips", "skips (compact)", "skips", lambda: compact(feed_forward())),
    Point(f"skips, token tuning {steps}", "skips (compact)", f"skips tok {steps}",
      lambda: compact(tuned())),
  ]  # fmt: skip
  return found


def galleries(experiment, count: int) -> list:
  """The first `count` (0: all) `ood_galleries` scenes, (key, batch of one), written when
  missing (before any JAX work: the generator forks)."""
  from experiments import data

  root = data.ensure_galleries(experiment)
  held_out = data.HeldOutSet(root / "test", str(root / "eval_index.json"), count)
  scenes = data.evaluation_scenes(experiment, held_out=held_out)
  if count and len(scenes) < count:
    raise ValueError(f"{root} holds {len(scenes)} galleries, {count} asked for")
  return scenes


def warm_up(name: str, method, scenes: list, scorer) -> float:
  """Seconds of a point's first prediction + render (the first scene): compilation included."""
  from tokengs_jax import evaluation

  warm = evaluation.evaluate(scenes[:1], {name: method}, scorer).scores[name]
  print(f"[pareto] {name}: first scene {warm.predict_seconds[0] + warm.render_seconds[0]:.2f} s")
  return warm.predict_seconds[0] + warm.render_seconds[0]


def row_of(name: str, timed, first: float) -> dict:
  """A point's row from its `evaluation.MethodScores` over every scene and its warm-up seconds:
  PSNR / LPIPS, median seconds per scene (prediction + render, each alone), compile seconds."""
  predict, render = (np.asarray(x) for x in (timed.predict_seconds, timed.render_seconds))
  summary = timed.summary()
  row = {"method": name, "psnr": summary["psnr"], "lpips": summary.get("lpips", float("nan"))}
  row["seconds"] = float(np.median(predict + render))
  row["predict_s"], row["render_s"] = float(np.median(predict)), float(np.median(render))
  row["compile_s"] = max(0.0, first - float(predict[0] + render[0]))
  print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else str(v) for k, v in row.items()))
  return row


PANEL = (640, 480)  # pixels of each metric's chart


def _x_ticks(low: float, high: float) -> list[float]:
  """1-2-5 ticks of a log axis within [low, high] seconds."""
  ticks = [m * 10.0**e for e in range(-4, 4) for m in (1, 2, 5)]
  inside = [t for t in ticks if low <= t <= high]
  return inside or [low, high]


def _place(draw, font, u: float, v: float, text: str, taken: list, area: tuple) -> None:
  """Writes `text` beside the marker at (u, v): right, left, above or below, nearest first, the
  first spot inside the plot `area` (left, top, right, bottom) that overlaps no earlier label
  (else the first spot inside), so close points stay readable; a label moved away from its marker
  gets a grey leader line."""
  width = draw.textlength(text, font=font)
  spots = [(u + 6, v - 6), (u - 6 - width, v - 6), (u - width / 2, v - 18), (u - width / 2, v + 6)]
  for dy in (-18, 6, -30, 18, -42, 30, -54, 42):
    spots += [(u + 6, v + dy), (u - 6 - width, v + dy)]
  boxes = [(x, y, x + width, y + 12) for x, y in spots]
  inside = [b for b in boxes if area[0] <= b[0] and b[2] <= area[2] and area[1] <= b[1]
    and b[3] <= area[3]] or boxes  # fmt: skip
  free = [b for b in inside if not any(_overlap(b, t) for t in taken)]
  box = (free or inside)[0]
  taken.append(box)
  if box[1] > v + 6 or box[3] < v - 6:  # not level with its marker
    edge = box[0] if box[0] > u else box[2]
    draw.line([u, v, edge, box[1] + 6], fill=(160, 160, 160))
  draw.text(box[:2], text, fill=(0, 0, 0), font=font)


def _overlap(a: tuple, b: tuple) -> bool:
  return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def panel(rows: list[dict], groups: list[str], metric: str, title: str, ylabel: str):
  """One metric against seconds per scene (log axis): a marker and a label per point, coloured by
  group, token tuning joined in step order.  -> PIL image [PANEL]."""
  from experiments import figures

  series = {g: ([r["seconds"] for r in rows if r["group"] == g],) for g in groups}
  series = {
    g: (xs, [r[metric] for r in rows if r["group"] == g]) for g, (xs,) in series.items() if xs
  }
  clean = figures._finite_series(series, log_x=True)
  axes = figures._Axes.fit(clean, True, PANEL)
  (x_lo, x_hi), (y_lo, y_hi) = axes.x_range, axes.y_range
  x_pad, y_pad = max(0.08 * (x_hi - x_lo), 0.05), 0.04 * (y_hi - y_lo)  # no marker on a frame
  axes = dataclasses.replace(
    axes,
    x_range=(x_lo - x_pad, x_hi + x_pad),
    y_range=(y_lo - y_pad, y_hi + y_pad),
    x_ticks=_x_ticks(10.0 ** (x_lo - x_pad), 10.0 ** (x_hi + x_pad)),
  )
  area = (figures._LEFT, figures._TOP, PANEL[0] - figures._RIGHT, PANEL[1] - figures._BOTTOM)
  image, draw, font = figures._chart(axes, title=title, xlabel="seconds per scene", ylabel=ylabel)
  labels = []  # (label, u, v): placed after every marker is down, around all of them
  for group, color in zip(groups, figures.PALETTE):
    members = [r for r in rows if r["group"] == group and np.isfinite(r[metric])]
    xy = [(axes.u(r["seconds"]), axes.v(r[metric])) for r in members]
    figures._draw_series(draw, xy, color, joined=group == "token tuning")
    labels += [(r["label"], u, v) for r, (u, v) in zip(members, xy)]
  taken = [(u - 4, v - 4, u + 4, v + 4) for _, u, v in labels]
  for text, u, v in labels:
    _place(draw, font, u, v, text, taken, area)
  return image


def write_figure(path: pathlib.Path, rows: list[dict]) -> None:
  """docs/pareto.png: the PSNR and LPIPS panels side by side over one legend row."""
  from PIL import Image, ImageDraw

  from experiments import figures

  groups = list(dict.fromkeys(r["group"] for r in rows))
  left = panel(rows, groups, "psnr", "PSNR on the galleries (higher is better)", "PSNR (dB)")
  right = panel(rows, groups, "lpips", "LPIPS on the galleries (lower is better)", "LPIPS")
  image = Image.new("RGB", (2 * PANEL[0], PANEL[1] + 28), (255, 255, 255))
  image.paste(left, (0, 0))
  image.paste(right, (PANEL[0], 0))
  draw, font, x = ImageDraw.Draw(image), figures._font(), 16
  for group, color in zip(groups, figures.PALETTE):
    draw.ellipse([x, PANEL[1] + 9, x + 8, PANEL[1] + 17], fill=color)
    draw.text((x + 12, PANEL[1] + 7), group, fill=(0, 0, 0), font=font)
    x += 24 + draw.textlength(group, font=font)
  path.parent.mkdir(parents=True, exist_ok=True)
  image.save(path)


HEADER = ("method", "PSNR (dB)", "LPIPS", "s / scene", "prediction s", "render s", "compile s")


def machine_state() -> dict:
  """What the seconds depend on: CPU, cores, load, niceness, JAX and its platform."""
  import jax

  model_name = platform.processor() or "?"
  cpuinfo = pathlib.Path("/proc/cpuinfo")
  if cpuinfo.exists():
    names = [
      ln.split(":", 1)[1].strip() for ln in cpuinfo.read_text().splitlines() if "model name" in ln
    ]
    model_name = names[0] if names else model_name
  return {
    "cpu": f"{model_name}, {os.cpu_count()} cores",
    "jax": f"jax {jax.__version__} on {jax.devices()[0].platform}",
    "niceness": os.nice(0),
    "date": datetime.datetime.now().strftime("%Y-%m-%d %H:%M"),
  }


def _cells(row: dict) -> list[str]:
  return [
    row["method"],
    f"{row['psnr']:.2f}",
    f"{row['lpips']:.4f}",
    *(f"{row[k]:.4f}" for k in ("seconds", "predict_s", "render_s")),
    f"{row['compile_s']:.1f}",
  ]


def write_table(path: pathlib.Path, rows: list[dict], copy: dict, facts: dict) -> None:
  """docs/pareto.md: the command, the machine state, the table and what its columns mean."""
  lines = [
    "# Run time against error (issue 27)",
    "",
    "Generated, with `pareto.png` beside it, by (from the repository root):",
    "",
    f"    {facts['command']}",
    "",
    f"- Scenes: the first {facts['scenes']} of the RE10K default's 24 `ood_galleries` "
    f"({facts['views']} each); model: the shipped `synthetic-tiny` weights ({facts['model']}); "
    "PSNR / LPIPS: `evaluation.evaluate`, mean over scenes.",
    f"- Machine: {facts['cpu']}; {facts['jax']}; niceness {facts['niceness']}; {facts['date']}.",
    f"- Load average (1 / 5 / 15 min) before: {facts['load_before']}, after: "
    f"{facts['load_after']}. The seconds are figures of the machine as loaded then (other runs "
    "shared its cores): compare the points with each other, not with other tables.",
    "",
    "| " + " | ".join(HEADER) + " |",
    "|" + "---|" * len(HEADER),
  ]
  lines += ["| " + " | ".join(_cells(r)) + " |" for r in [*rows, copy]]
  lines += [
    "",
    f"- The last row, the {COPY} (`evaluation.baselines`), is the copy a model must beat; it "
    "renders nothing and is not drawn.",
    *(f"- {note.format(**facts)}" for note in NOTES),
  ]
  path.parent.mkdir(parents=True, exist_ok=True)
  path.write_text("\n".join(lines) + "\n")


NOTES = (
  "s / scene: the median over the scenes of prediction (reconstruction and any tuning, arrays "
  "ready: `MethodScores.predict_seconds`) plus the target render (`render_seconds`); scoring "
  "left out. One timed pass runs every point on a scene before the next scene, after a "
  "warm-up scene per point, so a change of load falls on all points alike.",
  "compile s: the warm-up scene's prediction + render minus the same scene's in the timed pass. "
  "The points run in the table's order in one process (a fresh persistent compilation cache), "
  "so a point pays only for what no earlier one compiled: the skips and the bf16 points share "
  "the target render with feed-forward, and tuning at other step counts compiles its scan anew.",
  "Token counts: the trained {tokens}-token table resampled to K rows (`train.transplant_params`, as "
  "`experiments/studies/token_count.py`), no retraining; feed-forward.",
  "Tuning: `tasks.Task.methods` with `--eval.tuning-target tokens|gaussians|tokens+gaussians "
  "--eval.tuning-steps N` (lr {token_rate:g} tokens, {gaussian_rate:g} Gaussians; the run's tuning "
  "loss).",
  "bf16: `ModelConfig.matmul_dtype='bfloat16'` (bf16 operands, float32 accumulation).",
  "skips: `Method.compact`, i.e. `render_targets(compact=True)`: the Gaussians no target camera "
  "can draw moved out before the render (the same images, exactly).",
)


def measure_all(experiment, scenes: list, names) -> tuple[list[dict], dict]:
  """(a row per point named in `names`, None: every point; the copy's row)."""
  from experiments import tasks, weights
  from tokengs_jax import evaluation

  params = weights.load_params(experiment.checkpoint)
  chosen = points(tasks.Task(), experiment, params)
  unknown = set(names or ()) - {p.name for p in chosen}
  if unknown:
    raise ValueError(f"unknown points {sorted(unknown)}; known: {[p.name for p in chosen]}")
  chosen = [p for p in chosen if names is None or p.name in names]
  scorer = evaluation.Scorer(lpips=True)
  methods = {p.name: p.method() for p in chosen}
  methods[COPY] = evaluation.baselines()["nearest_view"]
  first = {name: warm_up(name, method, scenes, scorer) for name, method in methods.items()}
  # One pass, every method on a scene before the next scene: a change of the machine's load
  # falls on every point alike.
  timed = evaluation.evaluate(scenes, methods, scorer).scores
  rows = [row_of(name, timed[name], first[name]) for name in methods]
  for row, p in zip(rows, chosen):
    row.update(group=p.group, label=p.label)
  return rows[:-1], rows[-1]


def main(argv: list[str] | None = None) -> list[dict]:
  from experiments import re10k
  from tokengs_jax import process

  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--scenes", type=int, default=None, help="galleries (default all 24)")
  parser.add_argument("--quick", action="store_true", help=f"2 galleries, points {QUICK_POINTS}")
  parser.add_argument("--points", nargs="+", default=None, help="only these points (names)")
  parser.add_argument("--out", default=str(REPO / "docs"), help="folder of pareto.{png,md}")
  parser.add_argument("--synthetic-dir", default=None, help="galleries' root (default: preset's)")
  process.add_arguments(parser)
  args = parser.parse_args(argv)
  experiment = re10k.PRESETS["synthetic-tiny"]
  count = args.scenes if args.scenes is not None else (2 if args.quick else 0)
  if args.synthetic_dir:  # a folder of its own: only the galleries asked for (each is fixed by
    # the seed and its index, so the first N are the same whatever the count)
    workers = 1 if count == 1 else experiment.synthetic.workers  # one scene: no worker to fork
    synthetic = dataclasses.replace(experiment.synthetic, num_ood=count or 24, workers=workers)
    experiment = dataclasses.replace(
      experiment, synthetic_dir=args.synthetic_dir, synthetic=synthetic
    )
  load_before = os.getloadavg()
  scenes = galleries(experiment, count)  # before JAX starts threads: the generator forks
  names = args.points or (list(QUICK_POINTS) if args.quick else None)
  with tempfile.TemporaryDirectory() as cache:
    process.setup(compile_cache=cache, host_memory=args.host_memory)
    rows, copy = measure_all(experiment, scenes, names)
  out = pathlib.Path(args.out)
  _, batch = scenes[0]
  facts = machine_state()
  facts.update(scenes=len(scenes), load_before=_load(load_before), load_after=_load())
  config = experiment.model
  facts.update(
    model=f"{config.num_gs_tokens} tokens x {config.gaussians_per_token} Gaussians",
    tokens=config.num_gs_tokens,
    token_rate=experiment.eval.tuning_learning_rate,
    gaussian_rate=experiment.eval.tuning_gaussian_learning_rate,
  )
  facts["views"] = "{}x{}, {} inputs, {} targets".format(
    *batch["target_images"].shape[-3:-1],
    batch["context_images"].shape[1],
    batch["target_images"].shape[1],
  )
  command = " ".join(["python benchmarks/pareto.py", *(argv if argv is not None else sys.argv[1:])])
  facts["command"] = f"nice -n {facts['niceness']} {command}" if facts["niceness"] else command
  write_table(out / "pareto.md", rows, copy, facts)
  write_figure(out / "pareto.png", rows)
  print(f"[pareto] wrote {out / 'pareto.md'} and {out / 'pareto.png'}", flush=True)
  return [*rows, copy]


def _load(values=None) -> str:
  return " / ".join(f"{v:.2f}" for v in (values or os.getloadavg()))


if __name__ == "__main__":
  main()
