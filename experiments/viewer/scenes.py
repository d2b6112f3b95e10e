"""What the viewer shows, host-side: held-out scenes of a results folder (or a PLY) as Gaussians,
cameras and renders by our own renderer, and the selection (opacity threshold, static / dynamic).

A results folder (`experiments.tasks.run_eval`) holds `metrics.json` with the run's `experiment`
settings (the model's architecture included) and `params.msgpack`; from them the held-out scenes
are rebuilt exactly as the evaluation saw them (same views) and reconstructed on demand. The
folder may come from anyone: opening it reads, and writes no data where its settings point.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from experiments import data, weights
from experiments.config import Experiment, from_fields
from experiments.kubric_task import KubricExperiment, KubricTask
from experiments.tasks import Task
from tokengs_jax import evaluation, export, metrics
from tokengs_jax.gaussians import Gaussians
from tokengs_jax.math import quat_to_rotmat
from tokengs_jax.objective import ObjectiveConfig


@dataclasses.dataclass(frozen=True)
class Cameras:
  """Views of one scene (numpy).  images: [V, H, W, 3] in [0, 1], c2w: [V, 4, 4] OpenCV,
  intrinsics: [V, 4] (fx, fy, cx, cy) in pixels."""

  images: np.ndarray
  c2w: np.ndarray
  intrinsics: np.ndarray


@dataclasses.dataclass(frozen=True)
class ViewScene:
  """One reconstruction to look at.

  Attributes:
    key: scene name.
    gaussians: unbatched numpy Gaussians [N].
    num_static: the first `num_static` Gaussians come from static tokens, the rest from dynamic
      ones (Kubric models); N for static models.
    inputs / targets: the evaluation's input and target views; None for a bare PLY.
    time: the time the dynamic Gaussians were decoded at (None: static model).
  """

  key: str
  gaussians: Gaussians
  num_static: int
  inputs: Cameras | None = None
  targets: Cameras | None = None
  time: float | None = None

  @property
  def num_gaussians(self) -> int:
    return len(self.gaussians.opacities)


def covariances(scales: np.ndarray, quats: np.ndarray) -> np.ndarray:
  """World covariances R diag(s^2) R^T, which viser's splat renderer takes.

  scales: [N, 3] linear std devs, quats: [N, 4] wxyz (any norm) -> [N, 3, 3].
  """
  rot = np.asarray(quat_to_rotmat(jnp.asarray(quats, jnp.float32)))  # normalises
  scaled = rot * np.asarray(scales)[:, None, :]
  return scaled @ np.swapaxes(scaled, -1, -2)


def finite(gaussians: Gaussians) -> np.ndarray:
  """Gaussians whose every parameter is finite.  -> bool [N]."""
  fields = [np.asarray(x).reshape(len(gaussians.opacities), -1) for x in jax.tree.leaves(gaussians)]
  return np.all(np.isfinite(np.concatenate(fields, axis=-1)), axis=-1)


def selection(
  scene: ViewScene, threshold: float, show_static: bool = True, show_dynamic: bool = True
) -> np.ndarray:
  """Which Gaussians are shown: finite ones with opacity >= threshold, in the parts switched on.
  -> bool [N]."""
  part = np.arange(scene.num_gaussians) < scene.num_static
  wanted = np.where(part, show_static, show_dynamic)
  return wanted & finite(scene.gaussians) & (np.asarray(scene.gaussians.opacities) >= threshold)


def opacity_census(
  opacities: np.ndarray, thresholds=(0.01, 0.05, 0.1, 0.5)
) -> list[tuple[float, int]]:
  """(threshold, how many Gaussians reach it): how many of the predicted Gaussians matter."""
  opacities = np.asarray(opacities)
  return [(t, int(np.sum(opacities >= t))) for t in thresholds]


_HARMLESS = Gaussians(
  means=np.zeros(3, np.float32),
  opacities=np.float32(0.0),
  scales=np.full(3, 1e-3, np.float32),
  quats=np.float32([1.0, 0.0, 0.0, 0.0]),
  colors=np.zeros(3, np.float32),
)


def masked(gaussians: Gaussians, visible: np.ndarray) -> Gaussians:
  """The same Gaussians with the hidden ones made fully transparent: a render of these equals a
  render of the subset (a zero-opacity splat adds nothing), and the shapes stay fixed, so one
  compiled renderer serves every threshold. A hidden Gaussian with a non-finite parameter is
  replaced whole by a transparent finite one (NaN would reach the pixels through the sort)."""
  transparent = dataclasses.replace(
    gaussians, opacities=np.where(visible, gaussians.opacities, 0.0).astype(np.float32)
  )
  bad = ~finite(gaussians)
  return jax.tree.map(
    lambda x, fill: np.where(bad.reshape((-1,) + (1,) * (x.ndim - 1)), fill, x).astype(np.float32),
    transparent,
    _HARMLESS,
  )


def scaled_intrinsics(intrinsics: np.ndarray, factor: float) -> np.ndarray:
  """Intrinsics of the same camera with `factor` times as many pixels per side (pixel-centre
  convention: continuous image coordinates scale, so fx, fy, cx, cy all scale)."""
  return np.asarray(intrinsics, np.float32) * np.float32(factor)


def render(
  gaussians: Gaussians,
  c2w: np.ndarray,
  intrinsics: np.ndarray,
  height: int,
  width: int,
  objective: ObjectiveConfig = ObjectiveConfig(),
  context_images: np.ndarray | None = None,
) -> np.ndarray:
  """One view as the evaluation renders it (`evaluation.render_targets`: exact, with the run's
  objective: its background, near and far; an "input_mean" background is the mean colour of
  `context_images` [Vi, H, W, 3]).  c2w: [4, 4], intrinsics: [4] -> rgb [H, W, 3] numpy."""
  batched = jax.tree.map(lambda x: np.asarray(x)[None], gaussians)
  return evaluation.render_targets(
    batched,
    np.asarray(c2w)[None, None],
    np.asarray(intrinsics)[None, None],
    height=height,
    width=width,
    objective=objective,
    context_images=None if context_images is None else np.asarray(context_images)[None],
  ).rgb[0, 0]


def psnr(image: np.ndarray, target: np.ndarray) -> float:
  return float(metrics.psnr(image, target))


# ----------------------------------------------------------------------------------------------
# Sources: a results folder, or a bare PLY


def experiment_from_fields(fields: dict):
  """(experiment, task) from `metrics.json["experiment"]`: a Kubric run when the fields hold the
  Kubric-only ones (`KubricExperiment` extends `Experiment`)."""
  if set(fields) <= {f.name for f in dataclasses.fields(Experiment)}:
    return from_fields(Experiment, fields), Task()
  return from_fields(KubricExperiment, fields), KubricTask()


_MISSING_DATA = (
  "opening a results folder writes no data; pass --generate-data to write it, or --synthetic-dir "
  "/ --data-dir to point at the held-out scenes"
)


class ResultsSource:
  """The held-out scenes of a results folder, reconstructed by its trained weights on demand.

  Args:
    folder: results folder with `metrics.json` and `params.msgpack`.
    checkpoint: other weights (`params.msgpack`) to look at with the folder's settings; default
      the folder's trained `params.msgpack`, else the weights the run evaluated.
    data_dir / synthetic_dir: where the held-out scenes are, if not where the run had them.
    generate_data: write the synthetic set the settings name if it is missing; otherwise a
      missing set raises `data.GenerationRefused` (one line naming `--generate-data`).
    num_scenes: held-out scenes offered (0: the run's `eval.num_scenes`).
  """

  def __init__(
    self,
    folder,
    checkpoint=None,
    data_dir: str | None = None,
    synthetic_dir: str | None = None,
    generate_data: bool = False,
    num_scenes: int = 0,
  ):
    folder = pathlib.Path(folder)
    saved = json.loads((folder / "metrics.json").read_text())
    experiment, task = experiment_from_fields(saved["experiment"])
    changes = {}
    trained = checkpoint or (
      folder / "params.msgpack" if (folder / "params.msgpack").exists() else None
    )
    if trained:
      changes.update(checkpoint=str(trained), official_checkpoint=None)
    if data_dir is not None:
      changes["data_dir"] = data_dir
    if synthetic_dir is not None:
      changes["synthetic_dir"] = synthetic_dir
    experiment = dataclasses.replace(experiment, **changes)
    if num_scenes:
      experiment = dataclasses.replace(
        experiment, eval=dataclasses.replace(experiment.eval, num_scenes=num_scenes)
      )
    if generate_data:
      task.prepare(experiment)  # writes a missing synthetic set (before JAX starts threads)
    with data.refusing_generation(_MISSING_DATA):
      self.evaluation_scenes = task.evaluation_scenes(experiment)
    self.folder, self.experiment, self.config = folder, experiment, experiment.model
    self.objective = task.objective(experiment)  # the render settings the run was scored with
    self.params = weights.initial_params(experiment, finetune=False)
    self.title = saved.get("title", str(folder))
    self._scenes: dict[tuple[int, float | None], ViewScene] = {}

  @property
  def keys(self) -> list[str]:
    return [key for key, _ in self.evaluation_scenes]

  @property
  def time_conditioned(self) -> bool:
    return bool(self.config.time_embedding)

  def default_time(self, index: int) -> float | None:
    batch = self.evaluation_scenes[index][1]
    return float(batch["target_times"][0, 0]) if self.time_conditioned else None

  def scene(self, index: int, time: float | None = None) -> ViewScene:
    """Scene `index` reconstructed; dynamic models decode at `time` (default the first target's)."""
    if (index, time) not in self._scenes:
      self._scenes[index, time] = self._reconstruct(index, time)
    return self._scenes[index, time]

  def _reconstruct(self, index: int, time: float | None) -> ViewScene:
    key, batch = self.evaluation_scenes[index]
    if self.time_conditioned and time is None:
      time = self.default_time(index)
    target_times = jnp.asarray([time], jnp.float32) if self.time_conditioned else None
    # the browser draws one colour per Gaussian: colours that depend on the viewer are those
    # seen from the first input camera
    first_camera = batch["context_c2w"][:, :1]
    gaussians = evaluation.gaussians_for_batch(
      self.params, batch, self.config, target_times, first_camera
    )
    gaussians = jax.tree.map(
      lambda x: np.asarray(x, np.float32), jax.device_get(gaussians.first_set())
    )
    views = lambda prefix: Cameras(
      np.asarray(batch[f"{prefix}_images"][0], np.float32),
      np.asarray(batch[f"{prefix}_c2w"][0], np.float32),
      np.asarray(batch[f"{prefix}_intrinsics"][0], np.float32),
    )
    return ViewScene(
      key, gaussians, self.config.num_static_gaussians, views("context"), views("target"), time
    )


class PlySource:
  """A bare PLY (e.g. `gaussians.ply` of a results folder): one scene, no cameras, no renders."""

  time_conditioned = False
  objective = ObjectiveConfig()  # no run: the official grey background

  def __init__(self, path):
    path = pathlib.Path(path)
    fields = export.read_ply(path)
    self._scene = ViewScene(
      path.stem,
      Gaussians(**{k: v.astype(np.float32) for k, v in fields.items()}),
      num_static=len(fields["opacities"]),
    )
    self.title = str(path)
    self.folder = path.parent

  @property
  def keys(self) -> list[str]:
    return [self._scene.key]

  def default_time(self, index: int) -> None:
    return None

  def scene(self, index: int, time: float | None = None) -> ViewScene:
    return self._scene


def open_source(path, **options):
  """A results folder or a `.ply` file -> its source of scenes."""
  path = pathlib.Path(path)
  if path.suffix == ".ply":
    if any(options.values()):
      raise ValueError(
        f"{sorted(k for k, v in options.items() if v)} apply to results folders, not to a PLY"
      )
    return PlySource(path)
  if not (path / "metrics.json").exists():
    raise FileNotFoundError(f"{path}: neither a .ply nor a results folder with metrics.json")
  return ResultsSource(path, **options)
