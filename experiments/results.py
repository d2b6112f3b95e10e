"""The results folder: metrics.json / metrics.md, grids, fly-through, PLY, TensorBoard scalars.

Every writer here writes only on the process that writes results
(`tokengs_jax.evaluation.writes_results()`, process 0); elsewhere it does nothing.

metrics.json: the run's settings and facts, plus the first (primary) test set's `metrics`
(method -> {"mean", "per_scene", "seconds"}), `checks` and, where the set has any, `notes`
(`Evaluation.notes`: scores its data could not give); further test sets go under
`other_test_sets` (name -> {"metrics", "checks", "notes"}). metrics.md has one table per test set.

Names read from data (scene keys) never become paths as they are: `data_path` makes them safe
file names inside their folder. Pictures and exports run in `media_step`s, after metrics.json.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import pathlib
import re
from collections.abc import Mapping, Sequence

import jax
import numpy as np

from experiments import figures
from experiments.config import EvalSettings
from tokengs_jax import evaluation, export, splatting


_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")
_NAME_CHARACTERS = 120  # of the sanitised name: with the hash and a suffix, far below 255 bytes


def safe_file_name(name: str) -> str:
  """A file name for a name read from data (a scene key): the name itself when it is letters,
  digits, `.`, `_` and `-` not starting with a dot; otherwise every run of other characters
  becomes `_`, leading dots go, and `+` and a hash of the original name are appended. So
  `/abs/x` or `../../x` names no other folder, and two keys never share a file: an unchanged
  name has no `+`, and changed ones differ by their hashes."""
  name = str(name)
  cleaned = _UNSAFE.sub("_", name).lstrip(".")[:_NAME_CHARACTERS]
  if cleaned and cleaned == name:
    return name
  return f"{cleaned}+{hashlib.sha256(name.encode()).hexdigest()[:12]}"


def data_path(folder, name: str, suffix: str) -> pathlib.Path:
  """`folder / (safe_file_name(name) + suffix)`: the path of a file named after data.

  Raises ValueError when it does not resolve inside `folder` (a link there pointing out of it):
  data never chooses where a file is written."""
  folder = pathlib.Path(folder)
  path = folder / (safe_file_name(name) + suffix)
  if not path.resolve().is_relative_to(folder.resolve()):
    raise ValueError(f"refusing to write {path}: it resolves to {path.resolve()}, outside {folder}")
  return path


@contextlib.contextmanager
def media_step(what: str, failures: list[str]):
  """One picture or export of a results folder, run after its metrics.json: an exception is
  printed in one line and appended to `failures` instead of raised, so a picture that cannot be
  written (a NaN Gaussian `write_ply` refuses, a missing video encoder, a path `data_path`
  refuses) costs itself only, never the scores or the other pictures."""
  try:
    yield
  except Exception as error:  # whatever broke a picture: reported, never fatal
    message = str(error).strip().splitlines()
    reason = f"{what}: {type(error).__name__}" + (f": {message[0]}" if message else "")
    print(f"[results] not written: {reason}", flush=True)
    failures.append(reason)


def markdown_table(
  rows: Mapping[str, Mapping[str, object]] | Sequence[Mapping[str, object]],
  columns: Sequence[str],
  header: str = "method",
  float_format: str = ".4f",
) -> str:
  """A Markdown table, one column per name of `columns` (blank where a row lacks it; floats as
  `float_format`): `rows` maps each row's name (the first column, under `header`) to its values,
  or is the rows themselves."""
  if isinstance(rows, Mapping):
    rows = [{**values, header: name} for name, values in rows.items()]
    columns = [header, *columns]
  lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
  for values in rows:
    cells = [
      format(values[c], float_format)
      if isinstance(values.get(c), float)
      else str(values.get(c, ""))
      for c in columns
    ]
    lines.append("| " + " | ".join(cells) + " |")
  return "\n".join(lines) + "\n"


def _set_payload(result: evaluation.Evaluation) -> dict:
  summary = result.summary()
  return {
    "metrics": {
      name: {"mean": summary[name], "per_scene": s.per_scene, "seconds": s.seconds}
      for name, s in result.scores.items()
    },
    "checks": evaluation.checks(summary),
    **({"notes": result.notes} if result.notes else {}),
  }


def _set_summary(name: str, result: evaluation.Evaluation) -> list[str]:
  """Markdown: the set's mean table, the methods that scored nothing, the notes (scores the
  data could not give), the checks."""
  summary = result.summary()
  columns = list(dict.fromkeys(c for values in summary.values() for c in values))
  count = max((len(s.per_scene) for s in result.scores.values()), default=0)
  text = [
    f"\n## Test set `{name}`\n",
    f"Mean over held-out scenes (each scene: mean over its target views); {count} scenes.\n",
    markdown_table(summary, columns),
  ]
  unscored = [method for method, values in summary.items() if not values]
  if unscored:
    text.append(f"\nScored no scene: {', '.join(unscored)}.\n")
  if result.notes:
    text += ["\nNotes:\n"] + [f"- {k}: {v}\n" for k, v in result.notes.items()]
  checks = evaluation.checks(summary)
  if checks:
    text += ["\nChecks:\n"] + [f"- {k}: {v}\n" for k, v in checks.items()]
  return text


def _set_per_scene(result: evaluation.Evaluation) -> list[str]:
  columns = list(dict.fromkeys(c for values in result.summary().values() for c in values))
  text = []
  for method, scores in result.scores.items():
    if scores.per_scene:
      text += [
        f"\n### {method}: per scene\n",
        markdown_table({s["key"]: s for s in scores.per_scene}, columns, header="scene"),
      ]
  return text


def write_metrics(out_dir, results: Mapping[str, evaluation.Evaluation], info: dict) -> dict:
  """metrics.json and metrics.md of named test sets (the first is the primary); returns the
  payload (also on processes that do not write)."""
  sets = {name: _set_payload(result) for name, result in results.items()}
  first = next(iter(sets), None)
  payload = {
    **info,
    "test_sets": list(sets),
    **(sets[first] if first else {}),
    "other_test_sets": {name: sets[name] for name in list(sets)[1:]},
  }
  if evaluation.writes_results():
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "metrics.json").write_text(json.dumps(payload, indent=1, default=str))
    text = [f"# {info.get('title', 'Results')}\n"]
    for name, result in results.items():
      text += _set_summary(name, result) + _set_per_scene(result)
    (out_dir / "metrics.md").write_text("".join(text))
  return payload


def summary_text(results: Mapping[str, evaluation.Evaluation]) -> str:
  """The mean table and checks of every test set (what a run prints at its end)."""
  return "".join(line for name, result in results.items() for line in _set_summary(name, result))


def write_scalars(writer, results: Mapping[str, evaluation.Evaluation], step: int) -> None:
  """eval/<method>/<metric> of the primary set, eval/<set>/<method>/<metric> of the others."""
  if writer is None:
    return
  for position, (name, result) in enumerate(results.items()):
    prefix = "eval/" if position == 0 else f"eval/{name}/"
    for method, values in result.summary().items():
      for metric, value in values.items():
        writer.add_scalar(f"{prefix}{method}/{metric}", value, step)


def scene_grid(entry: dict, methods: Sequence[str]) -> np.ndarray:
  """inputs | targets | one row per method | depth of the last Gaussian method (colour bar)."""
  batch = entry["batch"]
  rows = [
    ("inputs", list(batch["context_images"][0])),
    ("targets", list(batch["target_images"][0])),
  ]
  rows += [(m, list(entry[m]["rgb"])) for m in methods]
  splatted = [m for m in methods if entry[m]["depth"] is not None]
  near_far = None
  if splatted:
    last = entry[splatted[-1]]
    images, near_far = figures.depth_row(list(last["depth"]), list(last["alpha"]))
    rows.append((f"depth ({splatted[-1]})", images))
  return figures.labelled_grid(rows, title=str(entry["key"]), depth_range=near_far)


def write_grids(
  out_dir,
  kept: Sequence[dict],
  methods: Sequence[str],
  writer=None,
  step: int = 0,
  tag: str = "eval",
) -> list[pathlib.Path]:
  """grids/<scene>.png for every kept scene (and TensorBoard images)."""
  if not evaluation.writes_results():
    return []
  out_dir = pathlib.Path(out_dir)
  written = []
  for entry in kept:
    grid = scene_grid(entry, methods)
    written.append(export.save_png(data_path(out_dir, entry["key"], ".png"), grid))
    if writer is not None:
      writer.add_image(f"{tag}/{entry['key']}", grid, step, dataformats="HWC")
  return written


def write_training_pictures(writer, entry: dict, method: str, step: int) -> None:
  """TensorBoard's pictures of a run in training (`train.log_image_every`), of one kept scene
  (an `evaluation.evaluate` entry) and its `method`: the scene's grid as `train/images` (inputs,
  targets, the method's renders and depth, `scene_grid`) and histograms of its Gaussians (the
  first set: a dynamic model's at the first target's time), non-finite values left out:
  `gaussian/opacity`, `gaussian/log_scale` (every axis) and `gaussian/distance` (of the means
  from the origin of the normalised frame the model works in)."""
  writer.add_image("train/images", scene_grid(entry, [method]), step, dataformats="HWC")
  one = _first_set(entry, method)
  values = {
    "opacity": one.opacities,
    "log_scale": np.log(np.maximum(one.scales, np.finfo(np.float32).tiny)),
    "distance": np.linalg.norm(one.means, axis=-1),
  }
  for name, value in values.items():
    value = value[np.isfinite(value)]
    if value.size:
      bins = np.linspace(0.0, 1.0, 51) if name == "opacity" else "tensorflow"
      writer.add_histogram(f"gaussian/{name}", value, step, bins=bins)


def _first_set(entry: dict, method: str):
  """The first set ([1] or [1, Vt] -> [1]) of a kept scene's `method` Gaussians, on the host."""
  return jax.tree.map(np.asarray, entry[method]["gaussians"].first_set())


