"""One subtask of an edit (paper 3.1, 3.3) as a state machine: :func:`init`,
:func:`step`, :func:`settle`, :func:`terminate`, :func:`postprocess`.

:func:`run_subtask` trains subtask ``spec`` from an :class:`~jaxedit.edit.state.EditState`
(possibly resumed) until it converges. Edits come through one
:class:`~jaxedit.edit.buffer.EditSource`; the host acts only between chunks, at steps
fixed by the config, so a seeded run and a resumed one take the same steps and bits.
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
from ..io.views import device_float, stored_views
from ..raster.placement import commit
from ..train import CHUNK, Batch, apply_step, epoch_view, grow_for_redo, scan_steps
from .buffer import EditedView, EditJob, EditSource, make_source, side_by_side, view_order
from .context import EditContext
from .local import blend
from .plan import (ProEditConfig, SubtaskLimits, SubtaskSpec, anneal_horizon, anneal_timestep,
                   subtask_limits)
from .state import DeviceState, EditState, apply_edits, begin_subtask, tally_density, track_loss

# fold_in "purposes" of the per-subtask key: one stream per use, never shared.
_ORDER, _TRAIN, _VIEWS, _EDIT = 1, 2, 3, 4
#: Longest wait (seconds) for the missing views at a plateau or a guard.
WAIT_S = 600


def train_view(key: jax.Array, step: int, num_views: int) -> int:
    """The view trained at ``step``: epochs of seeded permutations (pure in (key, step))."""
    return int(epoch_view(key, int(step), num_views))


# -- the editor's side --
def make_edit_fns(ctx: EditContext, spec: SubtaskSpec, horizon: int) -> tuple[
        Callable[[EditJob, Any], Any], Callable[[list[EditJob], Any], list]]:
    """``(edit_one(job, scene) -> view, edit_many(jobs, scene) -> views)`` of subtask ``spec``.

    Each renders the job's view of ``scene`` and edits it with embedding e(r) against the
    original photo, key :func:`edit_key` of (run key | subtask, view, iteration), timestep
    annealed over ``horizon`` steps after the warm-up (IN2N mode: the fixed range).
    ``edit_many`` takes jobs of one step and edits them in the editor's batches.
    """
    cfg = ctx.config
    ratio = 0.0 if spec.kind == "refine" else spec.ratio
    embedding = interpolate_embedding(ctx.e_prompt, ctx.e_null, ratio)
    sub_key = jax.random.fold_in(jax.random.fold_in(ctx.key, spec.index), _EDIT)
    renderer = ctx.renderer
    cameras = [ctx.data.train_cameras[i] for i in range(len(ctx.data.train_images))]
    originals = jax.device_put(stored_views(ctx.data.train_images), ctx.editor_device)

    def t_range(job: EditJob) -> tuple[float, float]:
        if job.timestep is not None:
            return (job.timestep, job.timestep)
        if cfg.mode == "in2n":
            return tuple(cfg.timestep_range)
        t = anneal_timestep(job.step, horizon, *cfg.timestep_range)
        return (t, t)

    def edit_many(jobs: list[EditJob], scene) -> list:
        if len({job.step for job in jobs}) != 1:
            raise ValueError("edit_many takes the jobs of one step")
        # Device arrays where the scene is; a torch editor copies them to its device.
        renders = [renderer(scene, cameras[job.view]).rgb for job in jobs]
        # A local edit's mask is applied once, in take_edits.
        photos = [device_float(originals[job.view]) for job in jobs]
        return edit_views(ctx.editor, renders, photos, embedding,
                          [edit_key(sub_key, job.view, job.iteration) for job in jobs],
                          timestep_range=t_range(jobs[0]), guidance=cfg.guidance)

    def edit_one(job: EditJob, scene):
        return edit_many([job], scene)[0]

    return edit_one, edit_many

def take_edits(ctx: EditContext, st: EditState, arrivals: list[EditedView],
               horizon: int) -> EditState:
    """``st`` with the edited views ``arrivals`` as training images (in arrival order).

    A local edit's image is ``mask * edit + (1 - mask) * photo``. An edit counts as made
    at t_min when its step is past ``horizon`` (or its explicit timestep is <= t_min).
    """
    images = [e.image for e in arrivals]
    if ctx.masks is not None:
        images = [blend(im, ctx.data.train_images[e.job.view], ctx.masks[e.job.view])
                  for im, e in zip(images, arrivals)]
    t_min = ctx.config.timestep_range[0]
    return apply_edits(st, [e.job.view for e in arrivals], images,
                       [e.job.step >= horizon if e.job.timestep is None
                        else e.job.timestep <= t_min for e in arrivals])


# -- chunks of training steps on the device --
class ChunkResult(NamedTuple):
    """What the host learns from a chunk (NumPy): ``losses`` float [k] of the completed
    steps, ``redo`` (a step asked for more room), ``plateau`` at the last completed step,
    and the chunk's step ``metrics`` ([length] each)."""

    losses: np.ndarray
    redo: bool
    plateau: bool
    metrics: dict


