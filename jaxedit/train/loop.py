"""The training loop: data order, compiled chunks of steps, the divergence guard, :func:`fit`.
Step ``s``'s view and key depend on ``(base key, s)`` only, so resuming is bit-identical."""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..camera import Camera
from ..errors import DataError
from .room import default_room, grow_for_redo, plan_room, planned_headroom, size_buffer
from .state import Batch, TrainState, key_data
from .step import GUARDED, apply_step

# -- data order --

def _stream_keys(base_data):
    base = jax.random.wrap_key_data(base_data)
    return jax.random.fold_in(base, 0), jax.random.fold_in(base, 1)


def epoch_view(key: jax.Array, step, num_views: int):
    """Entry ``step % N`` of a permutation of ``num_views`` (static) seeded by ``key``
    and the epoch ``step // N``: the data order of every trainer."""
    epoch, i = step // num_views, step % num_views
    return jax.random.permutation(jax.random.fold_in(key, epoch), num_views)[i]


def _view_and_key(base_key_data, step, num_views: int):
    k_views, k_steps = _stream_keys(base_key_data)
    view = epoch_view(k_views, step, num_views)
    return view.astype(jnp.int32), jax.random.fold_in(k_steps, step)


view_and_key = jax.jit(_view_and_key, static_argnums=2)
view_and_key.__doc__ = """(view index int32 [], step key) of 0-based ``step`` among ``num_views`` (static).

A pure function of (base key data uint32 [2], step): the views follow a fresh
seeded permutation every epoch of ``num_views`` steps.
"""


def unit_float(image) -> jax.Array:
    """float32 in [0, 1] of a uint8 image (times 1/255, as OpenImageIO reads the file) or
    a float one as it is; training images may stay uint8 on the device."""
    image = jnp.asarray(image)
    if image.dtype == jnp.uint8:
        return image.astype(jnp.float32) * jnp.float32(1.0 / 255.0)
    return image


@jax.jit
def _select(images, cameras, base_key_data, step):
    view, key = _view_and_key(base_key_data, step, images.shape[0])
    return Batch(image=unit_float(images[view]), camera=cameras[view], view=view), key


def select_batch(images, cameras: Camera, base_key_data, step) -> tuple[Batch, jax.Array]:
    """(Batch of 0-based ``step``, its key) from images [N, H, W, 3] and cameras [N]."""
    return _select(jnp.asarray(images), cameras, jnp.asarray(base_key_data),
                   jnp.asarray(step, jnp.int32))


# -- chunks of steps on the device --

#: Steps per compiled chunk in :func:`fit` (the host acts only between chunks).
CHUNK = 16


def scan_steps(step, carry, n_active, *, length: int, after=None):
    """Up to ``length`` steps of ``step`` in one ``lax.scan``, ending early on a redo or a stop.

    Steps past ``n_active`` or after a redo/stop are skipped with blank metrics; a step
    asking for a redo must leave its carry unchanged.

    Args:
      step: ``(carry, i) -> (carry, metrics)``, ``i`` int32 [] the index in the chunk;
        ``metrics`` a dict of arrays holding a bool ``redo``.
      carry: the pytree the steps advance.
      n_active: int32 [], steps wanted (<= ``length``).
      length: static scan length.
      after: optional ``(carry, metrics, i) -> (metrics, stop)`` after every index; its
        stop counts only for a step that ran.
    Returns:
      (carry, metrics): metrics stacked [length] plus ``ran`` (bool [length]); a
      completed step has ``ran & ~redo``.
    """
    blank = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype),
                                   jax.eval_shape(step, carry, jnp.zeros((), jnp.int32))[1])

    def body(state, i):
        inner, stopped = state
        run = (i < n_active) & ~stopped
        inner, metrics = jax.lax.cond(run, step, lambda c, _: (c, blank), inner, i)
        stop = metrics["redo"]
        if after is not None:
            metrics, extra_stop = after(inner, metrics, i)
            stop = stop | extra_stop
        return (inner, stopped | (run & stop)), dict(metrics, ran=run)

    (carry, _), metrics = jax.lax.scan(body, (carry, jnp.zeros((), bool)),
                                       jnp.arange(length, dtype=jnp.int32))
    return carry, metrics


def _train_chunk(state: TrainState, images, cameras: Camera, n_active, *, length: int):
    """Up to ``length`` train steps in one :func:`scan_steps`, views and keys chosen on device.

    Args:
      images: float [N, H, W, 3] in [0, 1] or uint8, on the device.
      cameras: Camera batch [N].
      n_active: int32 [], steps wanted (<= ``length``).
    Returns:
      (state, metrics): per-step metrics stacked [length] plus ``ran``.
    """
    num_views = images.shape[0]

    def one(st, _):
        view, key = _view_and_key(st.key, st.step, num_views)
        return apply_step(st, Batch(image=unit_float(images[view]), camera=cameras[view],
                                    view=view), key)

    return scan_steps(one, state, n_active, length=length)