def write_scene_ply(path, entry: dict, method: str, min_opacity: float) -> list[pathlib.Path]:
  """A PLY of one kept scene's `method` Gaussians, without those of opacity below
  `min_opacity` (`export.write_ply`)."""
  if not evaluation.writes_results():
    return []
  one = _first_set(entry, method)
  return [
    export.write_ply(
      path, one.means, one.opacities, one.scales, one.quats, one.colors, min_opacity=min_opacity
    )
  ]


def write_flythrough(
  path,
  entry: dict,
  method: str,
  video_frames: int,
  render_config: splatting.RenderConfig | None = None,
) -> list[pathlib.Path]:
  """An MP4 of one kept scene's `method` Gaussians: `video_frames` frames through its input
  cameras and back."""
  if not evaluation.writes_results():
    return []
  batch = entry["batch"]
  keyframes = np.concatenate([batch["context_c2w"][0], batch["context_c2w"][0][::-1]])
  poses = export.fly_through_poses(keyframes, video_frames)
  height, width = batch["target_images"].shape[-3:-1]
  intrinsics = np.broadcast_to(batch["context_intrinsics"][0, :1], (len(poses), 4))
  single = jax.tree.map(lambda x: x[None], _first_set(entry, method))
  rgb = evaluation.render_targets(
    single, poses[None], intrinsics[None], height=height, width=width, render_config=render_config
  ).rgb
  frames = [figures.upscale(export.to_uint8(frame), 256) for frame in rgb[0]]
  return [export.write_mp4(path, frames, fps=12)]