class ChunkScalars(NamedTuple):
    """A chunk's plain-number settings, traced (int32 scalars each, a pytree) so that runs
    differing only in them share one program.

    subtask: the spec's index; step0: the subtask's step at the chunk's start; n_active:
    steps to run (<= the chunk's length); stop_if_plateau: 1 ends the chunk at a plateau;
    earliest_end: :func:`earliest_end`; warmup, patience: the config's; stop_on_plateau:
    the limits' (0: no plateau is ever reported).
    """

    subtask: Any
    step0: Any
    n_active: Any
    stop_if_plateau: Any
    earliest_end: Any
    warmup: Any
    patience: Any
    stop_on_plateau: Any

    def on_device(self) -> "ChunkScalars":
        return jax.device_put(ChunkScalars(*(np.int32(int(v)) for v in self)))


# min_delta stays static.
@functools.partial(jax.jit, static_argnames=("length", "min_delta"))
def _edit_chunk(device: DeviceState, cameras, regions, run_key, scalars: ChunkScalars, *,
                length, min_delta):
    train_state, images, tracker = device
    step0, warmup, patience = scalars.step0, scalars.warmup, scalars.patience
    stop_if_plateau, stop_on_plateau = scalars.stop_if_plateau > 0, scalars.stop_on_plateau > 0
    window = tracker.recent.shape[0]
    key_sub = jax.random.fold_in(run_key, scalars.subtask)
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
            # A local edit's plateau is that of the loss inside its region: the frozen rest
            # adds a loss no step can lower.
            tracked &= jnp.any(region > 0)
            loss = m["region_loss"]
        tr = jax.tree_util.tree_map(functools.partial(jnp.where, tracked),
                                    track_loss(tr, loss, min_delta=min_delta), tr)
        return (st, tr), m

    def after(carry, m, i):
        tr = carry[1]
        plateau = (stop_on_plateau & (tr.count >= window) & (tr.since_best >= patience)
                   & (step0 + i + 1 >= scalars.earliest_end))
        return dict(m, plateau=plateau), plateau & stop_if_plateau

    (train_state, tracker), metrics = scan_steps(one, (train_state, tracker), scalars.n_active,
                                                 length=length, after=after)
    return train_state, tracker, metrics


def step_chunk(ctx: EditContext, st: EditState, spec: SubtaskSpec, limits: SubtaskLimits,
               num_steps: int, *, stop_if_plateau: bool) -> tuple[EditState, ChunkResult]:
    """Up to ``num_steps`` (<= CHUNK) steps of subtask ``spec``: a pure function of its inputs.

    Stops early after a step that asks for a redo (not counted) or, when
    ``stop_if_plateau``, at a plateau (counted from :func:`earliest_end` on; never
    without ``limits.stop_on_plateau``).
    """
    cfg = ctx.config
    scalars = ChunkScalars(subtask=spec.index, step0=st.step, n_active=num_steps,
                           stop_if_plateau=stop_if_plateau, earliest_end=earliest_end(st, cfg),
                           warmup=cfg.warmup, patience=cfg.patience,
                           stop_on_plateau=limits.stop_on_plateau)
    train, tracker, metrics = _edit_chunk(*_chunk_args(ctx, st, scalars), length=CHUNK,
                                          min_delta=cfg.min_delta)
    metrics = jax.device_get(metrics)
    completed = metrics["ran"] & ~metrics["redo"]
    k = int(np.sum(completed))
    redo = bool(np.any(metrics["ran"] & metrics["redo"]))
    plateau = bool(k and metrics["plateau"][k - 1])
    density = tally_density(st.density, metrics["densify"], completed)
    return (st.replace(train=train, tracker=tracker, step=st.step + k, density=density),
            ChunkResult(np.asarray(metrics["loss"][:k]), redo, plateau, metrics))