train_chunk = jax.jit(_train_chunk, static_argnames=("length",))


def put_image(images: jax.Array, index, image) -> jax.Array:
    """``images`` [N, H, W, 3] with view ``index`` replaced by ``image`` [H, W, 3]; the
    buffer is donated, so the other views are not copied where donation is supported."""
    return _put_image(images, jnp.asarray(index, jnp.int32), jnp.asarray(image, images.dtype))


@functools.partial(jax.jit, donate_argnums=0)
def _put_image(images, index, image):
    return images.at[index].set(image)


#: Steps averaged by the divergence guard's loss rule.
GUARD_WINDOW = 16


def divergence(step0: int, metrics: dict, *, history=None, max_loss: float | None = 0.75,
               window: int = GUARD_WINDOW) -> str | None:
    """Why the steps of a chunk diverged, or None (host side, on fetched metrics).

    Args:
      step0: the step count before the chunk.
      metrics: per-step metrics of the chunk's completed steps (NumPy, [n]).
      history: the run's losses so far, this chunk's included (default: the chunk's).
      max_loss: bound on the loss averaged over the last ``window`` steps.
      window: steps averaged by the loss rule.
    Returns:
      a one-line reason naming the first bad step and quantity.
    """
    finite = metrics["finite"]
    for i in range(len(metrics["loss"])):
        for name in GUARDED:
            if not bool(finite[name][i]):
                what = "the loss" if name == "loss" else f"parameter {name}"
                return f"step {step0 + i + 1}: training diverged: {what} is not finite"
    n = len(metrics["loss"])
    losses = np.asarray(metrics["loss"] if history is None else history, np.float64)
    if max_loss is not None and n:
        recent = losses[-window:]
        if len(recent) >= min(window, 4) and recent.mean() > max_loss:
            return (f"step {step0 + n}: training diverged: the loss averaged "
                    f"{recent.mean():.3g} over {len(recent)} steps (more than {max_loss})")
    return None


# -- progress events (the library never draws) --

class TrainProgress(NamedTuple):
    """One progress event of :func:`fit`, sent after every chunk: ``desc``, ``step`` of
    ``total``, the last step's ``loss`` and ``psnr``, and alive ``gaussians``."""

    desc: str
    step: int
    total: int
    loss: float
    psnr: float
    gaussians: int



def _jsonable(metrics: dict) -> dict:
    out = {}
    for k, v in metrics.items():
        if isinstance(v, dict):
            out[k] = _jsonable(v)
        else:
            a = np.asarray(v)
            out[k] = a.item() if a.ndim == 0 else a.tolist()
    return out


