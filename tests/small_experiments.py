"""Small experiments shared by the tests of `experiments/` (test_tasks, test_experiments_data,
test_kubric_task): the `smoke` preset on 2 + 1 scenes, the Kubric default on 1 + 1 tiny ones."""

import dataclasses

from experiments import re10k


def small_smoke(tmp_path, eval_changes=None, **train_changes):
  """The smoke preset on 2 training scenes and 1 test scene under `tmp_path`, with these
  training (and evaluation) settings changed."""
  smoke = re10k.PRESETS["smoke"]
  return dataclasses.replace(
    smoke,
    synthetic_dir=str(tmp_path / "data"),
    synthetic=dataclasses.replace(smoke.synthetic, num_train=2, num_test=1, workers=1),
    train=dataclasses.replace(smoke.train, **train_changes),
    eval=dataclasses.replace(smoke.eval, **(eval_changes or {})),
  )


def tiny_kubric(tmp_path, **changes):
  """The Kubric default on one training and one test scene of 2 cameras x 4 frames at 16x16 (no
  held-out family) under `tmp_path / "data"`, with these settings changed."""
  from experiments import kubric
  from experiments.config import SyntheticSettings

  tiny = kubric.PRESETS["synthetic-tiny"]
  return dataclasses.replace(
    tiny,
    synthetic_dir=str(tmp_path / "data"),
    output_dir=str(tmp_path / "out"),
    model=tiny.model.replace(image_size=(16, 16)),
    num_cameras=2,
    synthetic=SyntheticSettings(num_train=1, num_test=1, frames=4, num_ood=0, workers=1),
    **changes,
  )
