"""The ProEdit driver of one subtask (paper 3.1, 3.3) as a state machine of pure parts.

A run's state is an immutable :class:`DriverState`; pure functions advance it:

* :func:`init_state`: the input scene and the original photos;
* :func:`begin_subtask`: paper 3.3 (1), every opacity to the cull threshold, fresh
  density statistics, loss tracker and edit flags;
* :func:`apply_edits`: edited views land in the device-resident training set;
* :func:`step_chunk`: up to ``CHUNK`` training steps in one compiled ``lax.scan``
  (views, keys, density control and the loss-plateau test all on the device);
  the host reads the chunk's losses once;
* :func:`finish_subtask`: the subtask's record appended, the clock moved on.

The edge is :func:`run_subtask`: the editor exchange (a thread in the
asynchronous mode), checkpoints and progress happen only between chunks, at
steps fixed by the config (every ``edit_every`` steps after the warm-up, every
``checkpoint_every`` steps), so a seeded run and a resumed one take the same
steps with the same bits.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import DataError
from .buffer import EditJob, Utilisation, make_source, view_order
from ..editors.base import edit_views, interpolate_embedding
from ..editors.keys import edit_key
from .outputs import Renderer
from .plan import ProEditConfig, SubtaskSpec, anneal_horizon, anneal_timestep, subtask_guard
from .trainer import SubtaskTrainer

# fold_in "purposes" of the per-subtask key: one stream per use, never shared.
_ORDER, _TRAIN, _VIEWS, _EDIT = 1, 2, 3, 4
#: Most steps per compiled chunk; the host acts only between chunks.
CHUNK = 16


# ---------------------------------------------------------------------------
# Views and convergence, pure in their inputs (host or device)
# ---------------------------------------------------------------------------
def _view_at(key, step, num_views: int):
    epoch, pos = step // num_views, step % num_views
    return jax.random.permutation(jax.random.fold_in(key, epoch), num_views)[pos]


def train_view(key: jax.Array, step: int, num_views: int) -> int:
    """The view trained at ``step``: epochs of seeded permutations (pure in (key, step))."""
    return int(_view_at(key, int(step), num_views))


class LossTracker(NamedTuple):
    """Running mean of the last ``window`` losses and steps since its last minimum.

    recent: float32 [window] ring buffer; count: int32, losses seen; best:
    float32, lowest running mean so far (inf before the window is full);
    since_best: int32, steps since then. A pytree: it is advanced on the device.
    """

    recent: jax.Array
    count: jax.Array
    best: jax.Array
    since_best: jax.Array

    @staticmethod
    def init(window: int) -> "LossTracker":
        return LossTracker(jnp.zeros((window,), jnp.float32), jnp.int32(0),
                           jnp.float32(math.inf), jnp.int32(0))

    def mean(self) -> float:
        n = min(int(self.count), len(self.recent))
        return float(np.mean(np.asarray(self.recent)[:n])) if n else math.inf


def track_loss(tracker: LossTracker, loss, *, min_delta: float) -> LossTracker:
    """Add one loss; a running mean below best * (1 - min_delta) resets the patience counter."""
    window = tracker.recent.shape[0]
    recent = tracker.recent.at[tracker.count % window].set(jnp.asarray(loss, jnp.float32))
    count = tracker.count + 1
    full = count >= window
    mean = jnp.mean(recent)
    better = (mean < tracker.best * (1.0 - min_delta)) | ~jnp.isfinite(tracker.best)
    best = jnp.where(full & better, mean, tracker.best)
    since = jnp.where(full, jnp.where(better, 0, tracker.since_best + 1), tracker.since_best)
    return LossTracker(recent, count, best.astype(jnp.float32), since.astype(jnp.int32))


class DensityTally(NamedTuple):
    """What density control did in a subtask (host ints, summed over its maintenance steps).

    refinements: maintenance steps; created / culled: Gaussians; budget_limited:
    maintenance steps whose creation the budget t(n) set (it created t(n), neither the
    candidates nor the cap held it lower); cap_limited: maintenance steps where the hard
    cap, not the budget t(n), bounded creation; shortfall: Gaussians those steps wanted
    (min(t(n), candidates)) but had no room for.
    """

    refinements: int = 0
    created: int = 0
    culled: int = 0
    budget_limited: int = 0
    cap_limited: int = 0
    shortfall: int = 0


def tally_density(tally: DensityTally, densify: dict, completed: np.ndarray) -> DensityTally:
    """``tally`` plus the maintenance steps among the ``completed`` steps of a chunk.

    ``densify`` holds :class:`jaxedit.densify.DensifyInfo`'s fields as NumPy arrays [length].
    """
    ran = completed & np.asarray(densify["refined"], bool)
    capped = ran & np.asarray(densify["cap_limited"], bool)
    by_budget = ran & ~capped & (np.asarray(densify["created"]) >= np.asarray(densify["budget"]))
    wanted = np.minimum(densify["budget"], densify["candidates"]).astype(np.int64)
    short = np.maximum(wanted - np.asarray(densify["created"], np.int64), 0)
    return DensityTally(tally.refinements + int(ran.sum()),
                        tally.created + int(np.sum(densify["created"], where=ran)),
                        tally.culled + int(np.sum(densify["culled"], where=ran)),
                        tally.budget_limited + int(by_budget.sum()),
                        tally.cap_limited + int(capped.sum()),
                        tally.shortfall + int(np.sum(short, where=capped)))


# ---------------------------------------------------------------------------
# What the driver reads and what it advances
# ---------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class EditData:
    """Views of the scene being edited.

    Attributes:
      train_images: float32 [N, H, W, 3], the original photos of the training views.
      train_cameras: batched Camera [N].
      test_images: float32 [M, H, W, 3], held-out originals (never trained on).
      test_cameras: batched Camera [M].
    """

    train_images: np.ndarray
    train_cameras: Any
    test_images: np.ndarray
    test_cameras: Any

    def __post_init__(self):
        if self.train_images.ndim != 4 or self.train_images.shape[-1] != 3:
            raise DataError("train_images", f"need float [N, H, W, 3], got {self.train_images.shape}")
        if len(self.train_cameras) != len(self.train_images):
            raise DataError("train_cameras", f"{len(self.train_cameras)} cameras for "
                                             f"{len(self.train_images)} images")
        if len(self.test_cameras) != len(self.test_images):
            raise DataError("test_cameras", f"{len(self.test_cameras)} cameras for "
                                            f"{len(self.test_images)} images")
        # On the device once: the training chunks read the cameras every step.
        object.__setattr__(self, "train_cameras", jax.device_put(self.train_cameras))
        object.__setattr__(self, "test_cameras", jax.device_put(self.test_cameras))

    @staticmethod
    def from_dataset(dataset) -> "EditData":
        """From a :func:`jaxedit.io.load_nerfstudio` dataset (train/test split)."""
        images = np.asarray(dataset.images, np.float32)
        train = np.asarray(dataset.train_indices)
        test = np.asarray(dataset.test_indices)
        if len(test) == 0:  # no held-out split: score on the training views, say so
            test = train
        return EditData(images[train], dataset.cameras[train], images[test], dataset.cameras[test])


@dataclasses.dataclass(frozen=True)
class DriverState:
    """Where a run is: everything needed to continue it exactly (never mutated).

    Attributes:
      subtask: index of the current subtask in the plan.
      step: steps already taken inside it (0: not started, opacity not yet reset).
      train: the trainer's state pytree (Gaussians, optimiser, densify stats).
      images: float32 [N, H, W, 3] on the device, the training images as of now.
      edited: bool [N] (host), views edited at least once in the current subtask.
      tracker: the loss tracker of the current subtask.
      records: one dict per finished subtask (schedule.json entries).
      seconds: wall time spent in the current subtask before the last restart.
      utilisation: buffer counters summed over the run.
      complete_at: the subtask's step when every view had been edited (-1: not yet);
        it may end no earlier than ``patience`` steps later, so it never ends on
        edits it has not trained on.
      annealed_at: the subtask's step when the first edit made at t_min arrived
        (-1: not yet); a plateau ends the subtask no earlier than ``patience`` steps
        later, so the annealing always reaches t_min.
      density: the subtask's :class:`DensityTally`.
    """

    subtask: int
    step: int
    train: Any
    images: jax.Array
    edited: np.ndarray
    tracker: LossTracker
    records: tuple = ()
    seconds: float = 0.0
    utilisation: Utilisation = dataclasses.field(default_factory=Utilisation)
    complete_at: int = -1
    annealed_at: int = -1
    density: DensityTally = DensityTally()


@dataclasses.dataclass(frozen=True)
class EditContext:
    """Everything a run reads but never changes.

    Attributes:
      editor: an :class:`jaxedit.editors.Editor`.
      prompt: the instruction p.
      data: the views (:class:`EditData`).
      config: :class:`ProEditConfig`; a ``max_steps`` of None becomes the scene's
        :func:`jaxedit.edit.plan.subtask_guard`.
      trainer: :class:`SubtaskTrainer`.
      renderer: :class:`Renderer` used for the editor's inputs and the snapshots.
      key: the run key (``jax.random.key(seed)``).
      editor_device: device of the editor (async mode), see :func:`pick_devices`.
      masks: float [N, H, W] per training view, a local edit's rendered relevance
        (:func:`jaxedit.edit.local.prepare`), or None (a global edit): the editor's
        output is blended with the render outside it, and the training image of an
        edited view with the original photo.
    """

    editor: Any
    prompt: str
    data: EditData
    config: ProEditConfig
    trainer: SubtaskTrainer
    renderer: Renderer
    key: jax.Array
    editor_device: Any = None
    masks: Any = None

    def __post_init__(self):
        if self.config.max_steps is None:
            n, h, w = self.data.train_images.shape[:3]
            object.__setattr__(self, "config", dataclasses.replace(
                self.config, max_steps=subtask_guard(n, h, w)))
        object.__setattr__(self, "e_prompt", np.asarray(self.editor.encode(self.prompt)))
        object.__setattr__(self, "e_null", np.asarray(self.editor.encode("")))


def make_edit_fns(ctx: EditContext, spec: SubtaskSpec, horizon: int) -> tuple[
        Callable[[EditJob, Any], Any], Callable[[list[EditJob], Any], list]]:
    """``(edit_one(job, scene) -> view, edit_many(jobs, scene) -> views)`` of subtask ``spec``:
    render the views, edit them with e(r).

    The editor sees ``image`` = the current render, ``original`` = the original
    photo, embedding e(r); the key is :func:`edit_key` of (run key | subtask, view, iteration);
    the timestep follows HiFA's annealing over ``horizon`` steps after the warm-up
    (:func:`anneal_horizon`; IN2N mode: the fixed range, from which the editor draws).
    ``edit_many`` takes jobs of one step (one timestep) and edits them in the editor's
    batches (:func:`jaxedit.editors.base.edit_views`).
    """
    cfg = ctx.config
    ratio = 0.0 if spec.kind == "refine" else spec.ratio
    embedding = interpolate_embedding(ctx.e_prompt, ctx.e_null, ratio)
    sub_key = jax.random.fold_in(jax.random.fold_in(ctx.key, spec.index), _EDIT)
    renderer = ctx.renderer
    # The original photos once on the editor's device (the default one when it has none).
    originals = jax.device_put(ctx.data.train_images, ctx.editor_device)

    def t_range(job: EditJob) -> tuple[float, float]:
        if job.timestep is not None:  # an explicit schedule fixes it (ScheduledEditSource)
            return (job.timestep, job.timestep)
        if cfg.mode == "in2n":
            return tuple(cfg.timestep_range)
        t = anneal_timestep(job.step, horizon, *cfg.timestep_range)
        return (t, t)

    def edit_many(jobs: list[EditJob], scene) -> list:
        if len({job.step for job in jobs}) != 1:
            raise ValueError("edit_many takes the jobs of one step")
        # Device arrays where the scene is (the editor's device in async mode): an editor
        # in JAX takes them as they are; the torch reference copies them to its own device.
        renders = [renderer(scene, ctx.data.train_cameras[job.view]).rgb for job in jobs]
        out = edit_views(ctx.editor, renders, [originals[job.view] for job in jobs], embedding,
                         [edit_key(sub_key, job.view, job.iteration) for job in jobs],
                         timestep_range=t_range(jobs[0]), guidance=tuple(cfg.guidance))
        if ctx.masks is None:
            return out
        from .local import blend  # a local edit: outside the mask the render stays

        return [blend(e, r, ctx.masks[job.view]) for e, r, job in zip(out, renders, jobs)]

    def edit_one(job: EditJob, scene):
        return edit_many([job], scene)[0]

    return edit_one, edit_many


def init_state(ctx: EditContext, gaussians, images: np.ndarray | None = None) -> DriverState:
    """A run at its very beginning: the input scene, the original photos as training images."""
    images = ctx.data.train_images if images is None else images
    # Room to densify from the start (growth means a recompile), but not much more: the
    # step's cost grows with the capacity. 1.5x, a multiple of 256.
    want = -(-int(1.5 * int(gaussians.num_alive())) // 256) * 256
    capacity = min(max(want, gaussians.capacity), max(ctx.trainer.settings.densify.max_gaussians,
                                                     gaussians.capacity))
    if capacity > gaussians.capacity:
        from ..gaussians import grow

        gaussians = grow(gaussians, capacity)
    return DriverState(subtask=0, step=0, train=ctx.trainer.init(gaussians, ctx.data.train_cameras),
                       images=jax.device_put(np.asarray(images, np.float32)),
                       edited=np.zeros((len(images),), bool),
                       tracker=LossTracker.init(ctx.config.loss_window))


def begin_subtask(ctx: EditContext, st: DriverState) -> DriverState:
    """The state at the start of a subtask: opacity reset (paper 3.3 (1); not in IN2N mode),
    nothing edited yet, a fresh loss tracker."""
    train = ctx.trainer.restart(st.train) if ctx.config.mode != "in2n" else st.train
    return dataclasses.replace(st, step=0, train=train, edited=np.zeros(len(st.edited), bool),
                               tracker=LossTracker.init(ctx.config.loss_window), seconds=0.0,
                               complete_at=-1, annealed_at=-1, density=DensityTally())


def apply_edits(st: DriverState, views, images, annealed=()) -> DriverState:
    """``st`` with edited ``images`` [K, H, W, 3] as the training images of ``views`` [K].

    ``annealed`` (bool [K], optional): the edit was made at t_min.
    """
    if not len(views):
        return st
    from ..train import put_image

    data, edited = st.images, st.edited.copy()
    for v, image in zip(views, images):
        data = put_image(data, int(v), image)
        edited[int(v)] = True
    complete_at = st.step if st.complete_at < 0 and edited.all() else st.complete_at
    annealed_at = st.step if st.annealed_at < 0 and any(annealed) else st.annealed_at
    return dataclasses.replace(st, images=data, edited=edited, complete_at=complete_at,
                               annealed_at=annealed_at)


def finish_subtask(st: DriverState, record: dict) -> DriverState:
    """The state after a finished subtask: its record kept, the next subtask not begun."""
    return dataclasses.replace(st, records=tuple(st.records) + (record,), subtask=st.subtask + 1,
                               step=0, seconds=0.0, complete_at=-1, annealed_at=-1,
                               density=DensityTally())


class ChunkResult(NamedTuple):
    """What the host learns from a chunk (NumPy).

    losses: float [k] of the k completed steps; redo: a step asked for a larger
    buffer or capacity (it is redone after :func:`jaxedit.train.grow_for_redo`);
    plateau: the loss plateaued at the last completed step; metrics: the step
    metrics of the chunk ([length] each, for the redo's sizes).
    """

    losses: np.ndarray
    redo: bool
    plateau: bool
    metrics: dict


@functools.partial(jax.jit, static_argnames=("length", "warmup", "window", "patience",
                                             "min_delta", "stop_on_plateau"))
def _edit_chunk(train_state, tracker, images, cameras, run_key, scalars, *, length, warmup,
                window, patience, min_delta, stop_on_plateau):
    from ..train import Batch, apply_step, scan_steps

    subtask, step0, n_active = scalars[0], scalars[1], scalars[2]
    stop_if_plateau, earliest_end = scalars[3] > 0, scalars[4]
    key_sub = jax.random.fold_in(run_key, subtask)
    views_key, train_key = (jax.random.fold_in(key_sub, _VIEWS),
                            jax.random.fold_in(key_sub, _TRAIN))
    num_views = images.shape[0]

    def one(carry, i):
        st, tr = carry
        s = step0 + i
        view = _view_at(views_key, s, num_views)
        st, m = apply_step(st, Batch(image=images[view], camera=cameras[view]),
                            jax.random.fold_in(train_key, s))
        tracked = ~m["redo"] & (s >= warmup)
        tr = jax.tree_util.tree_map(functools.partial(jnp.where, tracked),
                                    track_loss(tr, m["loss"], min_delta=min_delta), tr)
        return (st, tr), m

    def after(carry, m, i):
        tr = carry[1]
        plateau = (stop_on_plateau & (tr.count >= window) & (tr.since_best >= patience)
                   & (step0 + i + 1 >= earliest_end))
        return dict(m, plateau=plateau), plateau & stop_if_plateau

    (train_state, tracker), metrics = scan_steps(one, (train_state, tracker), n_active,
                                                 length=length, after=after)
    return train_state, tracker, metrics


def step_chunk(ctx: EditContext, st: DriverState, spec: SubtaskSpec, num_steps: int, *,
               stop_if_plateau: bool) -> tuple[DriverState, ChunkResult]:
    """Up to ``num_steps`` (<= CHUNK) steps of subtask ``spec``: a pure function of its inputs.

    Stops early after a step that asks for a redo (not counted) or, when
    ``stop_if_plateau``, at the step where the loss plateaus (a plateau counts
    only from :func:`earliest_end` on).
    """
    cfg = ctx.config
    # The chunk's only upload: five int32 (explicit; images and state stay on the device).
    scalars = jax.device_put(np.array([spec.index, st.step, num_steps, stop_if_plateau,
                                       earliest_end(st, cfg)], np.int32))
    train, tracker, metrics = _edit_chunk(
        st.train, st.tracker, st.images, ctx.data.train_cameras, ctx.key, scalars,
        length=CHUNK, warmup=ctx.trainer.settings.densify.warmup, window=cfg.loss_window,
        patience=cfg.patience, min_delta=cfg.min_delta, stop_on_plateau=cfg.stop_on_plateau)
    metrics = jax.device_get(metrics)  # the one host read of the chunk
    completed = metrics["ran"] & ~metrics["redo"]
    k = int(np.sum(completed))
    redo = bool(np.any(metrics["ran"] & metrics["redo"]))
    plateau = bool(k and metrics["plateau"][k - 1])
    density = tally_density(st.density, metrics["densify"], completed)
    return (dataclasses.replace(st, train=train, tracker=tracker, step=st.step + k,
                                density=density),
            ChunkResult(np.asarray(metrics["loss"][:k]), redo, plateau, metrics))


#: earliest_end while the annealing has not reached t_min: no plateau ends the subtask.
NOT_YET = 2 ** 30


def earliest_end(st: DriverState, cfg: ProEditConfig) -> int:
    """The first step count at which a plateau may end the subtask: ``patience`` steps of
    training on the complete edited dataset, and on an edit made at t_min (the annealing
    reaches its end in every subtask; not in IN2N mode, which does not anneal). While a
    view is still unedited a plateau is reported at once (0): it ends nothing, but with
    edits from a thread the driver then waits for the missing views."""
    if st.complete_at < 0:
        return 0
    if cfg.mode == "in2n":
        return st.complete_at + cfg.patience
    if st.annealed_at < 0:
        return NOT_YET
    return max(st.complete_at, st.annealed_at) + cfg.patience


def _last_step(st: DriverState, cfg: ProEditConfig, deterministic: bool,
               guard: int | None = None) -> int:
    """Where the guard (``max_steps``, or ``guard`` when the time guard fired there) ends
    the subtask. With edits from a thread, a guard that fired before every view was edited
    waits for them and then trains ``patience`` more steps on them; the deterministic
    schedule is a fixed budget (IN2N) and ends at the guard."""
    guard = cfg.max_steps if guard is None else min(guard, cfg.max_steps)
    if deterministic or st.complete_at < 0:
        return guard
    return max(guard, st.complete_at + cfg.patience)


def _next_stop(step: int, cfg: ProEditConfig, warmup: int, last: int, source=None) -> int:
    """The next step after ``step`` where the host must act (editor exchange, checkpoint, end);
    ``source`` (a deterministic one with ``next_due``) says when its next exchange is."""
    stops = [last, step + CHUNK, (step // cfg.checkpoint_every + 1) * cfg.checkpoint_every]
    if step < warmup:
        stops.append(warmup)
    elif source is not None:
        due = source.next_due(step - warmup)
        if due is not None:
            stops.append(warmup + due)
    else:
        stops.append(warmup + ((step - warmup) // cfg.edit_every + 1) * cfg.edit_every)
    return min(stops)


# ---------------------------------------------------------------------------
# The edge: editor exchange, checkpoints, progress
# ---------------------------------------------------------------------------
def run_subtask(ctx: EditContext, st: DriverState, spec: SubtaskSpec, *,
                callback: Callable | None = None, checkpoint: Callable | None = None,
                progress: Callable | None = None) -> tuple[DriverState, dict]:
    """Train subtask ``spec`` from ``st`` (possibly resumed mid-way) until it converges.

    Args:
      callback: ``callback(spec, step, loss)`` after every step (may raise, e.g. to stop).
      checkpoint: ``checkpoint(st)`` every ``checkpoint_every`` steps.
      progress: ``progress(spec, step, loss, st)`` after every chunk of steps.
    Returns:
      (state at the end of the subtask, {"steps", "converged", "guard", "seconds",
      "edits_complete_at", "anneal_horizon", "annealed_at", "density", "utilisation"});
      ``guard`` is None (plateau, or the end of a fixed budget), "steps" or "seconds";
      ``converged`` is None for a fixed budget (``stop_on_plateau`` False).
    """
    from ..train import grow_for_redo

    cfg, trainer = ctx.config, ctx.trainer
    n = len(ctx.data.train_images)
    warmup = trainer.settings.densify.warmup
    if st.step == 0:
        st = begin_subtask(ctx, st)
    key_sub = jax.random.fold_in(ctx.key, spec.index)
    order = view_order(n, jax.random.fold_in(key_sub, _ORDER))
    horizon = anneal_horizon(cfg, warmup)
    edit_one, edit_many = make_edit_fns(ctx, spec, horizon)
    # Room for two chunks' worth of edits, so a fast editor is never held up between
    # the trainer's collections.
    source = make_source(edit_one, order, asynchronous=cfg.asynchronous, edit_many=edit_many,
                         every=cfg.edit_every, initial_sweep=cfg.initial_sweep,
                         device=ctx.editor_device, capacity=2 * CHUNK,
                         trainer_device=next(iter(st.images.devices())),
                         exchanges=None if cfg.edit_plan is None else cfg.edit_plan[spec.index])
    scheduled = cfg.edit_plan is not None and cfg.edit_plan[spec.index] is not None
    started = time.perf_counter() - st.seconds
    converged, timed_out_at = False, None
    holder = [st]
    exchanged_at = None  # a chunk redone (larger buffers) must not edit the same views again

    def take(arrivals):
        images = [e.image for e in arrivals]
        if ctx.masks is not None:  # a local edit trains outside the mask on the originals
            from .local import blend

            images = [blend(im, ctx.data.train_images[e.job.view], ctx.masks[e.job.view])
                      for im, e in zip(images, arrivals)]
        t_min = cfg.timestep_range[0]
        holder[0] = apply_edits(holder[0], [e.job.view for e in arrivals], images,
                                [e.job.step >= horizon if e.job.timestep is None
                                 else e.job.timestep <= t_min for e in arrivals])

    with source:
        while True:
            st = holder[0]
            s = st.step
            due = source.due(s - warmup) if scheduled else (s - warmup) % cfg.edit_every == 0
            if s >= warmup and (due or not source.deterministic) and s != exchanged_at:
                take(source.exchange(s - warmup, trainer.gaussians(st.train)))
                exchanged_at = s
                st = holder[0]
            # The deterministic source edits the missing views itself: plateaus wait for it.
            stop_if_plateau = bool(st.edited.all()) or not source.deterministic
            last = _last_step(st, cfg, source.deterministic, timed_out_at)
            # With edits from a thread the host exchanges with the editor at every step, as
            # the per-step driver did: collecting them once per 10-step chunk left the editor
            # working from stale renders and cost the demo 1.5 dB (38.4 -> 36.4-36.9 dB vs
            # target, two seeds). The deterministic schedule runs whole chunks.
            nsteps = (_next_stop(s, cfg, warmup, last, source if scheduled else None) - s
                      if source.deterministic else 1)
            st, chunk = step_chunk(ctx, st, spec, nsteps,
                                   stop_if_plateau=stop_if_plateau)
            if chunk.redo:
                k = len(chunk.losses)
                st = dataclasses.replace(st, train=grow_for_redo(st.train, jax.tree_util.tree_map(
                    lambda a: a[k], chunk.metrics)))
            st = dataclasses.replace(st, seconds=time.perf_counter() - started)
            timed_out = cfg.max_seconds is not None and st.seconds >= cfg.max_seconds
            if timed_out_at is None and timed_out:
                timed_out_at = st.step
            holder[0] = st
            for i, loss in enumerate(chunk.losses):
                if callback is not None:
                    callback(spec, s + i + 1, float(loss))
            if progress is not None and len(chunk.losses):
                progress(spec, st.step, float(chunk.losses[-1]), st)
            if chunk.plateau and not st.edited.all() and not source.deterministic:
                # The loss settled on a partly stale dataset: wait for the missing views.
                source.wait_for(lambda: bool(holder[0].edited.all()), timeout=600, on_edits=take)
                st = holder[0]
                holder[0] = st = dataclasses.replace(st, tracker=st.tracker._replace(
                    since_best=jnp.int32(0)))
                continue
            if chunk.plateau and st.edited.all():
                converged = True
                break
            if st.step >= _last_step(st, cfg, source.deterministic, timed_out_at):
                if not st.edited.all() and not source.deterministic:
                    # Never end a subtask on a dataset the editor has not fully updated to
                    # e(r_i): a slow editor makes the trainer wait here (counted), then the
                    # guard moves to `patience` steps after the last view arrived.
                    source.wait_for(lambda: bool(holder[0].edited.all()), timeout=600,
                                    on_edits=take)
                    if holder[0].edited.all():
                        continue
                break
            if checkpoint is not None and st.step % cfg.checkpoint_every == 0 and not chunk.redo:
                checkpoint(st)
    st = holder[0]
    st = dataclasses.replace(st, seconds=time.perf_counter() - started,  # final waits, join
                             utilisation=st.utilisation.add(source.utilisation))
    guard = None if converged or not cfg.stop_on_plateau else (
        "seconds" if timed_out_at is not None else "steps")
    # a fixed budget (IN2N, the equal-budget controls) has no plateau to reach: None, not True
    return st, {"steps": st.step, "converged": converged if cfg.stop_on_plateau else None,
                "guard": guard, "seconds": st.seconds,
                "edits_complete_at": None if st.complete_at < 0 else st.complete_at,
                "anneal_horizon": None if cfg.mode == "in2n" else warmup + horizon,
                "annealed_at": None if st.annealed_at < 0 else st.annealed_at,
                "density": st.density._asdict(),
                "utilisation": source.utilisation.as_dict()}
