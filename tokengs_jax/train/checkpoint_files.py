"""What a checkpoint directory may hold, and one-line errors for the writes a disk refuses.

The directory is the user's and may hold what orbax never writes: a step that is a symbolic link
(orbax deletes old steps with `rmtree`, which refuses a link, so every later save raised; and a
marker written into it landed outside the directory), or a FIFO, socket or device in a step
(orbax opens every file it lists or restores, and opening a FIFO blocks forever). Such a step is
set aside, with the reason logged, before orbax looks at the directory.

orbax reports a full or unwritable disk from its writer threads as tensorstore `ValueError`s
("RESOURCE_EXHAUSTED: ... [os_error_code='28']") or `OSError`s, each logged with its traceback
on the way (hundreds of lines, the last of them at exit); `CheckpointWriteError` says in one line
what failed, where, and what to do. A save that cannot fit is refused before orbax writes
(`missing_space`), so the usual way a disk fills up costs that one line alone.
"""

from __future__ import annotations

import errno
import os
import pathlib
import re
import stat

STEP_NAME = re.compile(r"\d+")  # orbax's step directories (no step prefix)
UNUSABLE_MARKER = "UNUSABLE.txt"

_FILE_KINDS = {
  stat.S_IFLNK: "symbolic link",
  stat.S_IFIFO: "FIFO",
  stat.S_IFSOCK: "socket",
  stat.S_IFCHR: "character device",
  stat.S_IFBLK: "block device",
  stat.S_IFREG: "regular file",
}


def _kind(mode: int) -> str:
  return _FILE_KINDS.get(stat.S_IFMT(mode), "directory")


def foreign_step_reason(step_dir: pathlib.Path) -> str | None:
  """Why `step_dir` is not a step as orbax writes one (a directory, not a link, holding only
  directories and regular files, none of them links); None when it is one."""
  mode = step_dir.lstat().st_mode
  if stat.S_ISLNK(mode):
    return f"a symbolic link (to {os.readlink(step_dir)}), not a directory orbax wrote"
  if not stat.S_ISDIR(mode):
    return f"a {_kind(mode)}, not a directory"
  for parent, directories, files in os.walk(step_dir):  # never descends into a linked directory
    for name in directories + files:
      path = pathlib.Path(parent, name)
      mode = path.lstat().st_mode
      if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        return f"holding {path.relative_to(step_dir)}, a {_kind(mode)} (orbax writes none)"
  return None


def set_aside(step_dir: pathlib.Path, reason: str) -> pathlib.Path:
  """Renames `step_dir` to `<step>.unusable[.k]` beside it (invisible to orbax, kept for
  inspection) and writes the reason into it as `UNUSABLE.txt`; returns the new path.

  A link is renamed, not followed: the marker is written only into a real directory, and never
  through a link in its place.
  """
  target, k = step_dir.with_name(f"{step_dir.name}.unusable"), 1
  while os.path.lexists(target):
    target, k = step_dir.with_name(f"{step_dir.name}.unusable.{k}"), k + 1
  step_dir.rename(target)
  if stat.S_ISDIR(target.lstat().st_mode):
    marker = target / UNUSABLE_MARKER
    if os.path.lexists(marker):
      marker.unlink()
    descriptor = os.open(marker, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644)
    with os.fdopen(descriptor, "w") as file:
      file.write(reason + "\n")
  return target


class CheckpointWriteError(RuntimeError):
  """The disk refused a checkpoint write (full, or not writable); the message is one line."""


_ELSEWHERE = "choose another checkpoint directory (experiments: --output-dir)"
_REFUSALS = {  # errno: (what failed, what to do)
  errno.ENOSPC: ("no space left on device", f"free space there or {_ELSEWHERE}"),
  errno.EDQUOT: ("disk quota exceeded", f"free space there or {_ELSEWHERE}"),
  errno.EACCES: ("permission denied", f"make it writable or {_ELSEWHERE}"),
  errno.EPERM: ("operation not permitted", f"make it writable or {_ELSEWHERE}"),
  errno.EROFS: ("read-only file system", _ELSEWHERE),
}
_TENSORSTORE_ERRNO = re.compile(r"\[os_error_code='(\d+)'\]")


def refused_write_errno(error: BaseException) -> int | None:
  """The errno of a full or unwritable disk in `error` or the errors it was raised from: an
  `OSError`'s own, or the `os_error_code` a tensorstore error message carries; else None."""
  seen = set()
  while error is not None and id(error) not in seen:
    seen.add(id(error))
    code = error.errno if isinstance(error, OSError) else None
    if code is None and (match := _TENSORSTORE_ERRNO.search(str(error))):
      code = int(match.group(1))
    if code in _REFUSALS:
      return code
    error = error.__cause__ or error.__context__
  return None


def _refusal(code: int, directory: pathlib.Path, step: int | None, detail: str = ""):
  what, remedy = _REFUSALS[code]
  writing = f"checkpoint step {step}" if step is not None else "checkpoints"
  return CheckpointWriteError(f"{what} writing {writing} to {directory}: {detail}{remedy}")


def write_error(error: BaseException, directory: pathlib.Path, step: int | None):
  """A `CheckpointWriteError` for `error` when the disk refused the write, else None."""
  code = refused_write_errno(error)
  return None if code is None else _refusal(code, directory, step)


def step_bytes(step_dir: pathlib.Path) -> int:
  """Bytes of the regular files in a step directory (what the next save will write again)."""
  return sum(
    path.lstat().st_size for path in step_dir.rglob("*") if stat.S_ISREG(path.lstat().st_mode)
  )


def missing_space(directory: pathlib.Path, step: int, needed: int, free: int):
  """The `CheckpointWriteError` of a save of `needed` bytes where only `free` are left."""
  detail = f"the step needs about {needed / 2**20:.1f} MiB, {free / 2**20:.1f} MiB are free; "
  return _refusal(errno.ENOSPC, directory, step, detail)
