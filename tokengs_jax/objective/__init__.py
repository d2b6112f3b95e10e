"""The TokenGS objective, one home for training, test-time tuning and evaluation.

- `settings`: `ObjectiveConfig` (background, near / far, view chunks, decode times) and
  `background_colours` / `render_settings`, what every render of the objective and of evaluation
  composites over and culls at.
- `supervision`: renders of Gaussians scored against views (`supervision_loss`), its terms and
  the memory-lean mean over view chunks (`mean_over_view_chunks`).
- `model_loss`: the losses of a model's parameters on a batch (`tokengs_loss_fn`, static and
  time-conditioned) built on them.

    loss_fn = tokengs_loss_fn(config, objective=ObjectiveConfig(view_chunk_size=2))
"""

from tokengs_jax.objective.model_loss import (
  dynamic_model_loss,
  static_model_loss,
  supervised_views,
  time_conditioned_loss,
  tokengs_loss_fn,
)
from tokengs_jax.objective.settings import (
  ObjectiveConfig,
  background_colours,
  check_cross_view,
  cross_view_flags,
  render_settings,
)
from tokengs_jax.objective.supervision import (
  add_opacity,
  add_visibility,
  mean_over_view_chunks,
  photometric_loss,
  render_diagnostics,
  render_views,
  supervision_loss,
)

__all__ = [
  "ObjectiveConfig",
  "add_opacity",
  "add_visibility",
  "background_colours",
  "check_cross_view",
  "cross_view_flags",
  "dynamic_model_loss",
  "mean_over_view_chunks",
  "photometric_loss",
  "render_diagnostics",
  "render_settings",
  "render_views",
  "static_model_loss",
  "supervised_views",
  "supervision_loss",
  "time_conditioned_loss",
  "tokengs_loss_fn",
]
