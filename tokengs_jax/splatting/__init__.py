"""Differentiable tile-based Gaussian splatting (gsplat 1.5.3 semantics) in jax.numpy."""

from tokengs_jax.splatting import compaction
from tokengs_jax.splatting.checks import RenderBudgetWarning
from tokengs_jax.splatting.config import RenderConfig, RenderResult, RenderStats
from tokengs_jax.splatting.exact import RenderBudgetError, larger_budget, render_exact
from tokengs_jax.splatting.pipeline import render

__all__ = [
  "RenderBudgetError",
  "RenderBudgetWarning",
  "RenderConfig",
  "RenderResult",
  "RenderStats",
  "compaction",
  "larger_budget",
  "render",
  "render_exact",
]
