"""The named pure operations of density control (as gsplat's ``strategy/ops.py``): cull,
rank, split, duplicate, reset and capacity growth outside jit, on the fixed-capacity
``alive`` layout, composed by :func:`jaxedit.densify.strategy.adaptive`."""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from .. import gaussians as glib
from ..gaussians import Gaussians
from .stats import DensifyStats


# -- Helpers on optimiser state --------------------------------------------------------

def _is_gaussians(x) -> bool:
    return isinstance(x, Gaussians)


def _map_gaussian_nodes(fn, tree):
    """Apply ``fn(name, array) -> array`` to every array field of every Gaussians node."""

    def on_node(node):
        if not _is_gaussians(node):
            return node
        fields = {}
        for f in dataclasses.fields(node):
            value = getattr(node, f.name)
            if isinstance(value, jax.Array) or hasattr(value, "shape"):
                value = fn(f.name, value)
            fields[f.name] = value
        return dataclasses.replace(node, **fields)

    return jax.tree_util.tree_map(on_node, tree, is_leaf=_is_gaussians)


def zero_moments(opt_state, mask: jax.Array, fields=None):
    """Zero the per-slot optimiser state where ``mask`` [C] is set.

    Args:
      opt_state: any optax state whose per-parameter parts are ``Gaussians``-shaped.
      mask: bool [C].
      fields: names of Gaussians fields to touch (default: all).
    """

    def fn(name, a):
        if fields is not None and name not in fields:
            return a
        if a.ndim == 0 or a.shape[0] != mask.shape[0]:
            return a
        m = mask.reshape(mask.shape + (1,) * (a.ndim - 1))
        return jnp.where(m, jnp.zeros_like(a), a)

    return _map_gaussian_nodes(fn, opt_state)


def opacity_reset(gaussians: Gaussians, opt_state, value: float, *, clamp: bool = False):
    """Reset opacities to ``value`` and zero the opacity optimiser moments.

    ``clamp=False``: every alive opacity set to ``value`` (ProEdit's per-subtask reset);
    ``clamp=True``: lowered to at most ``value`` (3DGS's periodic reset). Dead slots unchanged.

    Args:
      gaussians: Gaussians, capacity C.
      opt_state: optax state with Gaussians-shaped moments (or None).
      value: opacity in (0, 1).
    Returns:
      (gaussians, opt_state).
    """
    value = jnp.asarray(value, gaussians.opacity_logits.dtype)
    logit = jnp.log(value) - jnp.log1p(-value)
    # sigmoid(logit) can round one ulp below ``value``; the cull ``opacity < cull_alpha``
    # would then remove every Gaussian no view has updated yet.
    logit = jnp.where(jax.nn.sigmoid(logit) < value, jnp.nextafter(logit, jnp.inf), logit)
    new = jnp.minimum(gaussians.opacity_logits, logit) if clamp else jnp.full_like(
        gaussians.opacity_logits, logit)
    logits = jnp.where(gaussians.alive, new, gaussians.opacity_logits)
    g = dataclasses.replace(gaussians, opacity_logits=logits)
    if opt_state is not None:
        all_slots = jnp.ones(gaussians.alive.shape, bool)
        opt_state = zero_moments(opt_state, all_slots, fields=("opacity_logits",))
    return g, opt_state


# -- Capacity growth (outside jit) -----------------------------------------------------

def grown_capacity(capacity: int, needed: int, max_gaussians: int) -> int:
    """Smallest ``capacity * 2^m`` holding ``needed`` slots, clamped to ``max_gaussians``."""
    needed = min(int(needed), int(max_gaussians))
    new = max(int(capacity), 1)
    while new < needed:
        new *= 2
    return max(int(capacity), min(new, int(max_gaussians)))


def _pad_rows(a, extra: int):
    pad = jnp.zeros((extra,) + tuple(a.shape[1:]), a.dtype)
    return jnp.concatenate([a, pad], axis=0)


def grow_state(gaussians: Gaussians, opt_state, stats: DensifyStats | None, capacity: int):
    """Grow Gaussians, optimiser state and densify stats to ``capacity`` slots (outside
    jit); the new slots are dead with zero moments and statistics."""
    old = gaussians.capacity
    extra = capacity - old
    if extra < 0:
        raise ValueError(f"cannot shrink capacity {old} to {capacity}")
    if extra == 0:
        return gaussians, opt_state, stats
    g = glib.grow(gaussians, capacity)

    def fn(name, a):
        return _pad_rows(a, extra) if a.ndim >= 1 and a.shape[0] == old else a

    if opt_state is not None:
        opt_state = _map_gaussian_nodes(fn, opt_state)
    if stats is not None:
        stats = DensifyStats(grad_sum=_pad_rows(stats.grad_sum, extra),
                             count=_pad_rows(stats.count, extra),
                             max_radius=_pad_rows(stats.max_radius, extra),
                             last_culled=stats.last_culled)
    return g, opt_state, stats


# -- The operations of a maintenance step (pure; composed by :func:`.strategy.adaptive`) ---

