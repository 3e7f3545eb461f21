"""The density-control strategy: statistics, settings and the ``(init, update)`` pair.

As gsplat's strategies next to ``strategy/ops.py``: this module keeps what is carried
between steps and when to act, :mod:`jaxedit.densify.ops` what is done.
:func:`adaptive` turns a :class:`DensifyConfig` into a :class:`Strategy`; the
statistics it carries are :mod:`jaxedit.densify.stats`' :class:`DensifyStats`, each
update reports a :class:`DensifyInfo`, and :func:`creation_budget` is ProEdit's t(n, N).

What ``update`` does at every call: accumulate the 3DGS statistics of this
step's render (norm of the 2D-mean gradient in NDC units, visibility count,
largest screen radius). At maintenance steps (``step > warmup``, ``step %
refine_every == 0``, ``step <= stop_at``; with ``refine_from_warmup`` the clock starts
at the warm-up: ``step >= warmup``, ``(step - warmup) % refine_every == 0``), in this
order:

1. cull: alive Gaussians with opacity < ``cull_alpha``, or larger than
   ``cull_scale * scene_extent`` in world space, or (after the first opacity
   reset, as in INRIA's 3DGS) whose screen radius reached ``cull_screen`` of the
   image size. Culling first frees slots that the creation below can reuse at
   once, and no Gaussian is created from a parent that is being removed.
2. create: candidates are the surviving, seen Gaussians whose mean NDC gradient
   passes the threshold. They are ranked by that score (highest first, ties by
   slot index) and the first ``k`` are refined, with

   * classic mode (``budget=None``): ``k = min(#candidates, free slots,
     max_gaussians - alive)``, threshold ``grad_threshold`` (2e-4);
   * ProEdit's adaptive creation (``budget=t``): ``k = min(t(n, N),
     #candidates, free slots, max_gaussians - alive)`` where ``n`` is the number
     culled at the previous maintenance step and ``N`` the number alive before
     this one. The effective gradient threshold is the score of the k-th
     candidate: the threshold is chosen by the scheduled count, not fixed
     (paper, section 3.3 and appendix D).

   A selected Gaussian whose largest scale is <= ``dense_percent *
   scene_extent`` is duplicated (an exact copy goes to a free slot); a larger
   one is split: two children are drawn from the parent's own Gaussian
   distribution with ``key``, scales divided by ``split_factor`` (1.6); the
   first child replaces the parent in its slot, the second takes a free slot.
   Either way one refined Gaussian consumes exactly one free slot.
3. the optimiser moments (every ``Gaussians``-shaped node of ``opt_state``,
   e.g. Adam's mu and nu) of new, split and freed slots are zeroed; the
   statistics restart; ``n`` is remembered for the next budget.

At ``step % reset_every == 0`` (``step <= stop_at``) the opacities are clamped
to ``reset_value`` (2 x ``cull_alpha`` by default) and their moments zeroed.

The number of Gaussians never exceeds ``max_gaussians`` (a hard cap). When the
cap would allow more than the current capacity, ``update`` does not drop the
excess silently: ``info.capacity_limited`` is set and ``info.slots_needed``
says how many slots the step wanted; the caller (outside jit) grows the
capacity with :func:`jaxedit.densify.ops.grow_state` /
:func:`jaxedit.densify.ops.grown_capacity` and redoes the step (it is pure, so the
redo gives the same result as if the room had been there).
:func:`jaxedit.train.fit` does this automatically.

Step numbering: ``step`` is the number of optimiser steps done including the
current one (1-based), as in INRIA's trainer.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from ..errors import DataError, check_ranges, ranged
from ..gaussians import Gaussians
from .ops import cull_mask, opacity_reset, place, remove, select, split, zero_moments
from .stats import DensifyStats, RenderAux, accumulate, init_stats

BudgetFn = Callable[[jax.Array, jax.Array], jax.Array]


class DensifyInfo(NamedTuple):
    """What one ``update`` did (int32 / bool scalars; zeros when nothing was due).

    Attributes:
      refined: a maintenance (densify + cull) step ran.
      reset: the opacities were reset.
      created: Gaussians added (= split + duplicated).
      split, duplicated, culled: counts of each operation.
      alive: Gaussians alive after the update.
      capacity: slots in the pytree (static, reported for logs).
      candidates: Gaussians passing the gradient threshold.
      budget: t(n, N) in budget mode, or the number of candidates in classic mode.
      threshold: the effective NDC gradient threshold (score of the last
        created Gaussian; ``grad_threshold`` in classic mode when nothing was created).
      capacity_limited: free slots were the binding limit and the cap would
        allow more: grow the capacity and redo the step.
      cap_limited: the hard cap ``max_gaussians`` was the binding limit.
      slots_needed: alive + wanted creations (within the cap): the capacity the
        step needed.
    """

    refined: jax.Array
    reset: jax.Array
    created: jax.Array
    split: jax.Array
    duplicated: jax.Array
    culled: jax.Array
    alive: jax.Array
    capacity: jax.Array
    candidates: jax.Array
    budget: jax.Array
    threshold: jax.Array
    capacity_limited: jax.Array
    cap_limited: jax.Array
    slots_needed: jax.Array


class Strategy(NamedTuple):
    """An ``(init, update)`` pair, like an optax ``GradientTransformation``."""

    init: Callable
    update: Callable


# --------------------------------------------------------------------------------------
# Creation budget t(n, N)
# --------------------------------------------------------------------------------------

def creation_budget(*, min_new: int, growth: float, max_fraction: float) -> BudgetFn:
    """The family of creation budgets t(n, N) for ProEdit's adaptive creation.

        t(n, N) = max(min_new, min(floor(max_fraction N), n + ceil(growth N)))

    with ``n`` the number culled at the previous maintenance step and ``N`` the
    number alive. Why this shape: re-creating ``n`` replaces what the last cull
    removed, so capacity moves from Gaussians that lost their opacity (wrong
    geometry, floaters) to the places with the largest view-space gradient
    (where the edited views disagree with the scene most) without growing the
    scene; ``growth N`` adds a small fraction on top, so the total grows
    smoothly and geometrically (1.02^k after k maintenance steps by default,
    about x1.6 over a 25-step subtask) instead of exploding on inconsistent
    edited views; ``max_fraction N`` bounds a single step (after an opacity
    reset a cull can remove a large part of the scene; it is refilled at most
    10% per step); ``min_new`` lets a tiny or freshly culled scene still grow.
    The constants' defaults are :class:`DensifyConfig`'s ``budget_*`` fields.

    Returns:
      a jit-able function (n int [], N int []) -> int32 [].
    """
    if min_new < 0 or growth < 0 or max_fraction < 0:
        raise ValueError("creation_budget parameters must be >= 0")

    def budget(n, alive):
        n = jnp.asarray(n, jnp.float32)
        alive = jnp.asarray(alive, jnp.float32)
        t = jnp.minimum(jnp.floor(max_fraction * alive), n + jnp.ceil(growth * alive))
        return jnp.maximum(min_new, t).astype(jnp.int32)

    return budget


# --------------------------------------------------------------------------------------
# The strategy
# --------------------------------------------------------------------------------------

def nothing_done(capacity: int, alive) -> DensifyInfo:
    """The :class:`DensifyInfo` of an update that changed nothing (``alive``: int [])."""
    z = jnp.zeros((), jnp.int32)
    f = jnp.zeros((), bool)
    return DensifyInfo(refined=f, reset=f, created=z, split=z, duplicated=z, culled=z,
                       alive=alive.astype(jnp.int32), capacity=jnp.int32(capacity), candidates=z,
                       budget=z, threshold=jnp.zeros((), jnp.float32), capacity_limited=f,
                       cap_limited=f, slots_needed=alive.astype(jnp.int32))


@dataclasses.dataclass(frozen=True)
class DensifyConfig:
    """Density control settings: the one declaration of them and their defaults
    (nerfstudio Splatfacto / INRIA 3DGS). :func:`adaptive` turns them into a strategy;
    :class:`jaxedit.train.TrainConfig` stores them (JSON, checkpoints).

    Attributes:
      enabled: False turns density control off (no maintenance, no resets).
      max_gaussians: hard cap on the number of Gaussians alive, never exceeded.
      budget: ProEdit's adaptive creation with the budget :func:`creation_budget`
        instead of classic thresholding at ``grad_threshold``.
      budget_min_new: the budget's floor: Gaussians a maintenance may always create.
      budget_growth: the budget's growth: this fraction of those alive on top of the
        number the last maintenance culled.
      budget_max_fraction: the budget's ceiling: at most this fraction of those alive
        created in one maintenance.
      grad_threshold: classic mode: mean NDC gradient norm needed to refine (2e-4).
      grad_floor: budget mode: candidates need a mean gradient strictly above this.
      refine_every: steps between two density maintenances (split, duplicate, cull).
      warmup: steps before the first maintenance (maintenance only at ``step > warmup``).
      stop_at: last step with maintenance and opacity resets (None: half of the run's
        iterations, Splatfacto's 15000 of 30000).
      refine_from_warmup: False: INRIA's clock, maintenance at the multiples of
        ``refine_every`` above ``warmup``. True: maintenance at ``warmup, warmup +
        refine_every, ...``, so the warm-up is exactly the steps without density control
        (ProEdit's W).
      reset_every: opacity reset period (0 disables); only while ``step <= stop_at``.
      cull_alpha: cull opacity below this.
      reset_value: opacity after a periodic reset (None: ``2 * cull_alpha``).
      dense_percent: duplicate if max scale <= this * scene_extent, else split.
      split_factor: children's scales are the parent's divided by this.
      cull_scale: cull if max scale > this * scene_extent (None disables).
      cull_screen: cull if the screen radius reached this fraction of max(W, H)
        since the last maintenance; only after the first opacity reset, as in
        INRIA's 3DGS (early Gaussians are legitimately large on screen), hence
        never when ``reset_every`` is 0; None disables.
      strategy: the density strategy that reads these settings, by the name it was
        registered under (:func:`register_strategy`; "adaptive": :func:`adaptive`).
    """

    enabled: bool = True
    max_gaussians: int | None = ranged(1_000_000, low=1)
    budget: bool = False
    budget_min_new: int = 64
    budget_growth: float = 0.02
    budget_max_fraction: float = 0.1
    grad_threshold: float = 2e-4
    grad_floor: float = 0.0
    refine_every: int = ranged(100, low=1)
    warmup: int = ranged(500, low=0)
    refine_from_warmup: bool = False
    stop_at: int | None = ranged(None, low=0)
    reset_every: int = ranged(3000, low=0)
    cull_alpha: float = ranged(0.005, low=0.0, high=1.0, open=True)
    reset_value: float | None = None
    dense_percent: float = 0.01
    split_factor: float = 1.6
    cull_scale: float | None = 0.1
    cull_screen: float | None = 0.15
    strategy: str = "adaptive"

    def __post_init__(self):
        check_ranges(self)
        if self.strategy not in _STRATEGIES:
            raise DataError("strategy", f"unknown density strategy {self.strategy!r}; "
                                        f"registered: {', '.join(sorted(_STRATEGIES))}")


#: ``make(config, *, scene_extent, iterations) -> Strategy`` by name (:func:`register_strategy`).
_STRATEGIES: dict[str, Callable[..., Strategy]] = {}


def register_strategy(name: str, make: Callable[..., Strategy]) -> None:
    """Make ``DensifyConfig(strategy=name)`` train with ``make(config, *, scene_extent,
    iterations) -> Strategy`` (the signature of :func:`adaptive`). ``make`` must be a
    module-level function: compiled programs are cached by it."""
    if not name or not callable(make):
        raise DataError("strategy", f"need a name and a callable, got {name!r}, {make!r}")
    _STRATEGIES[name] = make


def strategy_for(config: DensifyConfig, *, scene_extent, iterations: int) -> Strategy:
    """The :class:`Strategy` ``config.strategy`` names, built from ``config``: the one place a
    run's density control is made."""
    return _STRATEGIES[config.strategy](config, scene_extent=scene_extent, iterations=iterations)


def adaptive(config: DensifyConfig, *, scene_extent: float, iterations: int) -> Strategy:
    """3DGS adaptive density control with an optional ProEdit creation budget.

    Args:
      config: the :class:`DensifyConfig`.
      scene_extent: world size of the scene (radius of the camera rig, INRIA's
        ``cameras_extent``); scales the duplicate/split and world-cull thresholds.
      iterations: the run's steps (``stop_at=None`` stops at half of them).
    """
    if config.max_gaussians is None:
        raise ValueError("max_gaussians is unresolved (None): set the cap first")
    stop_at = config.stop_at if config.stop_at is not None else iterations // 2
    reset_every = config.reset_every
    if not config.enabled:
        stop_at, reset_every = -1, 0
    budget = None
    if config.budget:
        budget = creation_budget(min_new=config.budget_min_new, growth=config.budget_growth,
                                 max_fraction=config.budget_max_fraction)
    max_gaussians, grad_threshold, grad_floor = (config.max_gaussians, config.grad_threshold,
                                                 config.grad_floor)
    refine_every, warmup, cull_alpha = config.refine_every, config.warmup, config.cull_alpha
    from_warmup = config.refine_from_warmup
    cull_screen = config.cull_screen
    if refine_every <= 0:
        raise ValueError("refine_every must be positive")
    if max_gaussians <= 0:
        raise ValueError("max_gaussians must be positive")
    reset_value = 2.0 * cull_alpha if config.reset_value is None else config.reset_value
    floor = grad_threshold if budget is None else grad_floor
    # INRIA culls by screen size only after the first opacity reset.
    screen_from = reset_every if reset_every > 0 else None
    dup_scale = config.dense_percent * scene_extent
    big_scale = None if config.cull_scale is None else config.cull_scale * scene_extent

    def init(gaussians: Gaussians) -> DensifyStats:
        return init_stats(gaussians.capacity)

    def refine(gaussians, opt_state, stats, step, key, frozen):
        n_alive0 = gaussians.num_alive()
        culled = cull_mask(gaussians, stats, step, cull_alpha=cull_alpha, big_scale=big_scale,
                           cull_screen=cull_screen, screen_from=screen_from) & ~frozen
        g = remove(gaussians, culled)
        n_alive1 = g.num_alive()
        # t(n, N) over the Gaussians the edit may change: a local edit's frozen ones are
        # never culled nor candidates, and counted in N they let the editable part grow by
        # 0.02 of the whole scene per step (person: a third more Gaussians in the region
        # than the global edit left there).
        t = None if budget is None else jnp.maximum(jnp.asarray(budget(
            stats.last_culled, n_alive0 - jnp.sum(gaussians.alive & frozen)), jnp.int32), 0)
        # Frozen Gaussians are never candidates (no split, no clone): only the editable
        # ones, and hence only their neighbourhood, get new Gaussians.
        seen = stats._replace(count=jnp.where(frozen, 0, stats.count))
        sel = select(seen, g.alive, floor=floor, budget=t, max_gaussians=max_gaussians)
        small = jnp.exp(jnp.max(g.log_scales, axis=-1)) <= dup_scale
        splits, dups = sel.selected & ~small, sel.selected & small
        g, second = split(g, splits, key, config.split_factor)
        # A duplicated parent's copy is its own row; a split parent's is its second child.
        rows = jax.tree_util.tree_map(lambda a, b: jnp.where(
            splits.reshape(splits.shape + (1,) * (a.ndim - 1)), a, b), second, g)
        g, created = place(g, rows, sel.order, sel.count)
        opt_state = zero_moments(opt_state, created | splits | culled)
        n_culled = (n_alive0 - n_alive1).astype(jnp.int32)
        new_stats = init_stats(g.capacity)._replace(last_culled=n_culled)
        k = sel.count
        kth = jnp.clip(k - 1, 0, g.capacity - 1)
        threshold = jnp.where(k > 0, sel.score[sel.order[kth]], jnp.float32(floor))
        free = g.capacity - n_alive1
        want_in_cap = jnp.minimum(sel.wanted, sel.room_cap)
        info = DensifyInfo(
            refined=jnp.ones((), bool), reset=jnp.zeros((), bool), created=k.astype(jnp.int32),
            split=jnp.sum(splits.astype(jnp.int32)), duplicated=jnp.sum(dups.astype(jnp.int32)),
            culled=n_culled, alive=(n_alive1 + k).astype(jnp.int32),
            capacity=jnp.int32(g.capacity), candidates=jnp.sum(sel.candidates.astype(jnp.int32)),
            budget=(jnp.sum(sel.candidates.astype(jnp.int32)) if t is None else t
                    ).astype(jnp.int32),
            threshold=threshold.astype(jnp.float32), capacity_limited=want_in_cap > free,
            cap_limited=sel.wanted > sel.room_cap,
            slots_needed=(n_alive1 + want_in_cap).astype(jnp.int32))
        return g, opt_state, new_stats, info

    def skip(gaussians, opt_state, stats, step, key, frozen):
        return gaussians, opt_state, stats, nothing_done(gaussians.capacity, gaussians.num_alive())

    def update(gaussians: Gaussians, opt_state, stats: DensifyStats, aux: RenderAux | None,
               step, key: jax.Array, frozen: jax.Array | None = None):
        """One step of density control; see the module docstring.

        Args:
          gaussians: Gaussians, capacity C (after this step's optimiser update).
          opt_state: optax state with Gaussians-shaped moments (or None).
          stats: DensifyStats from ``init`` or the previous update.
          aux: this step's RenderAux, or None to accumulate nothing.
          step: int, 1-based optimiser step count.
          key: PRNG key (split children).
          frozen: bool [C] or None: alive Gaussians never culled, split, cloned or
            reset (a local edit's outside; None: none).
        Returns:
          (gaussians, opt_state, stats, info: DensifyInfo).
        """
        step = jnp.asarray(step, jnp.int32)
        frozen = (jnp.zeros(gaussians.alive.shape, bool) if frozen is None
                  else jnp.asarray(frozen, bool))
        if aux is not None:
            stats = accumulate(stats, aux)
        if from_warmup:
            due = (step >= warmup) & ((step - warmup) % refine_every == 0) & (step > 0)
        else:
            due = (step > warmup) & (step % refine_every == 0)
        due = due & (step <= stop_at)
        gaussians, opt_state, stats, info = jax.lax.cond(
            due, refine, skip, gaussians, opt_state, stats, step, key, frozen)
        if reset_every > 0:
            do_reset = (step % reset_every == 0) & (step <= stop_at)

            def reset(g, o):
                r, o = opacity_reset(g, o, reset_value, clamp=True)
                return dataclasses.replace(r, opacity_logits=jnp.where(
                    frozen, g.opacity_logits, r.opacity_logits)), o

            gaussians, opt_state = jax.lax.cond(do_reset, reset, lambda g, o: (g, o),
                                                gaussians, opt_state)
            info = info._replace(reset=do_reset)
        return gaussians, opt_state, stats, info

    return Strategy(init=init, update=update)


register_strategy("adaptive", adaptive)
