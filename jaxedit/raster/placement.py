"""Committing arrays where they already are, so that jit compiles one program per call site.

jit's cache key holds each argument's committedness (``jnp`` without a device:
uncommitted; ``device_put`` or computed from committed inputs: committed). Leaves that
drift between the two across calls compile the same program twice; :func:`commit` at
those calls removes the drift without moving anything.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def commit(tree):
    """``tree`` with each uncommitted JAX array committed to its device (an alias, no
    copy) and each NumPy array or scalar to the default device; committed or sharded arrays,
    tracers and Python scalars are returned as they are."""
    return jax.tree_util.tree_map(_commit_leaf, tree)


def _commit_leaf(x):
    if isinstance(x, (np.ndarray, np.generic)):
        x = jnp.asarray(x)
    if not isinstance(x, jax.Array) or isinstance(x, jax.core.Tracer) or x.committed:
        return x
    return jax.device_put(x, x.sharding)
