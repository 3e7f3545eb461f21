"""The statistics of density control: one render's :class:`RenderAux`, summed into
:class:`DensifyStats` between maintenance steps (:func:`init_stats`, :func:`accumulate`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp


class RenderAux(NamedTuple):
    """What densification needs from one training render.

    Attributes:
      grad_means2d: float [C, 2], loss gradient w.r.t. the projected means, in pixels.
      radii: float or int [C], screen-space radius in pixels (0 if not drawn).
      visible: bool [C], drawn in this view.
      image_size: float [2], (width, height) in pixels.
    """

    grad_means2d: jax.Array
    radii: jax.Array
    visible: jax.Array
    image_size: jax.Array


def render_aux(grad_means2d, out, width: int, height: int) -> RenderAux:
    """A :class:`RenderAux` from a render output ``out`` and its 2D-mean gradient [C, 2]."""
    return RenderAux(grad_means2d=grad_means2d, radii=out.radii, visible=out.visible,
                     image_size=jnp.asarray([width, height], jnp.float32))


class DensifyStats(NamedTuple):
    """Running statistics between maintenance steps (all [C] per slot).

    Attributes:
      grad_sum: float [C], sum over views of the NDC 2D-mean gradient norm.
      count: int32 [C], number of views in which the Gaussian was drawn.
      max_radius: float [C], largest screen radius as a fraction of max(W, H).
      last_culled: int32 [], n: how many were culled at the previous maintenance step.
    """

    grad_sum: jax.Array
    count: jax.Array
    max_radius: jax.Array
    last_culled: jax.Array


def init_stats(capacity: int) -> DensifyStats:
    """Zero statistics for ``capacity`` slots (nothing culled before)."""
    return DensifyStats(grad_sum=jnp.zeros((capacity,), jnp.float32),
                        count=jnp.zeros((capacity,), jnp.int32),
                        max_radius=jnp.zeros((capacity,), jnp.float32),
                        last_culled=jnp.zeros((), jnp.int32))


def accumulate(stats: DensifyStats, aux: RenderAux) -> DensifyStats:
    """Add one view's NDC gradient norms, visibility and screen radii to ``stats``."""
    ndc = aux.grad_means2d * (0.5 * aux.image_size)  # pixel gradient -> NDC (INRIA's units)
    norm = jnp.sqrt(jnp.sum(ndc * ndc, axis=-1))
    vis = aux.visible.astype(bool)
    radius = aux.radii.astype(jnp.float32) / jnp.max(aux.image_size)
    return DensifyStats(grad_sum=stats.grad_sum + jnp.where(vis, norm, 0.0),
                        count=stats.count + vis.astype(jnp.int32),
                        max_radius=jnp.maximum(stats.max_radius, jnp.where(vis, radius, 0.0)),
                        last_culled=stats.last_culled)
