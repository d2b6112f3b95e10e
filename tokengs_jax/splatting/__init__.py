"""Differentiable tile-based Gaussian splatting (gsplat 1.5.3 semantics) in jax.numpy."""

from tokengs_jax.splatting.config import RenderConfig, RenderResult, RenderStats
from tokengs_jax.splatting.pipeline import render, scene_budget_hint

__all__ = ["RenderConfig", "RenderResult", "RenderStats", "render", "scene_budget_hint"]
