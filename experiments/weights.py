"""Network weights on disk: msgpack params, and the starting weights of a command."""

from __future__ import annotations

import pathlib

import jax

from experiments.config import Experiment
from tokengs_jax import model


def save_params(path, params) -> pathlib.Path:
  """Writes a params pytree as msgpack (flax.serialization)."""
  from flax import serialization

  path = pathlib.Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  path.write_bytes(serialization.msgpack_serialize(jax.device_get(params)))
  return path


def load_params(path) -> dict:
  from flax import serialization

  return serialization.msgpack_restore(pathlib.Path(path).read_bytes())


def initial_params(experiment: Experiment, *, finetune: bool):
  """Fresh weights, or (finetune / eval) the given checkpoint grown into the model if needed."""
  config = experiment.model
  fresh = model.init_params(jax.random.key(experiment.seed), config)
  if experiment.official_checkpoint:
    loaded = model.load_official_checkpoint(experiment.official_checkpoint, config)
  elif experiment.checkpoint:
    loaded = load_params(experiment.checkpoint)
  else:
    if finetune:
      raise ValueError("finetune needs --checkpoint or --official-checkpoint")
    return fresh
  from tokengs_jax.train import transplant_params

  params, report = transplant_params(jax.random.key(experiment.seed + 1), loaded, fresh)
  for line in report:
    print(f"[params] {line}", flush=True)
  return params