def cull_mask(g: Gaussians, stats: DensifyStats, step, *, cull_alpha: float,
              big_scale: float | None, cull_screen: float | None,
              screen_from: int | None) -> jax.Array:
    """bool [C]: alive Gaussians with opacity < ``cull_alpha``, largest world scale >
    ``big_scale``, or (after step ``screen_from``) screen radius > ``cull_screen``."""
    culled = jax.nn.sigmoid(g.opacity_logits) < cull_alpha
    if big_scale is not None:
        culled |= jnp.exp(jnp.max(g.log_scales, axis=-1)) > big_scale
    if cull_screen is not None and screen_from is not None:
        culled |= (stats.max_radius > cull_screen) & (step > screen_from)
    return culled & g.alive


def remove(g: Gaussians, mask: jax.Array) -> Gaussians:
    """``g`` with the slots of ``mask`` [C] dead (their parameters stay, unused)."""
    return dataclasses.replace(g, alive=g.alive & ~mask)


class Selection(NamedTuple):
    """The Gaussians one maintenance step refines, best first.

    Attributes:
      candidates: bool [C], alive, seen, mean NDC gradient above the floor.
      score: float [C], the mean gradient (-inf off the candidates).
      order: int32 [C], slots by decreasing score (ties: lower slot first).
      selected: bool [C], the first ``count`` of ``order``.
      count: int32 [], k, how many are refined.
      wanted: int32 [], min(budget, #candidates): what the step would create with room.
      room_cap: int32 [], how many the hard cap still allows.
    """

    candidates: jax.Array
    score: jax.Array
    order: jax.Array
    selected: jax.Array
    count: jax.Array
    wanted: jax.Array
    room_cap: jax.Array


def select(stats: DensifyStats, alive: jax.Array, *, floor: float, budget, max_gaussians: int
           ) -> Selection:
    """Rank the candidates by mean NDC gradient and select the first ``min(budget,
    #candidates, max_gaussians - alive, free slots)`` (``budget`` None: every candidate)."""
    capacity = alive.shape[0]
    avg = stats.grad_sum / jnp.maximum(stats.count, 1).astype(jnp.float32)
    cand = alive & (stats.count > 0) & (avg > floor)
    n_cand = jnp.sum(cand.astype(jnp.int32))
    score = jnp.where(cand, avg, -jnp.inf)
    index = jnp.arange(capacity, dtype=jnp.int32)
    _, order = jax.lax.sort((-score, index), num_keys=2)  # order[j]: j-th best slot
    rank = jnp.zeros((capacity,), jnp.int32).at[order].set(index)
    n_alive = jnp.sum(alive.astype(jnp.int32))
    want = jnp.minimum(n_cand if budget is None else budget, n_cand)
    room_cap = jnp.maximum(max_gaussians - n_alive, 0)
    k = jnp.minimum(jnp.minimum(want, room_cap), capacity - n_alive)
    return Selection(candidates=cand, score=score, order=order, selected=cand & (rank < k),
                     count=k, wanted=want, room_cap=room_cap)


def split(g: Gaussians, mask: jax.Array, key: jax.Array, factor: float
          ) -> tuple[Gaussians, Gaussians]:
    """Split the Gaussians of ``mask`` [C] in two, drawn from the parent's distribution.

    Returns:
      (g with split parents replaced by their first child, rows [C]: the second children
      at split rows, ``g``'s own elsewhere); children's scales divided by ``factor``.
    """
    eps = jax.random.normal(key, (g.capacity, 2, 3), g.means.dtype)
    offsets = jnp.einsum("cij,ckj->cki", g.rotations(), eps * jnp.exp(g.log_scales)[:, None, :],
                         precision=jax.lax.Precision.HIGHEST)  # no TF32 on GPUs
    children = g.means[:, None, :] + offsets
    m = mask[:, None]
    log_scales = jnp.where(m, g.log_scales - math.log(factor), g.log_scales)
    first = dataclasses.replace(g, means=jnp.where(m, children[:, 0], g.means),
                                log_scales=log_scales)
    second = dataclasses.replace(first, means=jnp.where(m, children[:, 1], g.means))
    return first, second


def place(g: Gaussians, rows: Gaussians, order: jax.Array, count) -> tuple[Gaussians, jax.Array]:
    """Write ``rows[order[j]]`` into the j-th free slot of ``g``, alive, for j < ``count``.

    Returns:
      (g, bool [C]: the slots written).
    """
    capacity = g.capacity
    index = jnp.arange(capacity, dtype=jnp.int32)
    _, free_order = jax.lax.sort((g.alive.astype(jnp.int32), index), num_keys=2)
    dst = jnp.where(index < count, free_order, capacity)  # capacity = out of range: dropped

    def put(a, new_rows):
        return a.at[dst].set(new_rows[order], mode="drop")

    placed = Gaussians(means=put(g.means, rows.means), log_scales=put(g.log_scales, rows.log_scales),
                       quats=put(g.quats, rows.quats),
                       opacity_logits=put(g.opacity_logits, rows.opacity_logits),
                       sh=put(g.sh, rows.sh), alive=put(g.alive, jnp.ones_like(g.alive)))
    return placed, jnp.zeros((capacity,), bool).at[dst].set(True, mode="drop")
