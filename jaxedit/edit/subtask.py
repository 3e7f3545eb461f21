"""One subtask of an edit (paper 3.1, 3.3) as a small state machine: init, step, terminate.

:func:`run_subtask` trains subtask ``spec`` from an :class:`jaxedit.edit.state.EditState`
(possibly resumed mid-way) until it converges, in the style of optimistix's solvers:

* :func:`init`: the loop's state :class:`SubtaskLoop` at the subtask's (re)start;
* :func:`step`: the editor exchange due at this step, then one chunk of training steps
  (:func:`step_chunk`: up to ``CHUNK`` steps in one compiled ``lax.scan``, views, keys,
  density control and the loss-plateau test on the device; the host reads the chunk's
  losses once);
* :func:`settle`: what the chunk's end means: a plateau (converged), a guard, or views
  still missing (wait for them), and whether a checkpoint is due;
* :func:`terminate`, then :func:`postprocess`: the state and the subtask's info.

The edits come from one :class:`jaxedit.edit.buffer.EditSource` interface, inline and
deterministic or from a producer thread; the loop asks it when an exchange is due and
waits on it for missing views, and never branches on which one it is. The host acts
only between chunks, at steps fixed by the config (exchanges after the warm-up, every
``checkpoint_every`` steps), so a seeded run and a resumed one take the same steps with
the same bits.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..editors.base import edit_views, interpolate_embedding
from ..editors.keys import edit_key
from ..raster.placement import commit
from ..train import CHUNK, Batch, apply_step, epoch_view, grow_for_redo, scan_steps
from .buffer import EditedView, EditJob, EditSource, make_source, side_by_side, view_order
from .context import EditContext
from .local import blend
from .plan import (ProEditConfig, SubtaskLimits, SubtaskSpec, anneal_horizon, anneal_timestep,
                   subtask_limits)
from .state import EditState, apply_edits, begin_subtask, tally_density, track_loss

# fold_in "purposes" of the per-subtask key: one stream per use, never shared.
_ORDER, _TRAIN, _VIEWS, _EDIT = 1, 2, 3, 4
#: Longest wait (seconds) for the missing views at a plateau or a guard.
WAIT_S = 600


def train_view(key: jax.Array, step: int, num_views: int) -> int:
    """The view trained at ``step``: epochs of seeded permutations (pure in (key, step))."""
    return int(epoch_view(key, int(step), num_views))


# ---------------------------------------------------------------------------
# The editor's side: renders edited with e(r), edits taken into the dataset
# ---------------------------------------------------------------------------
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
    # Each view's camera sliced once per subtask, not at every edit (a slice per leaf).
    cameras = [ctx.data.train_cameras[i] for i in range(len(ctx.data.train_images))]
    # The original photos once on the editor's device (the default one when it has none).
    originals = jax.device_put(ctx.data.train_images, ctx.editor_device)

    def t_range(job: EditJob) -> tuple[float, float]:
        if job.timestep is not None:  # the source fixes it (a study's explicit schedule)
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
        renders = [renderer(scene, cameras[job.view]).rgb for job in jobs]
        # A local edit's mask is applied once, where the edits become training images
        # (take_edits): blending here with the render as well weighted the edit by the
        # mask's square (0.49 at a border pixel of 0.7).
        return edit_views(ctx.editor, renders, [originals[job.view] for job in jobs], embedding,
                          [edit_key(sub_key, job.view, job.iteration) for job in jobs],
                          timestep_range=t_range(jobs[0]), guidance=cfg.guidance)

    def edit_one(job: EditJob, scene):
        return edit_many([job], scene)[0]

    return edit_one, edit_many

def take_edits(ctx: EditContext, st: EditState, arrivals: list[EditedView],
               horizon: int) -> EditState:
    """``st`` with the edited views ``arrivals`` as training images (in arrival order).

    A local edit's training image is ``mask * edit + (1 - mask) * original photo``: inside
    its rendered relevance the edit, outside it the photo. An edit counts as made at
    t_min when its step is past the annealing ``horizon`` (or its explicit timestep is at
    most t_min): the plateau may end the subtask ``patience`` steps after the first one.
    """
    images = [e.image for e in arrivals]
    if ctx.masks is not None:
        images = [blend(im, ctx.data.train_images[e.job.view], ctx.masks[e.job.view])
                  for im, e in zip(images, arrivals)]
    t_min = ctx.config.timestep_range[0]
    return apply_edits(st, [e.job.view for e in arrivals], images,
                       [e.job.step >= horizon if e.job.timestep is None
                        else e.job.timestep <= t_min for e in arrivals])


# ---------------------------------------------------------------------------
# Chunks of training steps on the device
# ---------------------------------------------------------------------------
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


# The run's settings that are plain numbers (warmup, patience, whether a plateau ends the
# subtask) are traced, not static: runs that differ only in them (ProEdit and a fixed budget,
# tests with other patience) share one program. The window is the tracker's shape; min_delta
# stays static, so that best * (1 - min_delta) is the constant it always was.
@functools.partial(jax.jit, static_argnames=("length", "min_delta"))
def _edit_chunk(train_state, tracker, images, cameras, regions, run_key, scalars, *, length,
                min_delta):
    subtask, step0, n_active = scalars[0], scalars[1], scalars[2]
    stop_if_plateau, earliest_end = scalars[3] > 0, scalars[4]
    warmup, patience, stop_on_plateau = scalars[5], scalars[6], scalars[7] > 0
    window = tracker.recent.shape[0]
    key_sub = jax.random.fold_in(run_key, subtask)
    views_key, train_key = (jax.random.fold_in(key_sub, _VIEWS),
                            jax.random.fold_in(key_sub, _TRAIN))
    num_views = images.shape[0]

    def one(carry, i):
        st, tr = carry
        s = step0 + i
        view = epoch_view(views_key, s, num_views)
        region = None if regions is None else regions[view]
        st, m = apply_step(st, Batch(image=images[view], camera=cameras[view], region=region),
                            jax.random.fold_in(train_key, s))
        tracked = ~m["redo"] & (s >= warmup)
        loss = m["loss"]
        if region is not None:
            # A local edit's plateau is that of the loss where it edits: the frozen rest
            # of the view adds a loss no step can lower, which flattens the relative test.
            # (Person, seeds 0-4, local minus global inside the region: -0.22 dB on
            # average with it, -0.38 dB without; the seeds spread by 0.3 dB.)
            tracked &= jnp.any(region > 0)
            loss = m["region_loss"]
        tr = jax.tree_util.tree_map(functools.partial(jnp.where, tracked),
                                    track_loss(tr, loss, min_delta=min_delta), tr)
        return (st, tr), m

    def after(carry, m, i):
        tr = carry[1]
        plateau = (stop_on_plateau & (tr.count >= window) & (tr.since_best >= patience)
                   & (step0 + i + 1 >= earliest_end))
        return dict(m, plateau=plateau), plateau & stop_if_plateau

    (train_state, tracker), metrics = scan_steps(one, (train_state, tracker), n_active,
                                                 length=length, after=after)
    return train_state, tracker, metrics


def step_chunk(ctx: EditContext, st: EditState, spec: SubtaskSpec, limits: SubtaskLimits,
               num_steps: int, *, stop_if_plateau: bool) -> tuple[EditState, ChunkResult]:
    """Up to ``num_steps`` (<= CHUNK) steps of subtask ``spec`` (its ``limits``): a pure
    function of its inputs.

    Stops early after a step that asks for a redo (not counted) or, when
    ``stop_if_plateau``, at the step where the loss plateaus (a plateau counts
    only from :func:`earliest_end` on; never without ``limits.stop_on_plateau``).
    """
    cfg = ctx.config
    # The chunk's only upload: eight int32 (explicit; images and state stay on the device).
    scalars = [spec.index, st.step, num_steps, stop_if_plateau, earliest_end(st, cfg),
               cfg.warmup, cfg.patience, limits.stop_on_plateau]
    train, tracker, metrics = _edit_chunk(*_chunk_args(ctx, st, scalars), length=CHUNK,
                                          min_delta=cfg.min_delta)
    metrics = jax.device_get(metrics)  # the one host read of the chunk
    completed = metrics["ran"] & ~metrics["redo"]
    k = int(np.sum(completed))
    redo = bool(np.any(metrics["ran"] & metrics["redo"]))
    plateau = bool(k and metrics["plateau"][k - 1])
    density = tally_density(st.density, metrics["densify"], completed)
    return (dataclasses.replace(st, train=train, tracker=tracker, step=st.step + k,
                                density=density),
            ChunkResult(np.asarray(metrics["loss"][:k]), redo, plateau, metrics))


def _chunk_args(ctx: EditContext, st: EditState, scalars: list) -> tuple:
    """:func:`_edit_chunk`'s arguments at ``st``: committed where they are (one program for
    fresh and trained leaves alike), the eight int32 ``scalars`` uploaded."""
    return (*commit((st.train, st.tracker, st.images, ctx.data.train_cameras, ctx.masks,
                     ctx.key)), jax.device_put(np.asarray(scalars, np.int32)))


def compile_chunk(ctx: EditContext, st: EditState) -> None:
    """Build the program of the training chunks that start from ``st``'s shapes (as a
    subtask begun on it runs them), or read it back from the persistent cache, without
    running it: the first chunk then starts at once. The edit does it on a thread while the
    difficulty schedule runs (:func:`jaxedit.pipelines.edit.run_edit`). On a GPU the
    schedule's edits leave the host free for it; on the 2-core CPU, whose cores the
    schedule's edits keep busy, the cold demo's first subtask went from 18 to 8 s (the
    program's 5 s compile moved) and the warm one's from 10 to 8 s, the schedule about 1 s
    longer."""
    _edit_chunk.lower(*_chunk_args(ctx, st, [0] * 8), length=CHUNK,
                      min_delta=ctx.config.min_delta).compile()


#: earliest_end while the annealing has not reached t_min: no plateau ends the subtask.
NOT_YET = 2 ** 30


def earliest_end(st: EditState, cfg: ProEditConfig) -> int:
    """The first step count at which a plateau may end the subtask: ``patience`` steps of
    training on the complete edited dataset, and on an edit made at t_min (the annealing
    reaches its end in every subtask; not in IN2N mode, which does not anneal). While a
    view is still unedited a plateau is reported at once (0): it ends nothing, but with
    edits from a thread the subtask then waits for the missing views."""
    if st.complete_at < 0:
        return 0
    if cfg.mode == "in2n":
        return st.complete_at + cfg.patience
    if st.annealed_at < 0:
        return NOT_YET
    return max(st.complete_at, st.annealed_at) + cfg.patience


def last_step(st: EditState, cfg: ProEditConfig, max_steps: int, can_wait: bool,
              guard: int | None = None) -> int:
    """Where the guard (``max_steps``, or ``guard`` when the time guard fired there) ends
    the subtask. With edits from a thread (``can_wait``), a guard that fired before every
    view was edited waits for them and then trains ``patience`` more steps on them; the
    deterministic schedule is a fixed budget (IN2N) and ends at the guard."""
    guard = max_steps if guard is None else min(guard, max_steps)
    if not can_wait or st.complete_at < 0:
        return guard
    return max(guard, st.complete_at + cfg.patience)


def next_stop(step: int, cfg: ProEditConfig, last: int, source: EditSource) -> int:
    """The next step after ``step`` where the host must act: the source's next exchange
    (a thread's: the next step), a checkpoint, the end of the warm-up or of the subtask."""
    warmup = cfg.warmup
    stops = [last, step + CHUNK, (step // cfg.checkpoint_every + 1) * cfg.checkpoint_every]
    if step < warmup:
        stops.append(warmup)
    due = source.next_due(step - warmup)
    if due is not None:
        stops.append(warmup + due)
    return min(stops)


# ---------------------------------------------------------------------------
# The state machine
# ---------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Subtask:
    """What one subtask's loop reads and never changes.

    Attributes:
      ctx: the run's context.
      spec: the subtask.
      limits: its step guard and plateau test (:func:`jaxedit.edit.plan.subtask_limits`).
      source: its edits' :class:`jaxedit.edit.buffer.EditSource` (entered by the caller).
      horizon: steps after the warm-up at which the annealed timestep reaches t_min
        (:func:`jaxedit.edit.plan.anneal_horizon`).
      started: ``time.perf_counter()`` when the subtask would have started had it never
        been interrupted (a resumed subtask keeps its seconds).
    """

    ctx: EditContext
    spec: SubtaskSpec
    limits: SubtaskLimits
    source: Any
    horizon: int
    started: float


class SubtaskLoop(NamedTuple):
    """Where a subtask's loop is (host side; each step returns a new one).

    st: the :class:`EditState`; exchanged_at: the step of the last exchange (None: none
    yet; a chunk redone with larger buffers must not edit the same views again);
    timed_out_at: the step at which ``max_seconds`` fired (None: it has not);
    converged: ended on its loss plateau; done: ended.
    """

    st: EditState
    exchanged_at: int | None = None
    timed_out_at: int | None = None
    converged: bool = False
    done: bool = False


def prepare(ctx: EditContext, st: EditState, spec: SubtaskSpec) -> Subtask:
    """Subtask ``spec``'s fixed parts: its limits, its edit source (the views in a seeded
    cyclic order, each edited from the current render with e(r)) and its annealing horizon."""
    cfg = ctx.config
    limits = ctx.hooks.limits_of(spec, subtask_limits(cfg, ctx.data.train_images.shape))
    key_sub = jax.random.fold_in(ctx.key, spec.index)
    order = view_order(len(ctx.data.train_images), jax.random.fold_in(key_sub, _ORDER))
    horizon = anneal_horizon(cfg, limits.max_steps)
    edit_one, edit_many = make_edit_fns(ctx, spec, horizon)
    trainer_device = next(iter(st.images.devices()))
    # Room for two chunks' worth of edits, so a fast editor is never held up between
    # the trainer's collections.
    source = None if ctx.hooks.edit_source is None else ctx.hooks.edit_source(
        spec, edit_one, order, edit_many=edit_many, trainer_device=trainer_device)
    if source is None:
        source = make_source(edit_one, order, asynchronous=cfg.asynchronous,
                             edit_many=edit_many, every=cfg.edit_every,
                             initial_sweep=cfg.initial_sweep, device=ctx.editor_device,
                             capacity=2 * CHUNK, trainer_device=trainer_device,
                             pipelined=cfg.pipelined and side_by_side(trainer_device,
                                                                      ctx.editor_device),
                             sweep_every=cfg.sweep_every)
    return Subtask(ctx, spec, limits, source, horizon, time.perf_counter() - st.seconds)


def init(sub: Subtask, st: EditState) -> SubtaskLoop:
    """The loop at ``st``, a state begun by :func:`jaxedit.edit.state.begin_subtask`."""
    return SubtaskLoop(st)


def step(sub: Subtask, loop: SubtaskLoop) -> tuple[SubtaskLoop, ChunkResult]:
    """The exchange due at the loop's step, then one chunk of training steps up to the
    next step where the host must act (:func:`next_stop`), then the edits the source made
    beside those steps (a pipelined source's)."""
    ctx, cfg, source = sub.ctx, sub.ctx.config, sub.source
    st, exchanged_at = loop.st, loop.exchanged_at
    s = st.step
    if s >= cfg.warmup and s != exchanged_at and source.due(s - cfg.warmup):
        st = take_edits(ctx, st, source.exchange(s - cfg.warmup, ctx.trainer.gaussians(st.train)),
                        sub.horizon)
        exchanged_at = s
    # A plateau before every view is edited: the deterministic source edits the missing
    # views at its own steps, so training goes on; a thread's edits are waited for.
    stop_if_plateau = bool(st.edited.all()) or source.can_wait
    last = last_step(st, cfg, sub.limits.max_steps, source.can_wait, loop.timed_out_at)
    st, chunk = step_chunk(ctx, st, sub.spec, sub.limits, next_stop(s, cfg, last, source) - s,
                           stop_if_plateau=stop_if_plateau)
    if chunk.redo:
        k = len(chunk.losses)
        st = dataclasses.replace(st, train=grow_for_redo(st.train, jax.tree_util.tree_map(
            lambda a: a[k], chunk.metrics)))
    # A pipelined source's edit, made beside these steps, enters the dataset at their end.
    st = take_edits(ctx, st, source.collect(), sub.horizon)
    st = dataclasses.replace(st, seconds=time.perf_counter() - sub.started)
    timed_out_at = loop.timed_out_at
    if timed_out_at is None and cfg.max_seconds is not None and st.seconds >= cfg.max_seconds:
        timed_out_at = st.step
    return loop._replace(st=st, exchanged_at=exchanged_at, timed_out_at=timed_out_at), chunk


def await_views(sub: Subtask, st: EditState) -> EditState:
    """``st`` with the edits that arrive until every view has one: the trainer's only wait
    (counted in the source's utilisation). A deterministic source returns at once: its
    edits arrive only at its exchanges."""
    arrived: list[EditedView] = []

    def complete() -> bool:
        edited = st.edited.copy()
        edited[[e.job.view for e in arrived]] = True
        return bool(edited.all())

    sub.source.wait_for(complete, timeout=WAIT_S, on_edits=arrived.extend)
    return take_edits(sub.ctx, st, arrived, sub.horizon)


def settle(sub: Subtask, loop: SubtaskLoop, chunk: ChunkResult) -> tuple[SubtaskLoop, bool]:
    """(the loop after what the chunk's end means, whether a checkpoint is due there).

    A plateau on the complete dataset converges; a plateau reached by a thread's source
    on a partly stale dataset waits for the missing views and looks for a new plateau on
    them. At the guard the subtask ends, after waiting for missing views where waiting
    brings them (then the guard moves to ``patience`` steps after the last one).
    """
    cfg, st = sub.ctx.config, loop.st
    if chunk.plateau and not st.edited.all() and sub.source.can_wait:
        st = await_views(sub, st)
        st = dataclasses.replace(st, tracker=st.tracker._replace(since_best=jnp.int32(0)))
        return loop._replace(st=st), False
    if chunk.plateau and st.edited.all():
        return loop._replace(converged=True, done=True), False
    if st.step >= last_step(st, cfg, sub.limits.max_steps, sub.source.can_wait,
                            loop.timed_out_at):
        if not st.edited.all():
            # Never end a subtask on a dataset the editor has not fully updated to e(r_i):
            # a slow editor makes the trainer wait here (counted).
            st = await_views(sub, st)
            if st.edited.all():
                return loop._replace(st=st), False
        return loop._replace(st=st, done=True), False
    return loop, st.step % cfg.checkpoint_every == 0 and not chunk.redo


def terminate(loop: SubtaskLoop) -> bool:
    return loop.done


def postprocess(sub: Subtask, loop: SubtaskLoop) -> tuple[EditState, dict]:
    """(the state at the end of the subtask, its info); after the source is closed, so its
    utilisation includes the final join."""
    cfg, source, plateau = sub.ctx.config, sub.source, sub.limits.stop_on_plateau
    st = dataclasses.replace(loop.st, seconds=time.perf_counter() - sub.started,
                             utilisation=loop.st.utilisation.add(source.utilisation))
    guard = None if loop.converged or not plateau else (
        "seconds" if loop.timed_out_at is not None else "steps")
    # a fixed budget (IN2N, the equal-budget controls) has no plateau to reach: None, not True
    return st, {"steps": st.step, "converged": loop.converged if plateau else None,
                "guard": guard, "seconds": st.seconds,
                "edits_complete_at": None if st.complete_at < 0 else st.complete_at,
                "anneal_horizon": None if cfg.mode == "in2n" else cfg.warmup + sub.horizon,
                "annealed_at": None if st.annealed_at < 0 else st.annealed_at,
                "density": st.density._asdict(),
                "utilisation": source.utilisation.as_dict()}


def run_subtask(ctx: EditContext, st: EditState, spec: SubtaskSpec, *,
                callback: Callable | None = None, checkpoint: Callable | None = None,
                progress: Callable | None = None) -> tuple[EditState, dict]:
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
    if st.step == 0:
        st = begin_subtask(ctx, st)
    sub = prepare(ctx, st, spec)
    with sub.source:
        loop = init(sub, st)
        while not terminate(loop):
            loop, chunk = step(sub, loop)
            first = loop.st.step - len(chunk.losses)
            for i, loss in enumerate(chunk.losses):
                if callback is not None:
                    callback(spec, first + i + 1, float(loss))
            if progress is not None and len(chunk.losses):
                progress(spec, loop.st.step, float(chunk.losses[-1]), loop.st)
            loop, checkpoint_due = settle(sub, loop, chunk)
            if checkpoint is not None and checkpoint_due:
                checkpoint(loop.st)
    return postprocess(sub, loop)
