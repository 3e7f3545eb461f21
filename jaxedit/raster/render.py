"""The entry point: :func:`render` (tile splatter) and its jittable core :func:`render_tiles`:
project, bin into a fixed-capacity pair buffer, composite."""

from __future__ import annotations

import dataclasses
import functools
import logging
import math

import jax
import jax.numpy as jnp
import numpy as np

from ..camera import Camera
from ..errors import DataError
from ..gaussians import Gaussians, grow
from .placement import commit
from . import binning as B
from . import composite as CP
from . import pallas as PK
from . import project as P
from .reference import finish
from .types import RenderOutput

log = logging.getLogger(__name__)

#: Capacities are rounded up to 2^(k/STEPS_PER_OCTAVE) (then to a multiple of 1024).
STEPS_PER_OCTAVE = 4
#: :func:`render`'s ladder: a frame's cost follows its pairs, not its buffer size.
RENDER_STEPS_PER_OCTAVE = 1
MIN_CAPACITY = 1024
#: Headroom over the counted pairs when a capacity is (re)chosen.
HEADROOM = 1.15

#: Tile size of the XLA compositor: small tiles waste less work on a CPU.
TILE = 8
#: Tile size of the Pallas kernel: one program per tile, its pixels the vector lanes.
PALLAS_TILE = 16

BACKENDS = ("auto", "xla", "pallas")


def resolve_backend(backend: str, platform: str | None = None) -> str:
    """The compositor for ``backend`` on ``platform`` (default JAX's): ``auto`` is Pallas on a
    GPU, XLA elsewhere; ``pallas`` off a GPU runs the interpreter."""
    if backend not in BACKENDS:
        raise DataError("backend", f"must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if backend == "auto":
        return "pallas" if (platform or jax.default_backend()) == "gpu" else "xla"
    return backend


def tile_size(backend: str) -> int:
    """Binning/compositing tile size of a resolved backend."""
    return PALLAS_TILE if backend == "pallas" else TILE

def next_capacity(needed: int, steps_per_octave: int = STEPS_PER_OCTAVE) -> int:
    """Smallest buffer size holding ``needed`` pairs on the geometric ladder of
    ``steps_per_octave`` sizes per doubling, multiples of 1024."""
    needed = max(int(needed), MIN_CAPACITY)
    k = math.ceil(steps_per_octave * math.log2(needed) - 1e-9)
    cap = int(math.ceil(2.0 ** (k / steps_per_octave) / 1024.0) * 1024)
    while cap < needed:  # guard against rounding
        k += 1
        cap = int(math.ceil(2.0 ** (k / steps_per_octave) / 1024.0) * 1024)
    return cap


def render_capacity(needed: int) -> int:
    """:func:`next_capacity` on :func:`render`'s coarser ladder (:data:`RENDER_STEPS_PER_OCTAVE`)."""
    return next_capacity(needed, RENDER_STEPS_PER_OCTAVE)


def _composite(proj, bins, w, h, capacity, backend):
    """features float [H, W, 4] and transmittance [H, W] of the binned pairs."""
    feats = jnp.concatenate([proj.colors, proj.depths[:, None]], -1)
    tile = tile_size(backend)
    if backend == "pallas":
        return PK.composite(proj.means2d, proj.conics, proj.opacities, feats, bins, w, h, tile,
                            PK.use_interpreter())
    tiles_x, tiles_y = B.grid_shape(w, h, tile)
    block = CP.block_elements(jax.default_backend())
    gids, tile_of, first = CP.make_chunks(bins, tiles_x * tiles_y, capacity, tile,
                                          block_elements=block)
    return CP.composite(proj.means2d, proj.conics, proj.opacities, feats, gids, tile_of, first,
                        w, h, tile, block)


def _render_one(gaussians, camera, background, means2d_delta, near, far, *, capacity, sh_degree,
                backend):
    proj = P.project(gaussians, camera, sh_degree=sh_degree, near=near, far=far,
                     means2d_delta=means2d_delta)
    w, h = camera.width, camera.height
    bins = B.bin_gaussians(proj, w, h, capacity, tile_size(backend))
    f_img, t_img = _composite(proj, bins, w, h, capacity, backend)
    rgb, alpha, depth = finish(f_img, t_img, background, gaussians.means.dtype)
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, means2d=proj.means2d, radii=proj.radii,
                        visible=proj.visible, num_intersections=bins.num_intersections,
                        overflow=bins.overflow)


