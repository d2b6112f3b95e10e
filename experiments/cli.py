"""The entry points' command line (tyro): `[command] [preset] [--field value ...]`.

    python -m experiments.re10k                                  # run, default preset
    python -m experiments.re10k eval paper --data-dir /data/re10k --official-checkpoint w.safetensors
    python -m experiments.re10k run smoke --train.steps 10 --model.enc-depth 1
    python -m experiments.re10k eval --from-run outputs/re10k/smoke --eval.media-scenes 0

Commands are subcommands (`run` = train then eval, the default; `train`, `finetune`, `eval`), and
so are the presets (one subcommand per named `Experiment`, the default preset when omitted); every
field of the chosen preset is a flag (nested fields as `--train.steps`, `--model.num-gs-tokens`).

`eval --from-run RUN_DIR` takes the place of a preset: the experiment a finished run recorded in
its metrics.json, scoring the weights it trained (`RUN_DIR/params.msgpack`; a run that only
evaluated: the weights it evaluated) into `RUN_DIR/eval/`; flags override it as a preset's.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import sys
from collections.abc import Mapping, Sequence
from typing import Annotated, Union

import tyro

from experiments.config import Experiment, from_fields
from experiments.tasks import COMMANDS, Command, Task, execute
from tokengs_jax import process


def _invocation_type(presets: Mapping[str, Experiment], default_preset: str):
  """A tyro type: one subcommand per command, each holding one subcommand per preset."""
  preset_union = Union[
    tuple(  # noqa: UP007 (tyro needs a typing.Union of Annotated types)
      Annotated[type(p), tyro.conf.subcommand(name, default=p, description=f"preset {name!r}")]
      for name, p in presets.items()
    )
  ]

  # built with make_dataclass: the field types are objects of this call, not importable names
  invocation = dataclasses.make_dataclass(
    "Invocation",
    [
      ("command", tyro.conf.Suppress[str], dataclasses.field(default="run")),
      (
        "experiment",
        Annotated[preset_union, tyro.conf.arg(name="")],
        dataclasses.field(default=presets[default_preset]),
      ),
    ],
    frozen=True,
  )

  descriptions = {
    "run": "train, then evaluate (default)",
    "train": "train only",
    "finetune": "train from --checkpoint / --official-checkpoint",
    "eval": "evaluate --checkpoint / --official-checkpoint, or a finished run's weights with "
    "its settings: eval --from-run RUN_DIR [flags]",
  }
  command_union = Union[
    tuple(  # noqa: UP007
      Annotated[
        invocation,
        tyro.conf.subcommand(c, default=invocation(command=c), description=descriptions[c]),
      ]
      for c in COMMANDS
    )
  ]
  return command_union, invocation()


def _split_from_run(argv: Sequence[str]) -> tuple[str | None, list[str]]:
  """(the folder of `--from-run DIR` / `--from-run=DIR`, or None; the other arguments)."""
  rest, folders, args = [], [], iter(argv)
  for arg in args:
    if arg == "--from-run":
      folders.append(next(args, None))
    elif arg.startswith("--from-run="):
      folders.append(arg.removeprefix("--from-run="))
    else:
      rest.append(arg)
  if len(folders) > 1 or None in folders:
    raise SystemExit("--from-run takes one folder: eval --from-run RUN_DIR [flags]")
  return (folders[0] if folders else None), rest


def recorded_experiment(run_dir, experiment_type: type[Experiment]) -> Experiment:
  """The experiment a finished run recorded in `RUN_DIR/metrics.json`, set to score the weights
  it trained (`params.msgpack`, when it trained; else the weights it evaluated) into
  `RUN_DIR/eval/`, so the run's own results stay as they are."""
  run_dir = pathlib.Path(run_dir)
  metrics = run_dir / "metrics.json"
  if not metrics.is_file():
    raise SystemExit(f"--from-run {run_dir}: no metrics.json (a run / eval writes it) there")
  try:
    experiment = from_fields(experiment_type, json.loads(metrics.read_text())["experiment"])
  except (KeyError, TypeError, ValueError) as error:  # not this entry point's record
    raise SystemExit(
      f"--from-run {run_dir}: its metrics.json records no {experiment_type.__name__} "
      f"({type(error).__name__}: {error}); a run of another entry point?"
    ) from None
  changes = {"output_dir": str(run_dir / "eval")}
  if (run_dir / "params.msgpack").is_file():
    changes.update(checkpoint=str(run_dir / "params.msgpack"), official_checkpoint=None)
  return dataclasses.replace(experiment, **changes)


def _spelt_out(
  argv: list[str], presets: Mapping[str, Experiment], default_preset: str
) -> list[str]:
  """argv with an omitted command and preset written in ("run", the default preset).

  tyro reads the flags of a default subcommand that is left out by another route, one that
  drops the `--field.no-x` form of booleans ("Unrecognized options"); the spelt-out form
  takes every flag. A request for help is left as it is, so that it lists the commands."""
  if "-h" in argv or "--help" in argv:
    return argv
  command, rest = (argv[:1], argv[1:]) if argv and argv[0] in COMMANDS else (["run"], argv)
  # one preset (`--from-run`) is no subcommand: tyro makes a union of one type that type
  named = len(presets) == 1 or (rest and rest[0] in presets)
  return command + ([] if named else [default_preset]) + rest


def parse(
  argv: Sequence[str], presets: Mapping[str, Experiment], default_preset: str, prog: str
) -> tuple[Command, Experiment]:
  """`[command] [preset] [flags]` -> (command, experiment); `eval --from-run RUN_DIR [flags]`
  in place of a preset: the run's `recorded_experiment`."""
  run_dir, argv = _split_from_run(argv)
  if run_dir is not None:
    presets = {"from-run": recorded_experiment(run_dir, type(presets[default_preset]))}
    default_preset = "from-run"
  command_type, default = _invocation_type(presets, default_preset)
  parsed = tyro.cli(
    command_type,
    args=_spelt_out(list(argv), presets, default_preset),
    default=default,
    prog=prog,
    config=(tyro.conf.OmitSubcommandPrefixes, tyro.conf.CascadeSubcommandArgs),
  )
  if run_dir is not None and parsed.command != "eval":
    raise SystemExit(
      f"--from-run re-evaluates a run: eval --from-run RUN_DIR, not {parsed.command}"
    )
  return parsed.command, parsed.experiment


def main(
  presets: Mapping[str, Experiment],
  default_preset: str,
  prog: str,
  argv: Sequence[str] | None = None,
  task: Task | None = None,
) -> dict | None:
  argv = sys.argv[1:] if argv is None else list(argv)
  command, experiment = parse(argv, presets, default_preset, prog)
  process.setup()
  return execute(command, experiment, task, invocation=" ".join([prog] + argv))
