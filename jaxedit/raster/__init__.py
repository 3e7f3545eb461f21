"""The tile splatter and its dense oracle.

``render`` (the fast tile splatter) and ``render_reference`` (the dense,
obviously-correct oracle) share one signature and one output type
(:class:`RenderOutput`). INRIA's conventions throughout: pixel centres at
+0.5, 0.3 px blur, alpha clamped at 0.99, 1/255 skip, a pixel stops before the
Gaussian that would drop its transmittance below 1e-4.

* ``render(gaussians, camera, *, background, sh_degree, near, far,
  means2d_delta, max_intersections)``: outside a trace it sizes its own
  intersection buffer and never returns a frame with dropped pairs; inside a
  caller's jit/vmap pass ``max_intersections`` and check ``out.overflow``.
* ``render_tiles(..., capacity=n)``: the pure jittable core.
* ``next_capacity(needed)``: the buffer size ladder (for callers that manage it).
* ``accumulate_weights(gaussians, camera, values)`` (oracle:
  ``accumulate_weights_reference``): per Gaussian, sum over pixels of its blending
  weight T_i alpha_i times per-pixel values [H, W, F] -> [C, F] (relevance lifting).
* ``placement.commit(tree)``: arrays committed where they are, so that jit compiles one
  program per call site (the renderer's and the edit's training chunks).

The 2D-mean gradient (``means2d_delta``) times (W/2, H/2) is INRIA's NDC
densification statistic.
"""

from .reference import accumulate_weights_reference, render_reference
from .render import accumulate_weights, next_capacity, render, render_tiles
from .types import RenderOutput

__all__ = ["RenderOutput", "accumulate_weights", "accumulate_weights_reference", "next_capacity",
           "render", "render_reference", "render_tiles"]
