"""Room for a step: the tile splatter's intersection buffer and the Gaussians' capacity.

Both are static sizes (changing one recompiles); a step that finds one too small asks for
a redo (:mod:`jaxedit.train.step`). Outside jit, they are sized (:func:`size_buffer`),
planned (:func:`plan_room`) and grown (:func:`grow_for_redo`).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math

import jax
import jax.numpy as jnp
import numpy as np

from .. import densify as dens
from ..camera import Camera
from ..gaussians import Gaussians
from ..raster import binning, project
from ..raster.render import next_capacity, resolve_backend, tile_size
from .state import Batch, TrainState
from .step import train_step

log = logging.getLogger("jaxedit.train")


#: Headroom of the intersection buffer over what the views need now (:func:`size_buffer`).
HEADROOM = 1.5


@functools.partial(jax.jit, static_argnames=("tile",))
def _count_views(gaussians: Gaussians, cameras: Camera, tile: int):
    def one(cam):
        proj = project.project(gaussians, cam, sh_degree=0)
        return binning.count_intersections(proj, cam.width, cam.height, tile)

    return jax.lax.map(one, cameras)


def measure_intersections(gaussians: Gaussians, cameras: Camera) -> int:
    """Most tile intersections any of ``cameras`` (a batch, or one camera) needs, counted at
    the tile size of the compositor the training step renders with (``backend="auto"``)."""
    if not cameras.batch_shape:
        cameras = jax.tree_util.tree_map(lambda a: jnp.asarray(a)[None], cameras)
    tile = tile_size(resolve_backend("auto"))
    return int(jnp.max(_count_views(gaussians, cameras, tile=tile)))


def size_buffer(state: TrainState, cameras: Camera, *, headroom: float = HEADROOM) -> TrainState:
    """``state`` with a tile buffer of ``headroom`` x what ``cameras`` need now (outside jit)."""
    needed = measure_intersections(state.gaussians, cameras)
    cap = next_capacity(max(int(needed * headroom), 1))
    log.info("train: intersection buffer %d (views need up to %d)", cap, needed)
    return dataclasses.replace(state, max_intersections=cap)


def grow_for_redo(state: TrainState, metrics: dict) -> TrainState:
    """After a step that asked for a redo: a larger intersection buffer and/or capacity.

    Outside jit. The buffer at least doubles; the capacity grows to :data:`GROWTH_ROOM` x
    the slots needed, clamped to the hard cap (RuntimeError when it cannot grow).
    """
    if bool(metrics["overflow"]):
        needed = int(np.max(np.asarray(metrics["num_intersections"])))

        new = max(2 * state.max_intersections, next_capacity(int(needed * HEADROOM)))
        log.info("train: intersection buffer %d -> %d (a view needed %d)",
                 state.max_intersections, new, needed)
        state = dataclasses.replace(state, max_intersections=new)
    if bool(metrics["capacity_limited"]):
        needed = int(metrics["densify"]["slots_needed"])
        cap = state.config.densify.max_gaussians

        new_cap = dens.grown_capacity(state.capacity, GROWTH_ROOM * needed, cap)
        if new_cap <= state.capacity:
            raise RuntimeError(f"capacity {state.capacity} cannot grow to hold {needed}")
        log.info("train: capacity %d -> %d Gaussians (density control needed %d, cap %d)",
                 state.capacity, new_cap, needed, cap)
        state = grown(state, new_cap)
    return state


def grown(state: TrainState, capacity: int) -> TrainState:
    """``state`` with ``capacity`` slots (outside jit): the new slots dead, zeroed and never
    frozen."""
    g, opt_state, stats = dens.grow_state(state.gaussians, state.opt_state,
                                           state.densify_stats, capacity)
    frozen = state.frozen
    if frozen is not None and frozen.shape[0] < capacity:
        frozen = jnp.concatenate([frozen, jnp.zeros((capacity - frozen.shape[0],), bool)])
    return dataclasses.replace(state, gaussians=g, opt_state=opt_state, densify_stats=stats,
                               frozen=frozen)


#: On a capacity redo, the capacity grows to hold this many times the slots the step needed.
GROWTH_ROOM = 2

#: The capacity :func:`fit` gives a fresh densifying run, a multiple of its alive Gaussians.
ROOM = {"gpu": 4.0, "cpu": 2.0}


def default_room(platform: str | None = None) -> float:
    """:func:`fit`'s ``room`` on ``platform`` (default: JAX's default backend): more on a
    GPU, where a dead slot costs nothing measurable, than on a CPU, where it costs per step."""
    return ROOM["gpu"] if (platform or jax.default_backend()) == "gpu" else ROOM["cpu"]


def _will_densify(state: TrainState, room: float | None) -> bool:
    d = state.config.densify
    stop_at = d.stop_at if d.stop_at is not None else state.config.iterations // 2
    return room is not None and room > 1 and d.enabled and int(state.step) < stop_at


def planned_headroom(state: TrainState, room: float | None) -> float:
    """The buffer's headroom for a run about to start: :data:`HEADROOM`, times ``room`` when
    density control will grow the scene (each buffer growth is a recompile)."""
    return HEADROOM * room if _will_densify(state, room) else HEADROOM


def planned_capacity(state: TrainState, room: float | None) -> int:
    """The capacity :func:`plan_room` gives ``state`` (never less than it has)."""
    d = state.config.densify
    if not _will_densify(state, room):
        return state.capacity
    want = next_capacity(math.ceil(room * int(state.gaussians.num_alive())))
    return max(state.capacity, min(want, int(d.max_gaussians)))


def plan_room(state: TrainState, room: float | None) -> TrainState:
    """``state`` with ``room`` x its alive Gaussians of capacity, allocated before its first
    step, so density control rarely stops the compiled chunk to grow it.

    Outside jit. The capacity is on :func:`jaxedit.raster.render.next_capacity`'s ladder, so
    nearby sizes share programs; it is part of the checkpoint, so :func:`fit` plans only at
    step 0 and a resume stays bit-exact.
    """
    new_cap = planned_capacity(state, room)
    if new_cap <= state.capacity:
        return state
    log.info("train: capacity %d -> %d Gaussians (room planned for density control)",
             state.capacity, new_cap)
    return grown(state, new_cap)


def step_with_retry(state: TrainState, batch: Batch, key, *, max_retries: int = 8):
    """:func:`train_step`, growing buffer/capacity and redoing until the step is complete.

    Returns:
      (state, metrics) with ``metrics`` pulled to the host (NumPy scalars).
    """
    if state.max_intersections <= 0:
        state = size_buffer(state, batch.camera)
    for _ in range(max_retries + 1):
        new, metrics = train_step(state, batch, key)
        metrics = jax.device_get(metrics)
        if not bool(metrics["redo"]):
            return new, metrics
        state = grow_for_redo(state, metrics)
    raise RuntimeError(f"train step still incomplete after {max_retries} retries")