def render_tiles(gaussians: Gaussians, camera: Camera, *, capacity: int, background=None,
                 sh_degree: int | None = None, near: float = 0.01, far: float = 1e10,
                 means2d_delta: jax.Array | None = None, backend: str = "auto") -> RenderOutput:
    """Pure, jittable tile splatter with a static intersection ``capacity``; arguments as
    :func:`render`. The caller checks ``out.overflow`` (True: pairs were dropped)."""
    capacity = int(capacity)
    if capacity < 1:
        raise DataError("max_intersections", f"must be a positive int, got {capacity}")
    backend = resolve_backend(backend)
    sh_degree = P.check_sh_degree(gaussians, sh_degree)
    bg = None if background is None else jnp.asarray(background, gaussians.means.dtype)
    fn = functools.partial(_render_one, capacity=capacity, sh_degree=sh_degree, backend=backend)
    if camera.batch_shape:
        d_axis = None if means2d_delta is None else 0
        return jax.vmap(lambda cam, d: fn(gaussians, cam, bg, d, near, far),
                        in_axes=(0, d_axis))(camera, means2d_delta)
    return fn(gaussians, camera, bg, means2d_delta, near, far)


@functools.partial(jax.jit, static_argnames=("sh_degree", "tile"))
def _count(gaussians, camera, near, far, means2d_delta, sh_degree, tile):
    def one(cam, d):
        proj = P.project(gaussians, cam, sh_degree=0, near=near, far=far, means2d_delta=d)
        return B.count_intersections(proj, cam.width, cam.height, tile)

    if camera.batch_shape:
        d_axis = None if means2d_delta is None else 0
        return jnp.max(jax.vmap(one, in_axes=(0, d_axis))(camera, means2d_delta))
    return one(camera, means2d_delta)


_render_tiles_jit = jax.jit(render_tiles, static_argnames=("capacity", "sh_degree", "backend"))


def count_pairs(gaussians: Gaussians, camera: Camera, *, backend: str = "auto", near: float = 0.01,
                far: float = 1e10) -> int:
    """(Gaussian, tile) pairs a frame needs at ``backend``'s tile size (max over a batch)."""
    tile = tile_size(resolve_backend(backend))
    return int(_count(gaussians, camera, near, far, None, sh_degree=0, tile=tile))


def _background_only(gaussians: Gaussians, camera: Camera, background) -> RenderOutput:
    """The frame of a scene with nothing on screen, a splatted frame's shapes and dtypes."""
    batch = camera.batch_shape
    dtype = gaussians.means.dtype
    bg = jnp.zeros((3,), dtype) if background is None else jnp.asarray(background, dtype)
    pixels = batch + (camera.height, camera.width)
    per_gaussian = batch + (gaussians.capacity,)
    return RenderOutput(rgb=jnp.broadcast_to(bg, pixels + (3,)), alpha=jnp.zeros(pixels, dtype),
                        depth=jnp.zeros(pixels, dtype),
                        means2d=jnp.zeros(per_gaussian + (2,), dtype),
                        radii=jnp.zeros(per_gaussian, jnp.int32),
                        visible=jnp.zeros(per_gaussian, bool),
                        num_intersections=jnp.zeros(batch, jnp.int32),
                        overflow=jnp.zeros(batch, bool))


@functools.partial(jax.jit, static_argnames=("capacity",))
def _pad_slots(gaussians: Gaussians, means2d_delta, capacity: int):
    """``(gaussians, means2d_delta)`` padded to ``capacity`` slots in one program."""
    if means2d_delta is not None:
        widths = [(0, 0)] * means2d_delta.ndim
        widths[-2] = (0, capacity - gaussians.capacity)
        means2d_delta = jnp.pad(means2d_delta, widths)
    return grow(gaussians, capacity), means2d_delta


def _bucketed(gaussians: Gaussians, means2d_delta):
    """The scene padded with dead slots to its :func:`render_capacity` step, so scenes of
    nearby sizes share one program."""
    padded = render_capacity(gaussians.capacity)
    if padded == gaussians.capacity:
        return gaussians, means2d_delta
    return _pad_slots(gaussians, means2d_delta, capacity=padded)


def _unpadded(out: RenderOutput, n: int) -> RenderOutput:
    """``out`` with its per-Gaussian arrays cut back to the scene's ``n`` slots."""
    if out.means2d.shape[-2] == n:
        return out
    return dataclasses.replace(out, means2d=out.means2d[..., :n, :], radii=out.radii[..., :n],
                               visible=out.visible[..., :n])


