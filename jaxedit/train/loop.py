"""The training loop: data order, compiled chunks of steps, the divergence guard, :func:`fit`.

The view of step ``s`` and its PRNG key are pure functions of ``(base key, s)``
(a seeded permutation per epoch), so a run resumed from any checkpoint ends
with bit-identical Gaussians, whatever the chunking. :func:`train_chunk` runs up
to ``length`` steps in one ``lax.scan`` with the views picked from the
device-resident images, density control included: the host acts only between
chunks (logs, checkpoints, the guard, growing the room after a redo).
"""

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

# --------------------------------------------------------------------------------------
# Data order
# --------------------------------------------------------------------------------------

def _stream_keys(base_data):
    base = jax.random.wrap_key_data(base_data)
    return jax.random.fold_in(base, 0), jax.random.fold_in(base, 1)


def epoch_view(key: jax.Array, step, num_views: int):
    """The view of 0-based ``step`` among ``num_views`` (static): entry ``step % N`` of a
    permutation of the views seeded by ``key`` (typed) and the epoch ``step // N``.

    The one data order of every trainer: :func:`fit`'s and the edit's subtasks
    (:func:`jaxedit.edit.subtask.step_chunk`), each with its own key."""
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
    """float32 in [0, 1] of a uint8 image (times 1/255, bit for bit OpenImageIO's float read
    of the same file) or a float one (as it is): the training images may stay uint8 on the
    device, a quarter of float32's memory."""
    image = jnp.asarray(image)
    if image.dtype == jnp.uint8:
        return image.astype(jnp.float32) * jnp.float32(1.0 / 255.0)
    return image


@jax.jit
def _select(images, cameras, base_key_data, step):
    view, key = _view_and_key(base_key_data, step, images.shape[0])
    return Batch(image=unit_float(images[view]), camera=cameras[view], view=view), key


def select_batch(images, cameras: Camera, base_key_data, step) -> tuple[Batch, jax.Array]:
    """(Batch of 0-based ``step``, its key) from images [N, H, W, 3] and cameras [N].

    The view is the ``step % N``-th entry of a seeded permutation of epoch ``step // N``.
    """
    return _select(jnp.asarray(images), cameras, jnp.asarray(base_key_data),
                   jnp.asarray(step, jnp.int32))


# --------------------------------------------------------------------------------------
# Chunks of steps on the device
# --------------------------------------------------------------------------------------

#: Steps per compiled chunk in :func:`fit` (the host acts only between chunks).
CHUNK = 16


