"""Training: optimiser and schedules, sharded step, checkpoints, distribution, the loop."""

from tokengs_jax.train.checkpoint import (
  Checkpointer,
  ChecksumError,
  UnusableCheckpointError,
  array_checksums,
  data_state_file,
  data_state_handler,
  iterator_state,
  set_iterator_state,
  verify_checksums,
)
from tokengs_jax.train.distributed import barrier, initialize, make_mesh, replicate, shard_batch
from tokengs_jax.train.loop import LoopConfig, NonFiniteError, train
from tokengs_jax.train.objective import decode_at_times, time_conditioned_loss, tokengs_loss_fn
from tokengs_jax.train.supervision import ObjectiveConfig, mean_over_view_chunks, supervision_loss
from tokengs_jax.train.optim import (
  OptimConfig,
  beta1_schedule,
  current_learning_rate,
  learning_rate_schedule,
  make_optimizer,
  weight_decay_mask,
)
from tokengs_jax.train.state import TrainState, create_train_state
from tokengs_jax.train.step import Precision, cast_floating, make_train_step, train_step_fn
from tokengs_jax.train.tokens import dynamic_tokens_from_static, expand_tokens, transplant_params

__all__ = [
  "Checkpointer",
  "ChecksumError",
  "LoopConfig",
  "UnusableCheckpointError",
  "array_checksums",
  "barrier",
  "data_state_file",
  "data_state_handler",
  "decode_at_times",
  "time_conditioned_loss",
  "NonFiniteError",
  "ObjectiveConfig",
  "OptimConfig",
  "Precision",
  "TrainState",
  "beta1_schedule",
  "cast_floating",
  "create_train_state",
  "current_learning_rate",
  "dynamic_tokens_from_static",
  "expand_tokens",
  "initialize",
  "iterator_state",
  "learning_rate_schedule",
  "make_mesh",
  "make_optimizer",
  "make_train_step",
  "mean_over_view_chunks",
  "replicate",
  "set_iterator_state",
  "shard_batch",
  "supervision_loss",
  "tokengs_loss_fn",
  "train",
  "train_step_fn",
  "transplant_params",
  "verify_checksums",
  "weight_decay_mask",
]