def _chunk_args(ctx: EditContext, st: EditState, scalars: ChunkScalars) -> tuple:
    """:func:`_edit_chunk`'s arguments at ``st``, committed where they are, with the
    ``scalars`` uploaded."""
    return (*commit((st.device, ctx.data.train_cameras, ctx.masks, ctx.key)),
            scalars.on_device())


def compile_chunk(ctx: EditContext, st: EditState) -> None:
    """Compile (or read from the persistent cache) the training chunk for ``st``'s
    shapes without running it, so the first chunk starts at once; the edit does it on a
    thread while the difficulty schedule runs."""
    _edit_chunk.lower(*_chunk_args(ctx, st, ChunkScalars(*[0] * 8)), length=CHUNK,
                      min_delta=ctx.config.min_delta).compile()


#: earliest_end while the annealing has not reached t_min: no plateau ends the subtask.
NOT_YET = 2 ** 30


def earliest_end(st: EditState, cfg: ProEditConfig) -> int:
    """The first step count at which a plateau may end the subtask.

    ``patience`` steps after the dataset is fully edited and an edit was made at t_min
    (IN2N mode: no annealing condition). 0 while a view is unedited: a plateau is then
    reported at once, ending nothing, so a threaded source waits for the missing views.
    """
    if st.complete_at < 0:
        return 0
    if cfg.mode == "in2n":
        return st.complete_at + cfg.patience
    if st.annealed_at < 0:
        return NOT_YET
    return max(st.complete_at, st.annealed_at) + cfg.patience


def last_step(st: EditState, cfg: ProEditConfig, max_steps: int, can_wait: bool,
              guard: int | None = None) -> int:
    """Where the guard (``max_steps``, or ``guard`` when the time guard fired) ends the
    subtask; with a threaded source (``can_wait``) and views still unedited at the guard,
    ``patience`` steps after they all arrive."""
    guard = max_steps if guard is None else min(guard, max_steps)
    if not can_wait or st.complete_at < 0:
        return guard
    return max(guard, st.complete_at + cfg.patience)


