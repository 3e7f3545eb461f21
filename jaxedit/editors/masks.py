"""Relevance masks: how much an instruction changes each pixel, as a mask. Shared by the
protocol (:mod:`.base`), the simulated editor and the JAX InstructPix2Pix's relevance
(:meth:`.jax_ip2p.JaxIP2PEditor.relevance`), in a module of its own so that none of them imports another."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .simulated_targets import blur


def relevance_mask(difference, *, sigma: float = 1.5, threshold: float = 0.3) -> jax.Array:
    """A difference map (how much an instruction changes each pixel) as a relevance mask.

    Args:
      difference: float [H, W] or [B, H, W], >= 0 (e.g. |target - original| or
        |eps(e) - eps(E(""))|).
      sigma: blur in pixels; threshold: on the map normalised to [0, 1] per view.
    Returns:
      float32 of the input's shape, 1 where relevant, else 0 (all 0 for a view with no
      difference).
    """
    d = jnp.asarray(difference, jnp.float32)
    single = d.ndim == 2
    d = d[None] if single else d
    peak = jnp.max(d, axis=(1, 2), keepdims=True)
    # blur works on [H, W, C]: the views ride along as channels.
    d = jnp.moveaxis(blur(jnp.moveaxis(d / jnp.maximum(peak, 1e-12), 0, -1), sigma), -1, 0)
    peak = jnp.max(d, axis=(1, 2), keepdims=True)
    m = ((d >= threshold * peak) & (peak > 1e-6)).astype(jnp.float32)
    return m[0] if single else m
