"""The tile splatter and its dense oracle.

``render`` (the tile splatter) and ``render_reference`` (the dense oracle) share one
signature and :class:`RenderOutput`, with INRIA's conventions. ``render_tiles`` is the
pure jittable core, ``next_capacity`` its buffer ladder, ``accumulate_weights`` (oracle
``accumulate_weights_reference``) the per-Gaussian sum of blending weights times
per-pixel values, and ``placement.commit`` keeps one program per call site.
"""

from .reference import accumulate_weights_reference, render_reference
from .render import accumulate_weights, next_capacity, render, render_tiles
from .types import RenderOutput

__all__ = ["RenderOutput", "accumulate_weights", "accumulate_weights_reference", "next_capacity",
           "render", "render_reference", "render_tiles"]
