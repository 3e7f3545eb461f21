"""The render background: its names (``TrainConfig.background``) and their colours.

One table, so that a name and an RGB triple are turned into each other in one place.
"""

from __future__ import annotations

from ..errors import DataError

#: The solid backgrounds by name; "random" (a colour per training step) has no one colour.
SOLID_BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}


def background_rgb(name: str) -> tuple[float, float, float] | None:
    """RGB of a solid background name; None for "random"."""
    return SOLID_BACKGROUNDS.get(name)


def background_name(rgb) -> str:
    """The name of a solid background colour (white or black); DataError for another one."""
    rgb = tuple(float(c) for c in rgb)
    for name, value in SOLID_BACKGROUNDS.items():
        if rgb == value:
            return name
    raise DataError("background", f"the trainer supports white or black, got {rgb}")
