"""The key of every editor call, a pure ``fold_in`` chain from a run's key, so seeded, resumed
and asynchronous runs draw the same keys."""

from __future__ import annotations

import math

import jax

from ..errors import DataError

_RATIO_QUANTUM = 1_000_000  # ratios enter keys as round(r * 1e6)


def quantize_ratio(ratio: float) -> int:
    """The integer round(ratio * 1e6) used to seed and memoise per-ratio work."""
    r = float(ratio)
    if not math.isfinite(r) or r < 0.0 or r > 4000.0:
        raise DataError("ratio", f"must be a finite number in [0, 1], got {ratio!r}")
    return int(round(r * _RATIO_QUANTUM))


def view_key(run_key: jax.Array, view_index: int, ratio: float, iteration: int) -> jax.Array:
    """``run_key`` folded with (view index, :func:`quantize_ratio` of ratio, iteration), so a
    ratio read back from JSON gives the same key."""
    if int(view_index) < 0 or int(iteration) < 0:
        raise DataError("view_key", f"view index and iteration must be >= 0, got "
                        f"{view_index}, {iteration}")
    k = jax.random.fold_in(run_key, int(view_index))
    k = jax.random.fold_in(k, quantize_ratio(ratio))
    return jax.random.fold_in(k, int(iteration))


def edit_key(edit_stream: jax.Array, view: int, iteration: int) -> jax.Array:
    """The key of the ``iteration``-th edit of ``view`` in a subtask's ``edit_stream``."""
    if int(view) < 0 or int(iteration) < 0:
        raise DataError("edit_key", f"view and iteration must be >= 0, got {view}, {iteration}")
    return jax.random.fold_in(jax.random.fold_in(edit_stream, int(view)), int(iteration))
