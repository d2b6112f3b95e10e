"""Runs a module as `__main__` and records the files this process opened for writing under a folder
(a Python audit hook on "open"), for `tests/test_multiprocess.py`:

    python tests/multiprocess_writes.py WATCHED RECORD -m experiments.re10k run smoke ...

writes `RECORD.<TOKENGS_PROCESS_ID>.json`: the sorted paths relative to WATCHED. Files written by
native code (tensorstore array chunks of orbax checkpoints) are not seen.
"""

import atexit
import json
import os
import runpy
import sys


def main() -> None:
  watched, record, flag, module, *args = sys.argv[1:]
  assert flag == "-m", "usage: multiprocess_writes.py WATCHED RECORD -m MODULE [ARGS...]"
  watched = os.path.realpath(watched)
  written = set()

  def hook(event, event_args):
    if event != "open" or not isinstance(event_args[0], str | bytes | os.PathLike):
      return
    path, mode, flags = event_args
    writing = (mode is not None and any(c in mode for c in "wax+")) or bool(
      flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT)
    )
    path = os.path.realpath(os.fsdecode(path))
    if writing and path.startswith(watched + os.sep):
      written.add(os.path.relpath(path, watched))

  def dump() -> None:
    index = os.environ.get("TOKENGS_PROCESS_ID", "0")
    with open(f"{record}.{index}.json", "w") as file:
      json.dump(sorted(written), file)

  atexit.register(dump)
  sys.addaudithook(hook)
  sys.argv = [module, *args]
  runpy.run_module(module, run_name="__main__", alter_sys=True)


if __name__ == "__main__":
  main()