def _media_path(out_dir: pathlib.Path, what: str, suffix: str, key: str | None) -> pathlib.Path:
  """`<what><suffix>` of the one exported scene (key None), else `<what>/<scene><suffix>`."""
  return out_dir / f"{what}{suffix}" if key is None else data_path(out_dir / what, key, suffix)


def write_scene_media(
  out_dir, kept: Sequence[dict], method: str, settings: EvalSettings, failures: list[str]
) -> None:
  """The PLY and (`settings.video_frames` > 0) fly-through of the first `settings.media_scenes`
  kept scenes' `method` Gaussians (0: of every kept scene): the one scene's as gaussians.ply /
  flythrough.mp4, several each under its key in gaussians/ and flythrough/. Each file is a
  `media_step`."""
  out_dir = pathlib.Path(out_dir)
  count = settings.media_scenes
  for entry in kept if count == 0 else kept[:count]:
    key = None if count == 1 else entry["key"]
    about = "" if key is None else f" of scene {key!r}"
    with media_step(f"gaussians.ply{about}", failures):
      path = _media_path(out_dir, "gaussians", ".ply", key)
      write_scene_ply(path, entry, method, settings.ply_min_opacity)
    if settings.video_frames > 0:
      with media_step(f"flythrough.mp4{about}", failures):
        path = _media_path(out_dir, "flythrough", ".mp4", key)
        write_flythrough(path, entry, method, settings.video_frames)


def tensorboard_writer(out_dir):
  """A TensorBoard writer on the writing process, None elsewhere."""
  if not evaluation.writes_results():
    return None
  from tensorboardX import SummaryWriter

  return SummaryWriter(str(pathlib.Path(out_dir) / "tensorboard"))