def fit(state: TrainState, images, cameras: Camera, *, key=None, iterations: int | None = None,
        log: Callable[[dict], None] | None = None, log_every: int = 10,
        checkpoint: Callable[[TrainState], None] | None = None,
        checkpoint_every: int | None = None, progress: Callable[[TrainProgress], None] | None = None,
        callback: Callable | None = None,
        should_stop: Callable[[int, list], bool] | None = None, desc: str = "train",
        chunk: int = CHUNK, max_loss: float | None = 0.75,
        room: float | None | str = "auto") -> TrainState:
    """Train until ``state.step == iterations`` (default ``state.config.iterations``).

    Steps run in compiled chunks of up to ``chunk`` (:func:`train_chunk`).

    Args:
      state: TrainState, fresh from :func:`init_state` or from a checkpoint.
      images: float [N, H, W, 3] in [0, 1] or uint8 (kept uint8 on the device), NumPy or JAX.
      cameras: Camera batch [N] matching ``images``.
      key: base PRNG key; default: the one in ``state``.
      iterations: stop at this step count (default: the config's).
      log: ``log(record)`` every ``log_every`` steps, at the last and at density-control steps.
      checkpoint: ``checkpoint(state)`` every ``checkpoint_every`` steps and at the end.
      progress: ``progress(TrainProgress)`` at the start and after every chunk.
      callback: ``callback(state, metrics)`` after every chunk (NumPy metrics [n]).
      should_stop: ``should_stop(step, loss_history) -> bool`` before every chunk.
      chunk: steps per compiled chunk (1: the host sees every step).
      max_loss: divergence guard threshold (:func:`divergence`; None: non-finite only).
      room: capacity of a fresh densifying run, x its alive Gaussians (None: grown on
        demand; "auto": :func:`default_room`). Changes only speed and the floats' last bits.
    Returns:
      the final TrainState.
    Raises:
      DataError: bad inputs, or the run diverged (the message names the step and
        quantity); nothing of the bad chunk is checkpointed.
    """
    if key is not None:
        state = dataclasses.replace(state, key=key_data(key))
    total = state.config.iterations if iterations is None else int(iterations)
    if chunk < 1:
        raise DataError("chunk", f"must be >= 1, got {chunk}")
    images = jnp.asarray(images)
    if images.dtype != jnp.uint8:
        images = images.astype(state.gaussians.means.dtype)
    if images.ndim != 4 or images.shape[-1] != 3:
        raise DataError("images", f"expected float [N, H, W, 3], got {tuple(images.shape)}")
    if len(cameras) != images.shape[0]:
        raise DataError("cameras", f"{len(cameras)} cameras for {images.shape[0]} images")
    if (cameras.width, cameras.height) != (images.shape[2], images.shape[1]):
        raise DataError("cameras", f"cameras are {cameras.width}x{cameras.height} but images are "
                                   f"{images.shape[2]}x{images.shape[1]}")
    if images.shape[0] == 0:
        raise DataError("images", "no training views")
    if state.config.camera_opt and state.cameras.num_views != images.shape[0]:
        raise DataError("cameras", f"{images.shape[0]} training views but the state learns "
                                   f"pose corrections for {state.cameras.num_views}")
    cameras = jax.tree_util.tree_map(jnp.asarray, cameras)
    room = default_room() if room == "auto" else room
    headroom = planned_headroom(state, room if int(state.step) == 0 else None)
    if int(state.step) == 0:
        state = plan_room(state, room)
    if state.max_intersections <= 0:
        state = size_buffer(state, cameras, headroom=headroom)
    if checkpoint is None:
        checkpoint_every = None
    step = int(jax.device_get(state.step))
    if progress is not None:
        progress(TrainProgress(desc, step, total, float("nan"), float("nan"),
                               int(state.gaussians.num_alive())))
    history: list[float] = []
    t0 = time.monotonic()
    steps_done = 0

    def launch(st, at):
        """Dispatch the chunk starting at step ``at`` without reading it."""
        n = min(chunk, total - at)
        if checkpoint_every:
            n = min(n, checkpoint_every - at % checkpoint_every)
        new, metrics = train_chunk(st, images, cameras, jax.device_put(np.int32(n)),
                                   length=chunk)
        return new, metrics, n

    ahead = None
    if step < total and not (should_stop is not None and should_stop(step, history)):
        ahead = launch(state, step)
    while ahead is not None:
        new, metrics, n = ahead
        # Dispatched before this chunk is read; dropped if it does not complete
        ahead = launch(new, step + n) if step + n < total else None
        metrics = jax.device_get(metrics)
        completed = metrics["ran"] & ~metrics["redo"]
        k = int(np.sum(completed))
        steps = jax.tree_util.tree_map(lambda a: a[:k], metrics)
        recent = history[-GUARD_WINDOW:] + [float(x) for x in steps["loss"]]
        reason = divergence(step, steps, history=recent, max_loss=max_loss,
                            window=GUARD_WINDOW)
        if reason is not None:
            raise DataError(desc, reason)
        state = new
        for i in range(k):
            history.append(float(steps["loss"][i]))
            done = step + i + 1
            if log is not None and (done % log_every == 0 or done == total
                                    or bool(steps["densify"]["refined"][i])):
                record = dict(step=done, elapsed_s=time.monotonic() - t0,
                              capacity=state.capacity,
                              max_intersections=state.max_intersections,
                              **_jsonable(jax.tree_util.tree_map(lambda a: a[i], steps)))
                log(record)
        step += k
        steps_done += k
        if k < n:  # a step asked for more room: grow, redo it
            state = grow_for_redo(state, jax.tree_util.tree_map(lambda a: a[k], metrics))
            ahead = None
        if k:
            if progress is not None:
                progress(TrainProgress(desc, step, total, float(steps["loss"][-1]),
                                       float(steps["psnr"][-1]),
                                       int(steps["num_gaussians"][-1])))
            if callback is not None:
                callback(state, steps)
            if checkpoint_every and step % checkpoint_every == 0:
                checkpoint(state)
        if should_stop is not None and step < total and should_stop(step, history):
            break
        if ahead is None and step < total:
            ahead = launch(state, step)
    if checkpoint is not None and steps_done and not (checkpoint_every
                                                      and step % checkpoint_every == 0):
        checkpoint(state)
    return state
