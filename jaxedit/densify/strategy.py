"""The density-control strategy: settings and the ``(init, update)`` pair (:func:`adaptive`)."""

from __future__ import annotations

import dataclasses
import functools
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
      refined: a maintenance step ran.
      reset: the opacities were reset.
      created: Gaussians added (split + duplicated).
      split, duplicated, culled: counts of each operation.
      alive: Gaussians alive after the update.
      capacity: slots in the pytree.
      candidates: Gaussians passing the gradient threshold.
      budget: t(n, N), or the candidate count in classic mode.
      grad_cut: the gradient score of the last Gaussian created (the effective cut).
      capacity_limited: free slots bound below the cap: grow and redo the step.
      cap_limited: ``max_gaussians`` was the binding limit.
      slots_needed: the capacity the step needed (alive + wanted, within the cap).
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
    grad_cut: jax.Array
    capacity_limited: jax.Array
    cap_limited: jax.Array
    slots_needed: jax.Array


class Strategy(NamedTuple):
    """An ``(init, update)`` pair, like an optax ``GradientTransformation``:
    ``init(gaussians) -> stats``; ``update(gaussians, opt_state, stats, aux, step, key,
    frozen=None, *, scene_extent) -> (gaussians, opt_state, stats, info)``."""

    init: Callable
    update: Callable


# -- Creation budget t(n, N) -----------------------------------------------------------

