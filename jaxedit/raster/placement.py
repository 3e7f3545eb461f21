"""Committing arrays where they already are, so that jit compiles one program per call site
(jit's cache key holds each argument's committedness)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def commit(tree):
    """``tree`` with each uncommitted JAX array committed to its device (no copy), NumPy arrays
    to the default device; other leaves as they are."""
    return jax.tree_util.tree_map(_commit_leaf, tree)


def _commit_leaf(x):
    if isinstance(x, (np.ndarray, np.generic)):
        x = jnp.asarray(x)
    if not isinstance(x, jax.Array) or isinstance(x, jax.core.Tracer) or x.committed:
        return x
    return jax.device_put(x, x.sharding)
