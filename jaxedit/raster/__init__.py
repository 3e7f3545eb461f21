"""The tile splatter and its dense oracle.

``render`` (the fast tile splatter) and ``render_reference`` (the dense,
obviously-correct oracle) share one signature and one output type.
"""

from .reference import render_reference
from .render import render
from .types import RenderOutput

__all__ = ["RenderOutput", "render", "render_reference"]
