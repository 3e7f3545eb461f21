"""The public render entry point (temporarily the dense oracle; the tile splatter follows)."""

from __future__ import annotations

import jax

from ..camera import Camera
from ..gaussians import Gaussians
from .reference import render_reference
from .types import RenderOutput


def render(gaussians: Gaussians, camera: Camera, *, background=None, sh_degree: int | None = None,
           near: float = 0.01, far: float = 1e10, means2d_delta: jax.Array | None = None,
           max_intersections: int | None = None) -> RenderOutput:
    """Render Gaussians (see :func:`render_reference` for the arguments)."""
    del max_intersections
    return render_reference(gaussians, camera, background=background, sh_degree=sh_degree,
                            near=near, far=far, means2d_delta=means2d_delta)
