"""The tile splatter (:func:`render`, :func:`render_tiles`) and its dense oracle
(:func:`render_reference`), one signature, INRIA's conventions."""

from .reference import accumulate_weights_reference, render_reference
from .render import accumulate_weights, next_capacity, render, render_tiles
from .types import RenderOutput

__all__ = ["RenderOutput", "accumulate_weights", "accumulate_weights_reference", "next_capacity",
           "render", "render_reference", "render_tiles"]
