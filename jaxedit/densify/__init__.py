"""Adaptive density control (densify / cull) as a pure, optax-shaped transformation.

``strategy = strategy_for(DensifyConfig(...), scene_extent=..., iterations=...)`` is a pair
of pure functions (:func:`adaptive` by default; another registered with
:func:`register_strategy` by ``DensifyConfig.strategy``)::

    stats = strategy.init(gaussians)
    gaussians, opt_state, stats, info = strategy.update(
        gaussians, opt_state, stats, render_aux, step, key)

Everything works on the fixed-capacity ``alive`` layout of
:class:`jaxedit.gaussians.Gaussians`: new Gaussians are written into free
(dead) slots, culled ones are marked dead, no shape ever depends on data, so
``update`` jit-compiles once and runs inside the compiled train step.

The package is split as gsplat's ``strategy/``:

* :mod:`.ops` -- the named pure operations, each usable alone: :func:`cull_mask` +
  :func:`remove` (cull), :func:`select` (rank and budget), :func:`split`,
  :func:`place` (duplication: a copy, or a split's second child, into a free slot),
  :func:`opacity_reset` and :func:`zero_moments` (reset), and the capacity growth
  outside jit (:func:`grown_capacity`, :func:`grow_state`);
* :mod:`.stats` -- the statistics both read (:class:`DensifyStats`, :func:`init_stats`,
  :func:`accumulate` of a :class:`RenderAux`);
* :mod:`.strategy` -- the settings (:class:`DensifyConfig`),
  ProEdit's creation budget t(n, N) (:func:`creation_budget`) and :func:`adaptive`,
  which composes the operations into the :class:`Strategy`; its docstring says what
  ``update`` does, step by step.

Every public name of the three is re-exported here: ``from jaxedit.densify import X``.
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