def next_stop(step: int, cfg: ProEditConfig, last: int, source: EditSource) -> int:
    """The next step after ``step`` where the host must act: an exchange, a checkpoint,
    the end of the warm-up or of the subtask, or ``CHUNK`` steps on."""
    warmup = cfg.warmup
    stops = [last, step + CHUNK, (step // cfg.checkpoint_every + 1) * cfg.checkpoint_every]
    if step < warmup:
        stops.append(warmup)
    due = source.next_due(step - warmup)
    if due is not None:
        stops.append(warmup + due)
    return min(stops)


# -- the state machine --
@dataclasses.dataclass(frozen=True)
class Subtask:
    """What one subtask's loop reads and never changes.

    Attributes:
      ctx: the run's context.
      spec: the subtask.
      limits: its step guard and plateau test (:func:`jaxedit.edit.plan.subtask_limits`).
      source: its :class:`jaxedit.edit.buffer.EditSource` (entered by the caller).
      horizon: steps after the warm-up at which the annealed timestep reaches t_min.
      started: ``time.perf_counter()`` at the uninterrupted start (a resume keeps its seconds).
    """

    ctx: EditContext
    spec: SubtaskSpec
    limits: SubtaskLimits
    source: Any
    horizon: int
    started: float


class SubtaskLoop(NamedTuple):
    """Where a subtask's loop is (host side, immutable): the state ``st``, the step of the
    last exchange ``exchanged_at`` (so a redone chunk does not edit again), ``timed_out_at``
    (``max_seconds`` fired), ``converged`` (on its plateau) and ``done``."""

    st: EditState
    exchanged_at: int | None = None
    timed_out_at: int | None = None
    converged: bool = False
    done: bool = False


def prepare(ctx: EditContext, st: EditState, spec: SubtaskSpec) -> Subtask:
    """Subtask ``spec``'s fixed parts: its limits, its edit source and its annealing horizon."""
    cfg = ctx.config
    limits = ctx.hooks.limits_of(spec, subtask_limits(cfg, ctx.data.train_images.shape))
    key_sub = jax.random.fold_in(ctx.key, spec.index)
    order = view_order(len(ctx.data.train_images), jax.random.fold_in(key_sub, _ORDER))
    horizon = anneal_horizon(cfg, limits.max_steps)
    edit_one, edit_many = make_edit_fns(ctx, spec, horizon)
    trainer_device = next(iter(st.images.devices()))
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
    """The exchange due at the loop's step, one chunk of steps up to :func:`next_stop`,
    then the edits a pipelined source made beside them."""
    ctx, cfg, source = sub.ctx, sub.ctx.config, sub.source
    st, exchanged_at = loop.st, loop.exchanged_at
    s = st.step
    if s >= cfg.warmup and s != exchanged_at and source.due(s - cfg.warmup):
        st = take_edits(ctx, st, source.exchange(s - cfg.warmup, ctx.trainer.gaussians(st.train)),
                        sub.horizon)
        exchanged_at = s
    # Before every view is edited, a sync source edits the rest at its own steps; a
    # thread's edits are waited for.
    stop_if_plateau = bool(st.edited.all()) or source.can_wait
    last = last_step(st, cfg, sub.limits.max_steps, source.can_wait, loop.timed_out_at)
    st, chunk = step_chunk(ctx, st, sub.spec, sub.limits, next_stop(s, cfg, last, source) - s,
                           stop_if_plateau=stop_if_plateau)
    if chunk.redo:
        k = len(chunk.losses)
        st = st.replace(train=grow_for_redo(st.train, jax.tree_util.tree_map(
            lambda a: a[k], chunk.metrics)))
    st = take_edits(ctx, st, source.collect(), sub.horizon)
    st = st.replace(seconds=time.perf_counter() - sub.started)
    timed_out_at = loop.timed_out_at
    if timed_out_at is None and cfg.max_seconds is not None and st.seconds >= cfg.max_seconds:
        timed_out_at = st.step
    return loop._replace(st=st, exchanged_at=exchanged_at, timed_out_at=timed_out_at), chunk


def await_views(sub: Subtask, st: EditState) -> EditState:
    """``st`` with the edits that arrive until every view has one: the trainer's only
    wait. A deterministic source returns at once."""
    arrived: list[EditedView] = []

    def complete() -> bool:
        edited = st.edited.copy()
        edited[[e.job.view for e in arrived]] = True
        return bool(edited.all())

    sub.source.wait_for(complete, timeout=WAIT_S, on_edits=arrived.extend)
    return take_edits(sub.ctx, st, arrived, sub.horizon)


def settle(sub: Subtask, loop: SubtaskLoop, chunk: ChunkResult) -> tuple[SubtaskLoop, bool]:
    """(the loop after the chunk's end, whether a checkpoint is due there).

    A plateau on the complete dataset converges; on a partly edited one a threaded
    source waits for the missing views and looks for a new plateau. At the guard the
    subtask ends, after waiting for missing views where waiting brings them.
    """
    cfg, st = sub.ctx.config, loop.st
    if chunk.plateau and not st.edited.all() and sub.source.can_wait:
        st = await_views(sub, st)
        st = st.replace(tracker=st.tracker._replace(since_best=jnp.int32(0)))
        return loop._replace(st=st), False
    if chunk.plateau and st.edited.all():
        return loop._replace(converged=True, done=True), False
    if st.step >= last_step(st, cfg, sub.limits.max_steps, sub.source.can_wait,
                            loop.timed_out_at):
        if not st.edited.all():
            # Never end a subtask on a dataset not fully updated to e(r_i).
            st = await_views(sub, st)
            if st.edited.all():
                return loop._replace(st=st), False
        return loop._replace(st=st, done=True), False
    return loop, st.step % cfg.checkpoint_every == 0 and not chunk.redo


def terminate(loop: SubtaskLoop) -> bool:
    return loop.done


def postprocess(sub: Subtask, loop: SubtaskLoop) -> tuple[EditState, dict]:
    """(the state at the end of the subtask, its info); call after the source is closed."""
    cfg, source, plateau = sub.ctx.config, sub.source, sub.limits.stop_on_plateau
    st = loop.st.replace(seconds=time.perf_counter() - sub.started,
                             utilisation=loop.st.utilisation.add(source.utilisation))
    guard = None if loop.converged or not plateau else (
        "seconds" if loop.timed_out_at is not None else "steps")
    # a fixed budget has no plateau to reach: converged is None
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
        st = begin_subtask(ctx, st, spec.kind)
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
