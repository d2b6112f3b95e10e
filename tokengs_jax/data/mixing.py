"""Training on several datasets at once, each repeated: the official `data_mode`.

The official `Options.data_mode` (`tokengs/options.py`) is a tuple of `(name, repeat)` pairs, e.g.
`(("dl3dv_scaled_0.15", 6),)`. `tokengs/data/__init__.py` (`get_datasets`) builds one `Provider`
per pair and concatenates them in a torch `ConcatDataset`. The training `DataLoader` shuffles that
concatenation (`shuffle=True`, seeded), so one batch may hold examples of every dataset.
`Provider.__init__` (`tokengs/data/provider.py`) reads a `_scaled_X` suffix as the dataset's
`scene_scale`, the translation scale of its camera scaling. It takes the view gaps
(`min_gap` / `max_gap`) from the dataset's registry entry and repeats the dataset's sample list
`repeat` times (`sample_list *= num_repeat`). Everything else (views, image size, camera frame)
is one setting for all datasets.

Here `MixedSource(parts)` is one random-access source over several. It holds part 0's scenes
`repeat` times in order, then part 1's, and so on. `InputPipeline` shards, shuffles (anew every
epoch) and batches it as any other source, so a batch mixes datasets, as official. Each part can
carry its own `ExampleConfig`: `InputPipeline` asks the source for it (`example_config(index,
default)`), so each dataset keeps its own translation scale and sampler. Those configs must agree
on what makes a batch stack (image shape, view counts, extra target maps); `MixedSource` refuses
parts that do not.

`parse_data_mode` reads one training dataset as the experiments' `--data-mode` names it,
`NAME:REPEAT:FOLDER`. NAME is an official-style dataset name: `re10k` or `dl3dv`, optionally with
`_scaled_X` (translation scale X; default `TRANSLATION_SCALES`). REPEAT is the official repeat
count (an integer >= 1). FOLDER is a data folder as `--data-dir` takes it (pixelSplat chunks with
`train/`, or DL3DV scenes as they ship). `training_mix` builds the mixed training source of such
entries.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import os
import pathlib
from collections.abc import Callable, Sequence

import numpy as np

from tokengs_jax.data import dl3dv
from tokengs_jax.data.chunked import ChunkedSceneSource
from tokengs_jax.data.pipeline import (
  DATASET_PRESETS,
  TRANSLATION_SCALES,
  ExampleConfig,
  NoUsableExamplesError,
)
from tokengs_jax.data.rejections import Rejections

__all__ = [
  "DATA_MODE_DATASETS",
  "DataModeEntry",
  "MixPart",
  "MixedSource",
  "parse_data_mode",
  "parse_dataset_name",
  "training_mix",
]

# The static datasets a mix may name (each has a `DATASET_PRESETS` sampler and translation scale).
DATA_MODE_DATASETS = ("re10k", "dl3dv")
_SCALED = "_scaled_"
_GRAMMAR = "NAME:REPEAT:FOLDER, e.g. dl3dv_scaled_0.15:6:/data/dl3dv"


@dataclasses.dataclass(frozen=True)
class MixPart:
  """One dataset of a mix.

  Attributes:
    source: `len()` + `[i]` -> scene record (a `ChunkedSceneSource`, `DL3DVSceneSource`, ...).
    repeat: how many times each of its scenes appears in one epoch of the mix (official
      `num_repeat`), an integer >= 1.
    config: how its examples are built; None: the pipeline's own config.
    name: how summaries and errors name it.
  """

  source: Sequence[dict]
  repeat: int = 1
  config: ExampleConfig | None = None
  name: str = ""

  def __post_init__(self):
    if isinstance(self.repeat, bool) or not isinstance(self.repeat, int) or self.repeat < 1:
      raise ValueError(f"mix part {self.name!r}: repeat must be an integer >= 1, got {self.repeat}")


def _batch_shape(config: ExampleConfig) -> tuple:
  """What two configs must share for their examples to stack into one batch."""
  sampler = config.sampler
  maps = (config.target_depths, config.target_objects, config.target_masks, config.target_flows)
  return tuple(config.image_shape), sampler.num_context_views, sampler.num_target_views, maps


class MixedSource:
  """Several scene sources as one, each part's scenes `repeat` times (the official
  `ConcatDataset` of repeated datasets). Index `i` of the mix is, within its part's block,
  scene `(i - block start) % len(part.source)`: the official `sample_list * num_repeat`.

  Raises ValueError for no parts or parts whose configs would not stack into one batch, and
  `NoUsableExamplesError` for a part with no scenes (a dataset asked for must not vanish).
  """

  def __init__(self, parts: Sequence[MixPart]):
    self.parts = tuple(parts)
    if not self.parts:
      raise ValueError("a mix needs at least one part")
    for number, part in enumerate(self.parts):
      if len(part.source) == 0:
        log = getattr(part.source, "rejections", None)
        raise NoUsableExamplesError(
          f"mix part {number} ({part.name or 'unnamed'}) has no scenes"
          + (f" ({log.summary()})" if log else "")
        )
    shapes = {_batch_shape(p.config): p.name for p in self.parts if p.config is not None}
    if len(shapes) > 1:
      raise ValueError(
        "the mix's parts must build examples of one shape (image shape, context and target "
        f"views, target maps) to share batches: {', '.join(f'{n}: {s}' for s, n in shapes.items())}"
      )
    self._ends = np.cumsum([len(p.source) * p.repeat for p in self.parts])

  def __len__(self) -> int:
    return int(self._ends[-1])

  def locate(self, index: int) -> tuple[int, int]:
    """(part number, scene index in that part's source) of the mix's scene `index`."""
    if not 0 <= index < len(self):
      raise IndexError(f"scene {index} of a mix of {len(self)}")
    part = int(np.searchsorted(self._ends, index, side="right"))
    start = int(self._ends[part - 1]) if part else 0
    return part, (index - start) % len(self.parts[part].source)

  def __getitem__(self, index: int) -> dict:
    part, scene = self.locate(int(index))
    return self.parts[part].source[scene]

  def example_config(self, index: int, default: ExampleConfig) -> ExampleConfig:
    """The config of scene `index`'s part, or `default` where the part has none."""
    config = self.parts[self.locate(int(index))[0]].config
    return default if config is None else config

  @property
  def rejections(self) -> Rejections:
    """What the parts' sources rejected so far, each reason prefixed by its part's name."""
    merged = Rejections("mix")
    for number, part in enumerate(self.parts):
      log = getattr(part.source, "rejections", None)
      if log:
        name = part.name or f"part{number}"
        merged.counts.update({f"{name}/{k}": v for k, v in log.counts.items()})
        merged.messages.extend(log.messages)
    return merged

  def counts(self) -> collections.Counter:
    """Examples per part name in one epoch of the mix (its scenes x repeat)."""
    counts = collections.Counter()
    for part in self.parts:
      counts[part.name] += len(part.source) * part.repeat
    return counts


def parse_dataset_name(name: str, *, where: str = "") -> tuple[str, float]:
  """(dataset, translation scale) of an official-style name: `re10k`, `dl3dv_scaled_0.15`, ...

  As the official `Provider`, `_scaled_X` sets the dataset's scale to X; without it, the dataset's
  `TRANSLATION_SCALES` entry. ValueError for a dataset other than `DATA_MODE_DATASETS` (Kubric,
  dynamic, is refused with its own reason) or a scale that is not a finite number > 0.
  """
  dataset, scaled, scale_text = name.partition(_SCALED)
  if dataset == "kubric":
    raise ValueError(
      f"{where}{name!r}: Kubric is dynamic (timed frames, its own view selection and pointmap "
      "scale) and cannot be mixed into a static run; train it with python -m experiments.kubric"
    )
  if dataset not in DATA_MODE_DATASETS:
    raise ValueError(
      f"{where}{name!r}: unknown dataset {dataset!r}; known: {', '.join(DATA_MODE_DATASETS)} "
      "(each optionally _scaled_X)"
    )
  if not scaled:
    return dataset, TRANSLATION_SCALES[dataset]
  try:
    scale = float(scale_text)
  except ValueError:
    scale = math.nan
  if not (math.isfinite(scale) and scale > 0):
    raise ValueError(f"{where}{name!r}: the scale after {_SCALED} must be a number > 0")
  return dataset, scale


@dataclasses.dataclass(frozen=True)
class DataModeEntry:
  """One training dataset of a mix: official name + repeat count, and where its data is.

  Attributes:
    dataset: `re10k` or `dl3dv`: its `DATASET_PRESETS` sampler.
    translation_scale: its camera translation scale (official `_scaled_X`).
    repeat: times each scene appears in one epoch of the mix (>= 1).
    folder: the data folder: pixelSplat chunks (`train/` is read) or DL3DV scenes as they ship.
    format: "chunks" or "zips" (`dl3dv.data_folder_format`).
  """

  dataset: str
  translation_scale: float
  repeat: int
  folder: pathlib.Path
  format: str

  @property
  def name(self) -> str:
    """The official-style name, e.g. `dl3dv_scaled_0.15`."""
    return f"{self.dataset}{_SCALED}{self.translation_scale:g}"

  def example_config(self, base: ExampleConfig) -> ExampleConfig:
    """`base` (the run's image shape, views, camera frame, flips and target maps) with this
    dataset's sampler gaps and translation scale: what official `Provider` takes per dataset."""
    sampler = dataclasses.replace(
      DATASET_PRESETS[self.dataset].sampler,
      num_context_views=base.sampler.num_context_views,
      num_target_views=base.sampler.num_target_views,
    )
    return dataclasses.replace(base, sampler=sampler, translation_scale=self.translation_scale)


def parse_data_mode(text: str, *, where: str = "--data-mode ") -> DataModeEntry:
  """One `NAME:REPEAT:FOLDER` entry (module docstring), its folder checked now (it exists and
  holds data of a layout that dataset can be read from). ValueError naming the entry otherwise.
  The folder is everything after the second colon, so it may itself hold colons."""
  parts = text.split(":", 2)
  if len(parts) != 3 or not all(parts):
    raise ValueError(f"{where}{text!r}: expected {_GRAMMAR}")
  name, repeat_text, folder = parts
  dataset, scale = parse_dataset_name(name, where=where)
  try:
    repeat = int(repeat_text)
  except ValueError:
    repeat = 0
  if repeat < 1:
    raise ValueError(f"{where}{text!r}: REPEAT must be an integer >= 1, got {repeat_text!r}")
  try:
    found = dl3dv.data_folder_format(folder)
  except dl3dv.DL3DVError as error:
    raise ValueError(f"{where}{text!r}: {error}") from None
  if found == "zips" and dataset != "dl3dv":
    raise ValueError(f"{where}{text!r}: {folder} holds DL3DV scenes; name it dl3dv(_scaled_X)")
  if found == "chunks" and not (pathlib.Path(folder) / "train").is_dir():
    raise ValueError(f"{where}{text!r}: {folder} has no train/ chunk folder to train on")
  return DataModeEntry(dataset, scale, repeat, pathlib.Path(folder), found)


def training_mix(
  entries: Sequence[str | DataModeEntry],
  base: ExampleConfig,
  held_out_index: str | os.PathLike | None = None,
  wrap: Callable[[Sequence[dict]], Sequence[dict]] | None = None,
) -> MixedSource:
  """The mixed training source of `entries` (`parse_data_mode` strings or entries), each part's
  examples built by `entry.example_config(base)`; bad scenes are skipped and counted.

  held_out_index: an evaluation index whose scenes DL3DV folders leave out
    (`dl3dv.dl3dv_training_source`); chunk folders train on `train/` only.
  wrap: applied to each part's source (e.g. adding true depths to the records).
  """
  parts = []
  for entry in entries:
    entry = parse_data_mode(entry) if isinstance(entry, str) else entry
    if entry.format == "zips":
      source = dl3dv.dl3dv_training_source(
        entry.folder, held_out_index=held_out_index, skip_bad=True
      )
    else:
      source = ChunkedSceneSource(entry.folder / "train", skip_bad=True)
    source = source if wrap is None else wrap(source)
    parts.append(MixPart(source, entry.repeat, entry.example_config(base), entry.name))
  return MixedSource(parts)