def scan_steps(step, carry, n_active, *, length: int, after=None):
    """Up to ``length`` steps of ``step`` in one ``lax.scan``, ending early on a redo or a stop.

    Step ``i`` runs when ``i < n_active`` and no earlier step of the chunk asked
    for a redo or a stop; the others are skipped (``lax.cond``) with blank
    metrics, so one compiled chunk serves every count. A step that asks for a
    redo must leave its carry as it was (see :func:`jaxedit.train.step.train_step`), so the
    returned carry is the one after the completed steps.

    Args:
      step: ``(carry, i) -> (carry, metrics)``, ``i`` int32 [] the index in the
        chunk; ``metrics`` is a dict of arrays holding a bool ``redo``.
      carry: the pytree the steps advance.
      n_active: int32 [], steps wanted (<= ``length``).
      length: static scan length.
      after: optional ``(carry, metrics, i) -> (metrics, stop)``, evaluated after
        every index: extends the metrics and says whether the chunk ends after
        this step (e.g. a loss plateau); its stop counts only for a step that ran.
    Returns:
      (carry, metrics): the metrics stacked over the chunk ([length] each) plus
      ``ran`` (bool [length]: the step was attempted); a completed step has
      ``ran & ~redo``.
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
    """Up to ``length`` train steps in one ``lax.scan`` (:func:`scan_steps`), views and keys
    chosen on the device.

    Args:
      state: TrainState.
      images: float [N, H, W, 3] in [0, 1] or uint8 training images (on the device).
      cameras: Camera batch [N].
      n_active: int32 [], steps wanted (<= ``length``).
      length: static scan length.
    Returns:
      (state, metrics): :func:`jaxedit.train.step.train_step`'s metrics stacked over the chunk
      ([length] each) plus ``ran``; a completed step has ``ran & ~redo``.
    """
    num_views = images.shape[0]

    def one(st, _):
        view, key = _view_and_key(st.key, st.step, num_views)
        return apply_step(st, Batch(image=unit_float(images[view]), camera=cameras[view],
                                    view=view), key)

    return scan_steps(one, state, n_active, length=length)


train_chunk = jax.jit(_train_chunk, static_argnames=("length",))


def put_image(images: jax.Array, index, image) -> jax.Array:
    """``images`` [N, H, W, 3] with view ``index`` replaced by ``image`` [H, W, 3], in place.

    The buffer is donated, so an edited view lands in the device-resident
    training set without copying the other views (where the platform supports
    donation; elsewhere it is a copy, with the same result).
    """
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
      max_loss: the loss averaged over the last ``window`` steps may not exceed
        this. A photometric loss is at most ~1.2 (L1 <= 1, 1 - SSIM <= 2); an
        untrained scene sits near 0.3-0.4 and an opacity reset returns there, a
        render unrelated to its target (the GPU failure of issue #18) at ~1.
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


# --------------------------------------------------------------------------------------
# Progress events (the library never draws: callers render them, see experiments/progress.py)
# --------------------------------------------------------------------------------------

class TrainProgress(NamedTuple):
    """One progress event of :func:`fit`, sent after every chunk of steps.

    Attributes:
      desc: the run's label (``fit(desc=...)``).
      step: steps done so far; total: the step the run ends at.
      loss, psnr: the last step's training loss and PSNR; gaussians: alive Gaussians.
    """

    desc: str
    step: int
    total: int
    loss: float
    psnr: float
    gaussians: int


# --------------------------------------------------------------------------------------
# The loop
# --------------------------------------------------------------------------------------

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

    The images live on the device and the steps run in compiled chunks of up to
    ``chunk`` (:func:`train_chunk`); the host acts only between chunks (logs,
    progress, checkpoints, the divergence guard, growing the buffer or capacity),
    reading the chunk's metrics back at once. Chunking does not change the
    result: the view and key of step s depend only on (key, s).

    Args:
      state: TrainState (fresh from :func:`init_state` or from :func:`load_checkpoint`).
      images: float [N, H, W, 3] training images in [0, 1], or uint8 ones (kept uint8 on
        the device, each step's view converted; :attr:`jaxedit.io.Dataset.pixels`), NumPy
        or JAX; the caller may pass a different array of the same shape to each call.
      cameras: Camera batch [N] matching ``images``.
      key: base PRNG key; default: the one in ``state`` (set by :func:`init_state`).
        The view and key of step s depend only on (key, s).
      iterations: stop at this step count (default: the config's).
      log: ``log(record)`` with a JSON-ready metrics record (step, elapsed seconds,
        capacity, buffer size and the step's metrics) every ``log_every`` steps, at
        the last step and at every density-control step; None: no records.
      checkpoint: ``checkpoint(state)`` every ``checkpoint_every`` steps (chunks end
        on those steps) and at the end of a run that took a step; None: never.
        The library writes no files: :mod:`jaxedit.pipelines.rundir` has the run
        directory's writers (a JSONL log, rolling ``ckpt_<step>.npz`` files).
      progress: ``progress(TrainProgress)`` after every chunk (and once at the start),
        e.g. to draw a bar; None: silent. The library itself never prints.
      callback: ``callback(state, metrics)`` after every chunk: the state at its
        end and the metrics of its completed steps (NumPy arrays [n]).
      should_stop: ``should_stop(step, loss_history) -> bool`` checked before
        every chunk; True ends the loop early (a final checkpoint is still written).
      chunk: steps per compiled chunk (1: the host sees every step).
      max_loss: divergence guard threshold (see :func:`divergence`; None: only
        non-finite values stop the run).
      room: a fresh run (step 0) that will densify starts with ``room`` x its alive
        Gaussians of capacity (:func:`plan_room`; None: as given, grown on demand;
        "auto": :func:`default_room`), and an unsized buffer ``room`` x the usual
        headroom (:func:`planned_headroom`). The capacity changes only the speed and the
        last bits of the floats (reductions over differently sized arrays).
    Returns:
      the final TrainState.
    Raises:
      DataError: the run diverged (a non-finite loss or parameter, or an exploding
        loss); the message names the step and the quantity. Nothing of the bad
        chunk is checkpointed, so the newest checkpoint is the last good state.
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
        """Dispatch the chunk that starts at step ``at`` (asynchronous: nothing is read)."""
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
        # The next chunk goes to the device before this one is read, so the device
        # never waits for the host's logging and checks. It assumes this chunk
        # completes; when it does not (a redo, a stop, divergence) it is dropped.
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
        if k < n:  # a step asked for more room: grow, then redo it in a new chunk
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