def render(gaussians: Gaussians, camera: Camera, *, background=None, sh_degree: int | None = None,
           near: float = 0.01, far: float = 1e10, means2d_delta: jax.Array | None = None,
           max_intersections: int | None = None, backend: str = "auto") -> RenderOutput:
    """Render Gaussians with the exact tile splatter.

    Args:
      gaussians: the scene, capacity C (dead slots never contribute, zero gradient).
      camera: a Camera, or a batch of B along a leading axis (vmapped).
      background: float [3] colour behind the Gaussians (default black).
      sh_degree: active SH degree (<= the pytree's); default all.
      near, far: camera-space depth range kept.
      means2d_delta: optional zeros float [C, 2] ([B, C, 2]) added to the projected means;
        its gradient is the pixel-space 2D-mean gradient (x (W/2, H/2): INRIA's NDC one).
      max_intersections: static pair buffer size; required inside a caller's jit/vmap,
        else a starting size, grown as needed.
      backend: "auto" (Pallas on a GPU, XLA elsewhere), "xla" or "pallas".
    Returns:
      RenderOutput: rgb [H, W, 3], alpha [H, W], depth [H, W] (expected), means2d [C, 2],
      radii [C], visible [C], num_intersections, overflow (leading B when batched).
    Raises:
      DataError: under a trace without ``max_intersections``.
    """
    sh_degree = P.check_sh_degree(gaussians, sh_degree)
    backend = resolve_backend(backend)
    # One program whatever the caller passes: an explicit background, arrays committed
    # where they are (a mix of fresh and trained leaves would compile again).
    background = jnp.zeros(3, gaussians.means.dtype) if background is None else \
        jnp.asarray(background, gaussians.means.dtype)
    gaussians, camera, background, means2d_delta = commit(
        (gaussians, camera, background, means2d_delta))
    kwargs = dict(background=background, sh_degree=sh_degree, near=near, far=far,
                  means2d_delta=means2d_delta, backend=backend)
    if gaussians.capacity == 0:  # an empty scene (a PLY without vertices): only background
        return _background_only(gaussians, camera, background)
    n = gaussians.capacity
    gaussians, means2d_delta = _bucketed(gaussians, means2d_delta)
    kwargs["means2d_delta"] = means2d_delta
    try:
        needed = int(_count(gaussians, camera, near, far, means2d_delta, sh_degree=sh_degree,
                            tile=tile_size(backend)))
    except jax.errors.ConcretizationTypeError:
        needed = None
    if needed == 0:  # nothing alive on screen (all dead or culled): the frame is the background
        return _unpadded(_background_only(gaussians, camera, background), n)
    if needed is None:  # under the caller's jit / vmap: their buffer, their overflow check
        if max_intersections is None:
            raise DataError("max_intersections", "render() inside jit/vmap needs a static "
                            "max_intersections (and a check of out.overflow)")
        return _unpadded(render_tiles(gaussians, camera, capacity=max_intersections, **kwargs), n)

    if max_intersections is not None and int(max_intersections) >= needed:
        cap = int(max_intersections)  # the caller's size, when it holds the frame
    else:
        cap = render_capacity(needed * HEADROOM)
    while True:
        out = _render_tiles_jit(gaussians, camera, capacity=cap, **kwargs)
        overflow = bool(np.any(np.asarray(out.overflow)))
        if not overflow:
            return _unpadded(out, n)
        need = int(np.max(np.asarray(out.num_intersections)))
        new = render_capacity(max(need * HEADROOM, 2 * cap))
        log.warning("render: intersection buffer overflowed (%d > %d), re-rendering with %d",
                    need, cap, new)
        cap = new


@functools.partial(jax.jit, static_argnames=("capacity", "sh_degree"))
def _weights_one(gaussians, camera, values, near, far, *, capacity, sh_degree):
    proj = P.project(gaussians, camera, sh_degree=sh_degree, near=near, far=far)
    w, h = camera.width, camera.height
    bins = B.bin_gaussians(proj, w, h, capacity, TILE)
    tiles_x, tiles_y = B.grid_shape(w, h, TILE)
    block = CP.block_elements(jax.default_backend())
    gids, tile_of, first = CP.make_chunks(bins, tiles_x * tiles_y, capacity, TILE,
                                          block_elements=block)
    return CP.accumulate_weights(proj.means2d, proj.conics, proj.opacities, values, gids,
                                 tile_of, first, w, h, TILE, block)


def accumulate_weights(gaussians: Gaussians, camera: Camera, values, *, near: float = 0.01,
                       far: float = 1e10) -> jax.Array:
    """Per Gaussian, sum over pixels (and views) of T_i alpha_i times ``values`` float
    [H, W, F] ([B, H, W, F] for a batch of cameras): float [C, F], 0 for Gaussians never
    drawn. No gradient; outside a trace only."""
    values = jnp.asarray(values, gaussians.means.dtype)
    if camera.batch_shape:
        total = jnp.zeros((gaussians.capacity, values.shape[-1]), values.dtype)
        for i in range(camera.batch_shape[0]):
            total = total + accumulate_weights(gaussians, camera[i], values[i], near=near, far=far)
        return total
    if values.shape[:2] != (camera.height, camera.width) or values.ndim != 3:
        raise DataError("values", f"need float [{camera.height}, {camera.width}, F], "
                                  f"got {tuple(values.shape)}")
    zero = jnp.zeros((gaussians.capacity, values.shape[-1]), values.dtype)
    if gaussians.capacity == 0:
        return zero
    needed = int(_count(gaussians, camera, near, far, None, sh_degree=0, tile=TILE))
    if needed == 0:
        return zero
    return _weights_one(gaussians, camera, values, near, far,
                        capacity=next_capacity(needed), sh_degree=0)
