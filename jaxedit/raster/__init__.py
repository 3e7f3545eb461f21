"""The tile splatter (:func:`render`, its jittable core :func:`render_tiles`) and its
dense oracle (:func:`render_reference`): one signature and :class:`RenderOutput`,
INRIA's conventions.
"""

from .reference import accumulate_weights_reference, render_reference
from .render import accumulate_weights, next_capacity, render, render_tiles
from .types import RenderOutput

__all__ = ["RenderOutput", "accumulate_weights", "accumulate_weights_reference", "next_capacity",
           "render", "render_reference", "render_tiles"]
