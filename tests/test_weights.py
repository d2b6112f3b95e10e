"""experiments.weights: the starting weights of a run."""

import dataclasses
import pathlib

import numpy as np
import pytest
from scenes import official_fixture

from experiments import weights
from experiments.config import Experiment

# The tiny official fixture's weights as torch saves a state dict (tests/test_model_official.py).
OFFICIAL_TINY_PTH = pathlib.Path(__file__).parent / "data" / "official_tiny.pth"


def test_official_weights_seed_a_grown_model_for_finetuning_but_must_match_for_evaluation():
  config, params, _ = official_fixture()
  grown = config.replace(num_gs_tokens=6, num_dynamic_gs_tokens=2, time_embedding=True)
  experiment = dataclasses.replace(
    Experiment(), model=grown, official_checkpoint=str(OFFICIAL_TINY_PTH)
  )
  started = weights.initial_params(experiment, finetune=True)
  np.testing.assert_array_equal(started["gs_tokens"][:4], params["gs_tokens"])
  assert started["gs_tokens"].shape == (6, 32) and started["gs_tokens_dynamic"].shape == (2, 32)
  with pytest.raises(ValueError, match="gs_tokens_dynamic"):
    weights.initial_params(experiment, finetune=False)
