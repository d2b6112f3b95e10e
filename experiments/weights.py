"""Network weights on disk: msgpack params, the starting weights of a command, and the weights
shipped in the repository (`ship`).

    python -m experiments.weights ship outputs/re10k/pretrain experiments/pretrained/re10k_synthetic
"""

from __future__ import annotations

import hashlib
import json
import pathlib
import shutil
import subprocess
import sys

import jax

from experiments.config import Experiment
from tokengs_jax import model, process


def save_params(path, params) -> pathlib.Path:
  """Writes a params pytree as msgpack (flax.serialization)."""
  from flax import serialization

  path = pathlib.Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  path.write_bytes(serialization.msgpack_serialize(jax.device_get(params)))
  return path


def load_params(path) -> dict:
  from flax import serialization

  return serialization.msgpack_restore(pathlib.Path(path).read_bytes())


def beside(params_path, name: str) -> pathlib.Path | None:
  """`<name>.msgpack` in the folder of `params_path` if it exists: where a run keeps its trained
  baselines' weights beside its own."""
  path = pathlib.Path(params_path).parent / f"{name}.msgpack"
  return path if path.exists() else None


def initial_params(experiment: Experiment, *, finetune: bool):
  """Fresh weights, or (finetune / eval) the given checkpoint grown into the model if needed.

  An official checkpoint is read strictly for evaluation (it must be the model's architecture)
  and leniently for finetuning, as the official `init_tokens_from_existing` allows: more tokens,
  dynamic tokens or another latent count than it holds are grown by `transplant_params`, with
  every missing or unexpected tensor logged (a mis-shaped weight is still refused)."""
  config = experiment.model
  fresh = model.init_params(jax.random.key(experiment.seed), config)
  if experiment.official_checkpoint:
    loaded = model.load_official_checkpoint(
      experiment.official_checkpoint, config, strict=not finetune
    )
  elif experiment.checkpoint:
    loaded = load_params(experiment.checkpoint)
  else:
    if finetune:
      raise ValueError("finetune needs --checkpoint or --official-checkpoint")
    return fresh
  from tokengs_jax.train import transplant_params

  params, report = transplant_params(jax.random.key(experiment.seed + 1), loaded, fresh)
  for line in report:
    print(f"[params] {line}", flush=True)
  return params


def source_commit() -> str | None:
  """The checkout's commit (`git rev-parse HEAD`, "+" appended when files differ from it), or
  None outside a git checkout: recorded in metrics.json, so shipped weights name their code."""
  root = pathlib.Path(__file__).resolve().parent.parent

  def git(*args):
    try:
      return subprocess.run(
        ["git", *args], cwd=root, capture_output=True, text=True, check=False, timeout=30
      )
    except (OSError, subprocess.TimeoutExpired):
      return None

  head = git("rev-parse", "HEAD")
  if head is None or head.returncode != 0:
    return None
  status = git("status", "--porcelain", "--untracked-files=no")
  dirty = status is None or bool(status.stdout.strip())
  return head.stdout.strip() + ("+" if dirty else "")


def sha256(path) -> str:
  return hashlib.sha256(pathlib.Path(path).read_bytes()).hexdigest()


def ship(run_dir, destination) -> dict:
  """Copies a finished run's weights (`params.msgpack` and its trained baselines'
  `<name>.msgpack`) to `destination` with `provenance.json`: the command, the experiment, the
  training time, the commit and each file's SHA-256, so the shipped weights can be reproduced
  and checked (`tests/test_pretrained.py`).

  A run that started from a checkpoint records, under `started_from`, the record of the weights
  it started from (`_record_of_start`), so a chain of stages stays reproducible after the
  earlier stage's weights are overwritten.

  Weights already shipped in `destination` that the run did not write (a baseline it did not
  retrain) stay, and their record in the previous `provenance.json` moves under `carried_over`
  (a file that record does not vouch for, by name and SHA-256, is refused)."""
  run_dir, destination = pathlib.Path(run_dir), pathlib.Path(destination)
  provenance = _run_record(run_dir)
  checkpoint = provenance["experiment"].get("checkpoint")
  started_from = _record_of_start(pathlib.Path(checkpoint)) if checkpoint else None
  carried_over = _carried_over(destination, set(provenance["files"]))
  destination.mkdir(parents=True, exist_ok=True)
  for name in provenance["files"]:
    shutil.copyfile(run_dir / name, destination / name)
  files = {name: record["sha256"] for name, record in carried_over.items()}
  provenance["files"] = dict(sorted({**files, **provenance["files"]}.items()))
  if started_from is not None:
    provenance["started_from"] = started_from
  if carried_over:
    provenance["carried_over"] = carried_over
  (destination / "provenance.json").write_text(json.dumps(provenance, indent=1) + "\n")
  return provenance


def _run_record(run_dir: pathlib.Path) -> dict:
  """What `ship` records of a finished run: its metrics.json's command, commit, experiment,
  training time and devices, and the SHA-256 of each weights file it wrote."""
  metrics = json.loads((run_dir / "metrics.json").read_text())
  return {
    "command": metrics["command"],
    "commit": metrics.get("commit"),
    "experiment": metrics["experiment"],
    "train_steps": metrics.get("train_steps"),
    "train_seconds": metrics.get("train_seconds"),
    "total_seconds": metrics.get("total_seconds"),
    "devices": metrics.get("devices"),
    "files": {path.name: sha256(path) for path in sorted(run_dir.glob("*.msgpack"))},
  }


def _record_of_start(checkpoint: pathlib.Path) -> dict:
  """The record of the weights a run started from: the `provenance.json` of shipped weights (it
  must vouch for the checkpoint's SHA-256), or the record of the run folder that wrote them (not
  what that run started from: its checkpoint's path may since hold other weights); a checkpoint
  with neither is recorded by its SHA-256 alone."""
  if not checkpoint.exists():
    raise ValueError(f"{checkpoint}, which the run started from, is gone: nothing vouches for it")
  folder, digest = checkpoint.parent, sha256(checkpoint)
  if (folder / "provenance.json").exists():
    record = json.loads((folder / "provenance.json").read_text())
  elif (folder / "metrics.json").exists():
    record = _run_record(folder)
  else:
    return {"files": {checkpoint.name: digest}}
  if record["files"].get(checkpoint.name) != digest:
    raise ValueError(f"{checkpoint} is not the file its folder's record describes")
  return record


def _carried_over(destination: pathlib.Path, written: set[str]) -> dict:
  """Name -> {sha256, command, commit, train_steps} of each weights file in `destination` that
  a ship writing `written` leaves in place, from the provenance that shipped it."""
  kept = sorted(path for path in destination.glob("*.msgpack") if path.name not in written)
  if not kept:
    return {}
  record_path = destination / "provenance.json"
  previous = json.loads(record_path.read_text()) if record_path.exists() else {}
  records = {}
  for path in kept:
    digest = sha256(path)
    if previous.get("files", {}).get(path.name) != digest:
      raise ValueError(
        f"{path} is not the file {record_path} records; remove it or ship the run that wrote it"
      )
    # a file carried over twice keeps the record of the run that trained it
    source = previous.get("carried_over", {}).get(path.name) or {
      field: previous.get(field) for field in ("command", "commit", "train_steps")
    }
    records[path.name] = {**source, "sha256": digest}
  return records


if __name__ == "__main__":
  process.setup()
  if len(sys.argv) != 4 or sys.argv[1] != "ship":
    sys.exit("usage: python -m experiments.weights ship RUN_DIR DESTINATION")
  print(json.dumps(ship(sys.argv[2], sys.argv[3])["files"], indent=1))
