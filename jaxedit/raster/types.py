"""Output type shared by the tile splatter and the reference renderer."""

from __future__ import annotations

import dataclasses

import jax


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RenderOutput:
    """What one render returns (a leading batch axis when cameras are batched).

    Attributes:
      rgb: float [H, W, 3], composited colour over the background.
      alpha: float [H, W], accumulated opacity 1 - T_final.
      depth: float [H, W], expected depth sum_i w_i z_i / alpha (0 where alpha ~ 0).
      means2d: float [C, 2], projected means in pixels.
      radii: int [C], screen-space radius in pixels; 0 for culled/dead Gaussians.
      visible: bool [C], projected on screen and alive.
      num_intersections: int [], tile intersections the frame needs (0 for the oracle).
      overflow: bool [], the buffer was too small (only inside a caller's trace): the
        image is incomplete; redo it with at least ``num_intersections``.
    """

    rgb: jax.Array
    alpha: jax.Array
    depth: jax.Array
    means2d: jax.Array
    radii: jax.Array
    visible: jax.Array
    num_intersections: jax.Array
    overflow: jax.Array
