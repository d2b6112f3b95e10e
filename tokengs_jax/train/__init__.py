"""Training: optimiser and schedules, sharded step, checkpoints, distribution, the loop.

The objective the loop minimises is `tokengs_jax.objective` (`tokengs_loss_fn`). Plumbing
(checkpoint checksums and data-state files, the optimiser's parts) is imported from its submodule,
e.g. `tokengs_jax.train.checkpoint.verify_checksums`.
"""

from tokengs_jax.train.checkpoint import Checkpointer
from tokengs_jax.train.checkpoint_files import CheckpointWriteError
from tokengs_jax.train.distributed import barrier, initialize, make_mesh, replicate, shard_batch
from tokengs_jax.train.loop import LoopConfig, NonFiniteError, TrainingStopped, train
from tokengs_jax.train.optim import OptimConfig, learning_rate_schedule, make_optimizer
from tokengs_jax.train.state import TrainState, create_train_state, ema_update, trained_params
from tokengs_jax.train.step import Precision, make_train_step, train_step_fn
from tokengs_jax.train.tokens import (
  dynamic_tokens_from_static,
  expand_tokens,
  split_gaussians,
  transplant_params,
)

__all__ = [
  "CheckpointWriteError",
  "Checkpointer",
  "LoopConfig",
  "NonFiniteError",
  "OptimConfig",
  "Precision",
  "TrainState",
  "TrainingStopped",
  "barrier",
  "create_train_state",
  "dynamic_tokens_from_static",
  "ema_update",
  "expand_tokens",
  "initialize",
  "learning_rate_schedule",
  "make_mesh",
  "make_optimizer",
  "make_train_step",
  "replicate",
  "shard_batch",
  "train",
  "train_step_fn",
  "trained_params",
  "split_gaussians",
  "transplant_params",
]
