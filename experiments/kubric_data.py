"""The Kubric experiments' data: the synthetic subsets (generated when missing), the training and
held-out scene sources, the example configuration and the view selection, each a function of a
`kubric_task.KubricExperiment`."""

from __future__ import annotations

import dataclasses
import functools
import pathlib

from experiments import data
from tokengs_jax.data import DATASET_PRESETS, ExampleConfig
from tokengs_jax.data.kubric import (
  KubricSceneSource,
  kubric_view_selector,
  list_kubric_scenes,
  load_kubric_evaluation_index,
)
from tokengs_jax.data.synthetic import generate_kubric_like
from tokengs_jax.data.synthetic.kubric_ood import generate_kubric_ood

# The held-out dynamic family's subset is also its test set's name in the results.
TRAIN_SUBSET, TEST_SUBSET, OOD_SUBSET = "v0", "test", "ood_kubric"


def kubric_example_config(experiment, *, training: bool) -> ExampleConfig:
  """The official Kubric example preset (pointmap scale) at the experiment's image size, camera
  normalisation and pointmap trim; random flips only in training, where the targets' object
  pixels, masks (PNG alpha) and flows come too when a loss term scores them."""
  return dataclasses.replace(
    DATASET_PRESETS["kubric"],
    image_shape=tuple(experiment.image_size),
    normalization=experiment.normalization,
    pointmap_trim_lo=experiment.pointmap_trim_lo,
    pointmap_trim_hi=experiment.pointmap_trim_hi,
    random_flip=training,
    deterministic=not training,
    target_objects=training and experiment.dyn_aux_on_objects,
    target_flows=training and experiment.lambda_flow > 0,
    target_masks=training and experiment.train.lambda_mask > 0,
  )


def kubric_views(experiment, num_targets: int):
  """The official dynamic view selection (inputs from `context_cameras` cameras in turn if set)."""
  return kubric_view_selector(
    experiment.num_context_views,
    num_targets,
    experiment.min_gap,
    experiment.max_gap,
    context_cameras=experiment.context_cameras,
  )


def data_root(experiment) -> pathlib.Path:
  """The data root; synthetic: writes each subset (the training family's train / test, and
  `synthetic.num_ood` scenes of the frozen held-out family,
  `tokengs_jax.data.synthetic.kubric_ood`) that is missing or was written with other arguments
  (`data.ensure_generated_set`: staged, stamped `<subset>/generator.json`)."""
  if experiment.data_dir:
    return pathlib.Path(experiment.data_dir)
  root = pathlib.Path(experiment.synthetic_dir)
  s = experiment.synthetic
  generators = {
    TRAIN_SUBSET: (generate_kubric_like, s.num_train, {"seed": experiment.seed}),
    TEST_SUBSET: (generate_kubric_like, s.num_test, {"seed": experiment.seed + 1000}),
    OOD_SUBSET: (generate_kubric_ood, s.num_ood, {}),  # its own frozen seed
  }
  height, width = experiment.image_size
  for subset, (generate, count, seed_argument) in generators.items():
    if count <= 0:
      continue
    arguments = {
      "num_scenes": count,
      "height": height,
      "width": width,
      "frames": s.frames,
      "num_cameras": experiment.num_cameras,
      **seed_argument,
    }
    data.ensure_generated_set(
      root,
      (subset,),
      {"generator": generate.__name__, **arguments},
      functools.partial(generate, subset=subset, workers=s.workers, **arguments),
      stamp=f"{subset}/generator.json",
      what=f"{count} synthetic Kubric scenes to {root / subset}",
      replace_other_settings=True,
    )
  return root


def scene_sources(experiment) -> tuple[KubricSceneSource, KubricSceneSource]:
  """(training scenes, held-out scenes): the synthetic subsets, or with `--data-dir` the last
  `eval.num_scenes` (default 16) scenes of the listing held out; with `--data-dir` and
  `--eval-index`, every scene of the listing is searched for the index's keys and those the
  index names are left out of training."""
  root = data_root(experiment)
  if not experiment.data_dir:
    return (
      KubricSceneSource(root, [TRAIN_SUBSET], num_cameras=experiment.num_cameras),
      KubricSceneSource(root, [TEST_SUBSET], num_cameras=experiment.num_cameras),
    )
  scenes = list_kubric_scenes(root)
  if experiment.eval_index:
    named = set(load_kubric_evaluation_index(experiment.eval_index))
    return (
      KubricSceneSource(
        scenes=[s for s in scenes if s.name not in named], num_cameras=experiment.num_cameras
      ),
      KubricSceneSource(scenes=scenes, num_cameras=experiment.num_cameras),
    )
  held_out = experiment.eval.num_scenes or 16
  return (
    KubricSceneSource(scenes=scenes[:-held_out], num_cameras=experiment.num_cameras),
    KubricSceneSource(scenes=scenes[-held_out:], num_cameras=experiment.num_cameras),
  )


def ood_source(experiment) -> KubricSceneSource | None:
  """The first `synthetic.num_ood` scenes of the frozen held-out family; None for real data or
  `synthetic.num_ood = 0`."""
  if experiment.data_dir or experiment.synthetic.num_ood <= 0:
    return None
  scenes = list_kubric_scenes(data_root(experiment), [OOD_SUBSET])
  return KubricSceneSource(
    scenes=scenes[: experiment.synthetic.num_ood], num_cameras=experiment.num_cameras
  )
