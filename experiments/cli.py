"""The entry points' command line (tyro): `[command] [preset] [--field value ...]`.

    python -m experiments.re10k                                  # run, default preset
    python -m experiments.re10k eval paper --data-dir /data/re10k --official-checkpoint w.safetensors
    python -m experiments.re10k run smoke --train.steps 10 --model.enc-depth 1

Commands are subcommands (`run` = train then eval, the default; `train`, `finetune`, `eval`), and
so are the presets (one subcommand per named `Experiment`, the default preset when omitted); every
field of the chosen preset is a flag (nested fields as `--train.steps`, `--model.num-gs-tokens`).
"""

from __future__ import annotations

import dataclasses
import sys
from collections.abc import Mapping, Sequence
from typing import Annotated, Union

import tyro

from experiments.config import Experiment
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
    "eval": "evaluate --checkpoint / --official-checkpoint",
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


def parse(
  argv: Sequence[str], presets: Mapping[str, Experiment], default_preset: str, prog: str
) -> tuple[Command, Experiment]:
  """`[command] [preset] [flags]` -> (command, experiment)."""
  command_type, default = _invocation_type(presets, default_preset)
  parsed = tyro.cli(
    command_type,
    args=list(argv),
    default=default,
    prog=prog,
    config=(tyro.conf.OmitSubcommandPrefixes, tyro.conf.CascadeSubcommandArgs),
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
