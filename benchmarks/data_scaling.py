"""The data-scaling curve (issue 23): the held-out margin over the best copy baseline against the
number of distinct training scenes, at a fixed step budget.

Each point trains TokenGS from scratch with the recipe of the shipped weights (`python -m
experiments.re10k run pretrain`: the varied family, 16 frames a scene) on `--synthetic.num-train
N` scenes for `--steps` steps, in `<root>/n<N>_s<seed>/` (data in `<root>/data_n<N>_s<seed>/`),
and scores it feed-forward. The default run (`python -m experiments.re10k`) trains nothing (it
evaluates the shipped weights), so it cannot give a point. A run whose `metrics.json` is
already there is not repeated, so points can be added one at a time; one trained with other
steps or scenes is refused, not tabulated. The table and plot go to `docs/data_scaling.{md,png}`.

    python benchmarks/data_scaling.py --scenes 48 240 960 3840 --seeds 0 --steps 3000
    python benchmarks/data_scaling.py --scenes 48 240 960 3840 --seeds 0 --steps 3000 \
        --collect-only

Columns per test set: the feed-forward PSNR minus the better of the nearest-view and
input-average copies (dB), and the feed-forward LPIPS, holes and depth AbsRel.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys

REPO = pathlib.Path(__file__).resolve().parent.parent
SETS = ("test", "ood_galleries", "frozen_courtyards")
COPIES = ("nearest_view", "input_average")


def point_folder(root: pathlib.Path, scenes: int, seed: int) -> pathlib.Path:
  """Where the point (`scenes`, `seed`) writes its run, `metrics.json` included."""
  return root / f"n{scenes}_s{seed}"


def point_command(root: pathlib.Path, scenes: int, seed: int, steps: int) -> list[str]:
  """The command that trains and scores the point (`scenes`, `seed`) under `root`."""
  return [
    sys.executable,
    "-m",
    "experiments.re10k",
    "run",
    "pretrain",
    "--output-dir",
    str(point_folder(root, scenes, seed)),
    "--synthetic-dir",
    str(root / f"data_n{scenes}_s{seed}"),
    "--synthetic.num-train",
    str(scenes),
    "--seed",
    str(seed),
    "--train.steps",
    str(steps),
    "--train.checkpoint-every",
    str(steps),
    "--eval.no-pixel-baseline",
    "--eval.tuning-steps",
    "0",
    "--eval.video-frames",
    "0",
  ]


def run_point(root: pathlib.Path, scenes: int, seed: int, steps: int, extra: list[str]) -> None:
  if (point_folder(root, scenes, seed) / "metrics.json").exists():
    return
  command = point_command(root, scenes, seed, steps) + extra
  print("[scaling]", " ".join(command), flush=True)
  subprocess.run(command, cwd=REPO, check=True)


def checked_metrics(out: pathlib.Path, scenes: int, steps: int) -> dict:
  """`out/metrics.json`, refused unless its run trained `steps` steps on `scenes` scenes (a
  folder left by another budget, or by a run that trained nothing, is not this curve's point)."""
  metrics = json.loads((out / "metrics.json").read_text())
  trained = (metrics.get("train_steps"), metrics["experiment"]["synthetic"]["num_train"])
  if trained != (steps, scenes):
    raise SystemExit(
      f"{out}: trained {trained[0]} steps on {trained[1]} scenes, not {steps} on {scenes}; "
      "remove the folder or ask for its budget"
    )
  return metrics


def margins(metrics: dict) -> dict[str, dict[str, float]]:
  """Per test set: trained PSNR over the best copy, and trained LPIPS / holes / AbsRel."""
  sets = {"test": metrics, **metrics.get("other_test_sets", {})}
  rows = {}
  for name in SETS:
    if name not in sets:
      continue
    means = {method: v["mean"] for method, v in sets[name]["metrics"].items()}
    trained = means["trained"]
    rows[name] = {
      "margin": trained["psnr"] - max(means[c]["psnr"] for c in COPIES),
      "lpips": trained.get("lpips", float("nan")),
      "holes": trained.get("holes", float("nan")),
      "absrel": trained.get("depth_absrel", float("nan")),
    }
  return rows


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--scenes", type=int, nargs="+", default=[48, 240, 960])
  parser.add_argument("--seeds", type=int, nargs="+", default=[0])
  parser.add_argument("--steps", type=int, default=6000, help="training steps of every point")
  parser.add_argument("--root", default="outputs/data_scaling")
  parser.add_argument("--collect-only", action="store_true", help="tabulate existing runs only")
  parser.add_argument("--docs", default=str(REPO / "docs"))
  args, extra = parser.parse_known_args()
  root = pathlib.Path(args.root)
  lines = [
    "| scenes | seed | " + " | ".join(f"{s} margin / LPIPS / holes / AbsRel" for s in SETS) + " |",
    "|---|---|" + "---|" * len(SETS),
  ]
  curves: dict[str, tuple[list[float], list[float]]] = {s: ([], []) for s in SETS}
  for scenes in args.scenes:
    for seed in args.seeds:
      out = point_folder(root, scenes, seed)
      if not args.collect_only:
        run_point(root, scenes, seed, args.steps, extra)
      if not (out / "metrics.json").exists():
        continue
      rows = margins(checked_metrics(out, scenes, args.steps))
      cells = [
        "{margin:+.2f} / {lpips:.3f} / {holes:.3f} / {absrel:.3f}".format(**rows[s])
        if s in rows
        else ""
        for s in SETS
      ]
      lines.append(f"| {scenes} | {seed} | " + " | ".join(cells) + " |")
      for s in rows:
        curves[s][0].append(scenes)
        curves[s][1].append(rows[s]["margin"])
  table = "\n".join(lines) + "\n"
  command = " ".join(["python benchmarks/data_scaling.py", *sys.argv[1:]])
  print(table)
  docs = pathlib.Path(args.docs)
  (docs / "data_scaling.md").write_text(
    f"# Data scaling (generated by `{command}`)\n\n"
    "Feed-forward PSNR minus the better copy baseline (dB), LPIPS, holes and depth AbsRel of the "
    "trained model per test set, against distinct training scenes of the varied family, each "
    f"point trained from scratch by `run pretrain` for {args.steps} steps.\n\n"
    + table
    + "\n![data scaling](data_scaling.png)\n"
  )
  sys.path.insert(0, str(REPO))
  from experiments import figures

  figures.line_plot(
    docs / "data_scaling.png",
    {s: c for s, c in curves.items() if c[0]},
    title=f"Held-out margin over the best copy vs training scenes ({args.steps} steps)",
    xlabel="distinct training scenes",
    ylabel="PSNR margin (dB)",
    log_x=True,
  )


if __name__ == "__main__":
  main()
