"""Where an edit run is (:class:`EditState`) and the pure functions that advance it:
:func:`init_state`, :func:`begin_subtask`, :func:`apply_edits`, :func:`finish_subtask`.

:class:`LossTracker` advances on the device (:func:`track_loss`), :class:`DensityTally` on
the host from a chunk's metrics (:func:`tally_density`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..gaussians import grow
from ..raster.render import next_capacity
from ..train import put_image
from .buffer import Utilisation
from .context import EditContext


class LossTracker(NamedTuple):
    """Running mean of the last ``window`` losses and steps since its last minimum (a pytree).

    recent: float32 [window] ring buffer; count: int32, losses seen; best: float32, lowest
    running mean so far (inf before the window is full); since_best: int32, steps since.
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

    refinements: maintenance steps; created / culled: Gaussians; budget_limited: steps that
    created exactly t(n); cap_limited: steps where the hard cap bounded creation; shortfall:
    Gaussians those steps wanted (min(t(n), candidates)) but had no room for.
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


class DeviceState(NamedTuple):
    """The device part of an edit's state (a pytree).

    Attributes:
      train: the trainer's state pytree (Gaussians, optimiser, densify stats).
      images: float32 [N, H, W, 3], the training images as of now.
      tracker: the loss tracker of the current subtask.
    """

    train: Any
    images: jax.Array
    tracker: LossTracker


@dataclasses.dataclass(frozen=True)
class HostState:
    """The host part of an edit's state: plain values.

    Attributes:
      subtask: index of the current subtask in the plan.
      step: steps already taken inside it (0: not started, opacity not yet reset).
      edited: bool [N] (NumPy), views edited at least once in the current subtask.
      records: one dict per finished subtask (schedule.json entries).
      seconds: wall time spent in the current subtask before the last restart.
      utilisation: buffer counters summed over the run.
      complete_at: the subtask's step when every view had been edited (-1: not yet); it
        ends no earlier than ``patience`` steps later.
      annealed_at: the subtask's step when the first edit made at t_min arrived (-1: not
        yet); it ends no earlier than ``patience`` steps later.
      density: the subtask's :class:`DensityTally`.
    """

    subtask: int
    step: int
    edited: np.ndarray
    records: tuple = ()
    seconds: float = 0.0
    utilisation: Utilisation = dataclasses.field(default_factory=Utilisation)
    complete_at: int = -1
    annealed_at: int = -1
    density: DensityTally = DensityTally()


HOST_FIELDS = tuple(f.name for f in dataclasses.fields(HostState))


def _part(part: str, name: str) -> property:
    return property(lambda st: getattr(getattr(st, part), name),
                    doc=f"``{part}.{name}`` (read-only)")


@dataclasses.dataclass(frozen=True)
class EditState:
    """Where a run is: everything needed to continue it exactly (never mutated).

    ``device`` (:class:`DeviceState`) and ``host`` (:class:`HostState`); their fields read
    as the state's own (``st.train``, ``st.step``), :meth:`replace` changes them by name.
    """

    device: DeviceState
    host: HostState

    @staticmethod
    def create(**fields) -> "EditState":
        """The state of :class:`DeviceState`'s and :class:`HostState`'s ``fields``."""
        device = {k: fields.pop(k) for k in DeviceState._fields}
        return EditState(DeviceState(**device), HostState(**fields))

    def replace(self, **changes) -> "EditState":
        """This state with the fields ``changes`` (of either part) replaced."""
        device = {k: changes.pop(k) for k in DeviceState._fields if k in changes}
        return EditState(self.device._replace(**device) if device else self.device,
                         dataclasses.replace(self.host, **changes) if changes else self.host)


# Every field of either part reads as the state's own (``st.train``, ``st.step``).
for _name in DeviceState._fields:
    setattr(EditState, _name, _part("device", _name))
for _name in HOST_FIELDS:
    setattr(EditState, _name, _part("host", _name))
del _name


def init_state(ctx: EditContext, gaussians, images: np.ndarray | None = None, *,
               capacity: int | None = None, max_intersections: int | None = None) -> EditState:
    """A run at its very beginning: the input scene, the original photos as training images.

    ``capacity`` / ``max_intersections``: the slots and tile buffer to start with (a branch
    takes its parent's, so the parent's compiled programs fit; None: sized from the scene).
    """
    images = ctx.data.train_images if images is None else images
    # 1.5x room to densify without a recompile, on the ladder the reconstruction used
    want = (next_capacity(math.ceil(1.5 * int(gaussians.num_alive()))) if capacity is None
            else int(capacity))
    capacity = min(max(want, gaussians.capacity), max(ctx.trainer.settings.densify.max_gaussians,
                                                     gaussians.capacity))
    if capacity > gaussians.capacity:
        gaussians = grow(gaussians, capacity)
    train = ctx.trainer.init(gaussians, None if max_intersections else ctx.data.train_cameras)
    if max_intersections:
        train = dataclasses.replace(train, max_intersections=int(max_intersections))
    return EditState.create(
        subtask=0, step=0, train=train, images=jax.device_put(np.asarray(images, np.float32)),
        edited=np.zeros((len(images),), bool), tracker=LossTracker.init(ctx.config.loss_window))


def begin_subtask(ctx: EditContext, st: EditState, kind: str = "edit") -> EditState:
    """The state at the start of a subtask of ``kind`` (:class:`SubtaskSpec`'s): opacity
    reset (paper 3.3 (1); not in IN2N mode, nor in the refinement r_0 unless
    ``refine_reset``), nothing edited yet, a fresh loss tracker."""
    cfg = ctx.config
    reset = kind != "refine" or cfg.refine_reset
    train = ctx.trainer.restart(st.train, reset_opacity=reset) if cfg.mode != "in2n" else st.train
    return st.replace(step=0, train=train, edited=np.zeros(len(st.edited), bool),
                       tracker=LossTracker.init(ctx.config.loss_window), seconds=0.0,
                       complete_at=-1, annealed_at=-1, density=DensityTally())


def apply_edits(st: EditState, views, images, annealed=()) -> EditState:
    """``st`` with edited ``images`` [K, H, W, 3] as the training images of ``views`` [K].

    ``annealed`` (bool [K], optional): the edit was made at t_min. Once every view is edited
    and an annealed edit arrived, the loss tracker starts afresh.
    """
    if not len(views):
        return st
    data, edited = st.images, st.edited.copy()
    for v, image in zip(views, images):
        data = put_image(data, int(v), image)
        edited[int(v)] = True
    complete_at = st.step if st.complete_at < 0 and edited.all() else st.complete_at
    annealed_at = st.step if st.annealed_at < 0 and any(annealed) else st.annealed_at
    tracker = st.tracker
    if min(complete_at, annealed_at) >= 0 > min(st.complete_at, st.annealed_at):
        # an earlier best was against other training images and would end the subtask early
        tracker = LossTracker.init(len(tracker.recent))
    return st.replace(images=data, edited=edited, complete_at=complete_at,
                               annealed_at=annealed_at, tracker=tracker)


def finish_subtask(st: EditState, record: dict) -> EditState:
    """The state after a finished subtask: its record kept, the next subtask not begun."""
    return st.replace(records=tuple(st.records) + (record,), subtask=st.subtask + 1,
                               step=0, seconds=0.0, complete_at=-1, annealed_at=-1,
                               density=DensityTally())