def creation_budget(*, min_new: int, growth: float, max_fraction: float) -> BudgetFn:
    """ProEdit's creation budget (paper 3.3), ``n`` culled at the previous maintenance, ``N``
    alive: t(n, N) = max(min_new, min(floor(max_fraction N), n + ceil(growth N))).

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


# -- The strategy ----------------------------------------------------------------------

def nothing_done(capacity: int, alive) -> DensifyInfo:
    """The :class:`DensifyInfo` of an update that changed nothing (``alive``: int [])."""
    z = jnp.zeros((), jnp.int32)
    f = jnp.zeros((), bool)
    return DensifyInfo(refined=f, reset=f, created=z, split=z, duplicated=z, culled=z,
                       alive=alive.astype(jnp.int32), capacity=jnp.int32(capacity), candidates=z,
                       budget=z, grad_cut=jnp.zeros((), jnp.float32), capacity_limited=f,
                       cap_limited=f, slots_needed=alive.astype(jnp.int32))


@dataclasses.dataclass(frozen=True)
class DensifyConfig:
    """Density control settings and their defaults (Splatfacto / INRIA 3DGS).

    Attributes:
      enabled: False turns density control off (no maintenance, no resets).
      max_gaussians: hard cap on the Gaussians alive, never exceeded.
      budget: ProEdit's adaptive creation (:func:`creation_budget`) instead of thresholding.
      budget_min_new: the budget's floor: Gaussians a maintenance may always create.
      budget_growth: the budget's growth: this fraction of those alive on top of the last cull.
      budget_max_fraction: the budget's ceiling: at most this fraction of those alive per step.
      grad_threshold: classic mode: mean NDC gradient norm needed to refine.
      grad_floor: budget mode: candidates need a mean gradient strictly above this.
      refine_every: steps between two density maintenances.
      warmup: steps before the first maintenance (None: set by the caller).
      stop_at: last step with maintenance and opacity resets (None: half the iterations).
      refine_from_warmup: maintenance from ``warmup`` on (ProEdit's W), not at multiples.
      reset_every: opacity reset period (0 disables).
      cull_alpha: cull opacity below this.
      reset_value: opacity after a periodic reset (None: ``2 * cull_alpha``).
      dense_percent: duplicate if max scale <= this * scene_extent, else split.
      split_factor: children's scales are the parent's divided by this.
      cull_scale: cull if max scale > this * scene_extent (None disables).
      cull_screen: cull if the screen radius reached this fraction of max(W, H) (None disables).
      strategy: the registered name of the strategy that reads these (:func:`register_strategy`).
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
    warmup: int | None = ranged(500, low=0)
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

    @property
    def floor(self) -> float:
        """The mean gradient a candidate must exceed: ``grad_floor`` with the budget, else
        ``grad_threshold``."""
        return self.grad_floor if self.budget else self.grad_threshold


#: ``make(config, *, iterations) -> Strategy`` by name (:func:`register_strategy`).
_STRATEGIES: dict[str, Callable[..., Strategy]] = {}


def register_strategy(name: str, make: Callable[..., Strategy]) -> None:
    """Make ``DensifyConfig(strategy=name)`` use ``make(config, *, iterations) -> Strategy``."""
    if not name or not callable(make):
        raise DataError("strategy", f"need a name and a callable, got {name!r}, {make!r}")
    _STRATEGIES[name] = make


def strategy_for(config: DensifyConfig, *, iterations: int) -> Strategy:
    """The :class:`Strategy` ``config.strategy`` names, built from ``config`` once: equal
    settings give the same object, so compiled steps are shared."""
    return _built(_STRATEGIES[config.strategy], config, int(iterations))


@functools.lru_cache(maxsize=64)
def _built(make, config: DensifyConfig, iterations: int) -> Strategy:
    return make(config, iterations=iterations)


def adaptive(config: DensifyConfig, *, iterations: int) -> Strategy:
    """3DGS adaptive density control with an optional ProEdit creation budget.

    At maintenance steps ``update`` culls, then splits large and duplicates small
    high-gradient candidates (at most the free slots, the cap and t(n, N)); every
    ``reset_every`` steps opacities are clamped. ``info.capacity_limited`` asks the caller
    to grow (:func:`jaxedit.densify.ops.grow_state`) and redo the step.

    Args:
      config: the :class:`DensifyConfig`.
      iterations: the run's steps (``stop_at=None`` stops at half of them).
    ``update``'s ``scene_extent`` (INRIA's ``cameras_extent``, traced) scales the
    duplicate/split and world-cull thresholds.
    """
    if config.max_gaussians is None:
        raise ValueError("max_gaussians is unresolved (None): set the cap first")
    if config.warmup is None:
        raise ValueError("warmup is unresolved (None): set the warm-up first")
    stop_at = config.stop_at if config.stop_at is not None else iterations // 2
    reset_every = config.reset_every
    if not config.enabled:
        stop_at, reset_every = -1, 0
    budget = None
    if config.budget:
        budget = creation_budget(min_new=config.budget_min_new, growth=config.budget_growth,
                                 max_fraction=config.budget_max_fraction)
    refine_every, warmup = config.refine_every, config.warmup
    if refine_every <= 0:
        raise ValueError("refine_every must be positive")
    if config.max_gaussians <= 0:
        raise ValueError("max_gaussians must be positive")
    reset_value = 2.0 * config.cull_alpha if config.reset_value is None else config.reset_value
    # INRIA culls by screen size only after the first opacity reset.
    screen_from = reset_every if reset_every > 0 else None

    def init(gaussians: Gaussians) -> DensifyStats:
        return init_stats(gaussians.capacity)

    def refine(gaussians, opt_state, stats, step, key, frozen, scene_extent):
        dup_scale = config.dense_percent * scene_extent
        big_scale = None if config.cull_scale is None else config.cull_scale * scene_extent
        n_alive0 = gaussians.num_alive()
        culled = cull_mask(gaussians, stats, step, cull_alpha=config.cull_alpha,
                           big_scale=big_scale, cull_screen=config.cull_screen,
                           screen_from=screen_from) & ~frozen
        g = remove(gaussians, culled)
        n_alive1 = g.num_alive()
        # t(n, N) counts only the editable Gaussians: with frozen ones in N a local edit's
        # region would grow by a fraction of the whole scene each step.
        t = None if budget is None else jnp.maximum(jnp.asarray(budget(
            stats.last_culled, n_alive0 - jnp.sum(gaussians.alive & frozen)), jnp.int32), 0)
        # Frozen Gaussians are never candidates, so only the editable region grows.
        seen = stats._replace(count=jnp.where(frozen, 0, stats.count))
        sel = select(seen, g.alive, floor=config.floor, budget=t,
                     max_gaussians=config.max_gaussians)
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
        grad_cut = jnp.where(k > 0, sel.score[sel.order[kth]], jnp.float32(config.floor))
        free = g.capacity - n_alive1
        want_in_cap = jnp.minimum(sel.wanted, sel.room_cap)
        info = DensifyInfo(
            refined=jnp.ones((), bool), reset=jnp.zeros((), bool), created=k.astype(jnp.int32),
            split=jnp.sum(splits.astype(jnp.int32)), duplicated=jnp.sum(dups.astype(jnp.int32)),
            culled=n_culled, alive=(n_alive1 + k).astype(jnp.int32),
            capacity=jnp.int32(g.capacity), candidates=jnp.sum(sel.candidates.astype(jnp.int32)),
            budget=(jnp.sum(sel.candidates.astype(jnp.int32)) if t is None else t
                    ).astype(jnp.int32),
            grad_cut=grad_cut.astype(jnp.float32), capacity_limited=want_in_cap > free,
            cap_limited=sel.wanted > sel.room_cap,
            slots_needed=(n_alive1 + want_in_cap).astype(jnp.int32))
        return g, opt_state, new_stats, info

    def skip(gaussians, opt_state, stats, step, key, frozen, scene_extent):
        return gaussians, opt_state, stats, nothing_done(gaussians.capacity, gaussians.num_alive())

    def update(gaussians: Gaussians, opt_state, stats: DensifyStats, aux: RenderAux | None,
               step, key: jax.Array, frozen: jax.Array | None = None, *, scene_extent):
        """One step of density control (:func:`adaptive`).

        Args:
          gaussians: capacity C, after this step's optimiser update.
          opt_state: optax state with Gaussians-shaped moments (or None).
          stats: DensifyStats from ``init`` or the previous update.
          aux: this step's RenderAux, or None.
          step: int, 1-based.
          key: PRNG key for split children.
          frozen: bool [C] or None: Gaussians never culled, split, cloned or reset.
          scene_extent: float [], the world size.
        Returns:
          (gaussians, opt_state, stats, info: DensifyInfo).
        """
        step = jnp.asarray(step, jnp.int32)
        frozen = (jnp.zeros(gaussians.alive.shape, bool) if frozen is None
                  else jnp.asarray(frozen, bool))
        if aux is not None:
            stats = accumulate(stats, aux)
        if config.refine_from_warmup:
            due = (step >= warmup) & ((step - warmup) % refine_every == 0) & (step > 0)
        else:
            due = (step > warmup) & (step % refine_every == 0)
        due = due & (step <= stop_at)
        gaussians, opt_state, stats, info = jax.lax.cond(
            due, refine, skip, gaussians, opt_state, stats, step, key, frozen, scene_extent)
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
