"""Adaptive density control (densify / cull) as a pure, optax-shaped transformation::

    strategy = strategy_for(DensifyConfig(...), iterations=...)   # built once per config
    stats = strategy.init(gaussians)
    gaussians, opt_state, stats, info = strategy.update(
        gaussians, opt_state, stats, render_aux, step, key, scene_extent=extent)

Laid out as gsplat's ``strategy/``: :mod:`.ops` (the operations), :mod:`.stats` (the
statistics), :mod:`.strategy` (settings, ProEdit's budget, :func:`adaptive`).
"""

from .ops import (Selection, cull_mask, grow_state, grown_capacity, opacity_reset, place, remove,
                  select, split, zero_moments)
from .stats import DensifyStats, RenderAux, accumulate, init_stats, render_aux
from .strategy import (BudgetFn, DensifyConfig, DensifyInfo, Strategy, adaptive, creation_budget,
                       nothing_done, register_strategy, strategy_for)

__all__ = [
    # ops
    "Selection", "cull_mask", "grow_state", "grown_capacity", "opacity_reset", "place", "remove",
    "select", "split", "zero_moments",
    # stats
    "DensifyStats", "RenderAux", "accumulate", "init_stats", "render_aux",
    # strategy
    "BudgetFn", "DensifyConfig", "DensifyInfo", "Strategy", "adaptive", "creation_budget",
    "nothing_done", "register_strategy", "strategy_for",
]
