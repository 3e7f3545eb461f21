"""The ablation's methods (rows) and how their budgets follow ProEdit's run of the same seed.

Every method runs the same trainer, W, patience, ``edit_every``, ``refine_every`` and step
guard; :func:`method_config` builds each one's :class:`.controls.ControlConfig`.
The followers take ProEdit's steps and training editor calls exactly: ``nd_equal`` by a
fractional edit schedule (:func:`fractional_exchanges`: the k-th single edit at step
round(k (L - W) / (R + 1)), not an integer ``edit_every``), ``nd_replay`` by replaying
ProEdit's own exchanges (:func:`replay_exchanges`: its sweeps, calls and timesteps, so as
many hottest-timestep edits) in one subtask without its opacity resets.
:func:`edits_per_subtask` counts the calls a periodic schedule makes, :class:`CallLog`
records every call's timestep (and the simulated editor's mode), :func:`timestep_bands`
bins them and :func:`sweep_agreement` measures how consistently the editor's modes were
drawn.
"""

from __future__ import annotations

import numpy as np

from jaxedit.edit.buffer import SyncEditSource
from jaxedit.edit.plan import anneal_timestep
from jaxedit.errors import DataError

from .controls import ControlConfig

METHODS = ("proedit", "nd", "nd_equal", "nd_replay", "nd_k", "uniform", "in2n")
#: The default rows of the mechanism variant (in2n, one more trainer compile and no
#: schedule, is asked for explicitly).
MAIN_METHODS = ("proedit", "nd", "nd_equal", "nd_replay", "nd_k", "uniform")
#: Methods that take ProEdit's run of the same seed as their budget.
FOLLOWERS = ("nd_equal", "nd_replay", "nd_k", "uniform", "in2n")
#: The rows of the negative-control variants.
CONTROL_METHODS = ("proedit", "nd")
#: ProEdit's subtask count by instruction kind (paper: ~8 for geometry, ~4 for texture edits;
#: "shape" is the simulated editor's geometry kind, "geometry" the bundled editor's).
TARGET_SUBTASKS = {"shape": 8, "geometry": 8}
TARGET_SUBTASKS_DEFAULT = 4
#: Timestep bands of the per-run call counts: the SDEdit range split in this many equal
#: parts, band 0 the hottest (t_max included).
BANDS = 4


def periodic_exchanges(steps: int, *, warmup: int, every: int, views: int,
                       initial_sweep: bool, horizon: int | None = None,
                       timestep_range: tuple[float, float] | None = None) -> list[tuple]:
    """The ``(step after the warm-up, views edited, timestep)`` exchanges a periodic subtask
    of ``steps`` steps makes (what a subtask does with :class:`SyncEditSource`); the
    timestep is its annealing over ``horizon`` when given, else None."""
    source = SyncEditSource(lambda job, scene: None, list(range(views)), every=every,
                            initial_sweep=initial_sweep)
    out = []
    for s in range(0, max(steps - warmup, 0), every):
        count = len(source.jobs_at(s))
        t = None if horizon is None else anneal_timestep(s, horizon, *timestep_range)
        out.append((s, count, t))
    return out


def fractional_exchanges(length: int, calls: int, *, warmup: int, views: int) -> tuple:
    """Exchanges of one subtask of ``length`` steps that make exactly ``calls`` editor calls:
    the initial sweep (every view) right after the warm-up, then the R = calls - views single
    edits at steps round(k (L - W) / (R + 1)), k = 1..R, after it (evenly spread, none on the
    sweep or past the end). A DataError when the subtask has no room for them."""
    room, rest = length - warmup, calls - views
    if rest < 0 or room < 1 or rest > room - 1:
        raise DataError("nd_equal", f"{calls} editor calls do not fit one subtask of {length} "
                                    f"steps ({views} views, warm-up {warmup})")
    singles = [int(round(k * room / (rest + 1))) for k in range(1, rest + 1)]
    return ((0, views, None),) + tuple((s, 1, None) for s in singles)


def replay_exchanges(lengths: list[int], *, warmup: int, every: int, views: int, horizon: int,
                     timestep_range: tuple[float, float]) -> tuple:
    """ProEdit's edit subtasks of ``lengths`` replayed in one subtask: each one's exchanges
    (its initial sweep and single edits, at the timesteps its annealing gave them) shifted
    by the steps before it, so the calls, sweeps and hottest-timestep edits are ProEdit's
    and only the opacity resets (and the ratios) differ. The first warm-up is the
    subtask's own; a later one's steps are trained with the editor's data, as in ProEdit."""
    out, offset = [], 0
    for length in lengths:
        for s, c, t in periodic_exchanges(length, warmup=warmup, every=every, views=views,
                                          initial_sweep=True, horizon=horizon,
                                          timestep_range=timestep_range):
            out.append((offset + s, c, t))
        offset += length
    return tuple(out)


def timestep_bands(timesteps, timestep_range: tuple[float, float], bands: int = BANDS) -> list[int]:
    """Editor calls per timestep band ([bands], band 0 the hottest: t_max down to t_max -
    (t_max - t_min) / bands; t_max itself is in band 0)."""
    lo, hi = timestep_range
    width = max(hi - lo, 1e-12) / bands
    out = [0] * bands
    for t in timesteps:
        out[min(max(int((hi - float(t)) / width), 0), bands - 1)] += 1
    return out


def edits_per_subtask(steps: int, *, warmup: int, every: int, views: int,
                      initial_sweep: bool) -> int:
    """Training edits of a deterministic subtask of ``steps`` steps: the subtask exchanges with
    the editor at steps s >= W with (s - W) % every == 0 and s < steps
    (:class:`jaxedit.edit.buffer.SyncEditSource` decides how many views each exchange edits)."""
    source = SyncEditSource(lambda job, scene: None, list(range(views)), every=every,
                            initial_sweep=initial_sweep)
    return sum(len(source.jobs_at(s)) for s in range(0, max(steps - warmup, 0), every))


def sweep_agreement(modes, edits: list[int], views: int) -> list[list[float]]:
    """Per subtask, per complete sweep (``views`` consecutive edits: every view once), the
    fraction of views drawn in the sweep's most common mode. ``modes`` int [sum(edits)] in
    the order the edits were made, ``edits`` the count of each subtask."""
    modes = np.asarray(modes, int)
    if len(modes) != sum(edits):
        raise ValueError(f"{len(modes)} recorded modes for {sum(edits)} edits")
    out, at = [], 0
    for count in edits:
        sub = modes[at:at + count]
        at += count
        out.append([float(np.bincount(sub[i:i + views]).max()) / views
                    for i in range(0, count - views + 1, views)])
    return out


def match_edit_every(target_edits: int, steps: list[int], *, warmup: int, views: int,
                     most: int) -> int:
    """The ``edit_every`` (1 .. most) whose training edits over subtasks of ``steps`` come
    closest to ``target_edits`` (ties: the larger, fewer exchanges)."""
    def edits(every):
        return sum(edits_per_subtask(s, warmup=warmup, every=every, views=views,
                                     initial_sweep=True) for s in steps)
    return min(range(1, most + 1), key=lambda e: (abs(edits(e) - target_edits), -e))


class CallLog:
    """An editor that remembers every edit call: its timestep (the middle of the range it
    was given) and, where the editor draws modes (the simulated editor's
    :meth:`edit_with_mode`), the mode; everything else is the editor's. Batched calls
    (``edit_many``) count one call per view. With ``observe`` (``(original, edited) ->
    anything``), what it says of each call's result, in ``observed`` (the ablation: which
    view and which outcome, :func:`jaxedit_lab.ablation._edit_observer`)."""

    def __init__(self, editor, observe=None):
        self.editor = editor
        self.modes: list[int] | None = [] if hasattr(editor, "edit_with_mode") else None
        self.timesteps: list[float] = []
        self.observe = observe
        self.observed: list = []

    def __getattr__(self, name):
        return getattr(self.editor, name)

    @property
    def calls(self) -> int:
        return len(self.timesteps)

    def _t(self, kwargs) -> float:
        lo, hi = kwargs.get("timestep_range", (0.02, 0.98))
        return 0.5 * (float(lo) + float(hi))

    def _seen(self, originals, outputs) -> None:
        if self.observe is not None:
            self.observed += [self.observe(o, x) for o, x in zip(originals, outputs)]

    def edit(self, image, original, embedding, key, **kwargs):
        self.timesteps.append(self._t(kwargs))
        if self.modes is None:
            out = self.editor.edit(image, original, embedding, key, **kwargs)
        else:
            out, mode = self.editor.edit_with_mode(image, original, embedding, key, **kwargs)
            self.modes.append(mode)
        self._seen([original], [out])
        return out

    def edit_many(self, images, originals, embedding, keys, **kwargs):
        out = self.editor.edit_many(images, originals, embedding, keys, **kwargs)
        self.timesteps += [self._t(kwargs)] * len(images)
        self._seen(originals, out)
        return out


def method_config(method: str, *, kind: str, lead: dict | None, warmup: int, patience: int,
                  max_steps: int, edit_every: int, views: int):
    """The :class:`.controls.ControlConfig` of ``method``; ``lead`` is ProEdit's run of the same seed
    ({"steps": per subtask, "edits": training edits per subtask, "horizon": its annealing
    horizon}). nd_equal and nd_replay make exactly ProEdit's steps and editor calls."""
    # the difficulty over 3 views and no plotted curve: the schedule's editor calls are
    # bookkeeping here, not part of any method's training budget
    common = dict(max_steps=max_steps, patience=patience, edit_every=edit_every,
                  asynchronous=False, pipelined=False, difficulty_views=3, curve_points=2)
    if method == "proedit":
        return ControlConfig.for_mode("proedit", warmup=warmup, target_subtasks=TARGET_SUBTASKS.get(
            kind, TARGET_SUBTASKS_DEFAULT), **common)
    if method == "nd":
        return ControlConfig.for_mode("nd", warmup=warmup, **common)
    steps, n = lead["steps"], len(lead["steps"]) - 2  # r0, n edit subtasks, rn
    if method == "uniform":
        return ControlConfig.for_mode("proedit", warmup=warmup, subtasks=n, **common)
    if method == "in2n":
        return ControlConfig.for_mode("in2n", max_steps=sum(steps), patience=patience,
                                      edit_every=edit_every, asynchronous=False,
                                      pipelined=False, curve_points=2)
    fixed = dict(common, anneal_steps=lead["horizon"])
    if method == "nd_k":
        return ControlConfig.for_mode("nd", warmup=warmup, nd_subtasks=n,
                                      subtask_steps=tuple(steps), **fixed)
    lengths = (steps[0], sum(steps[1:-1]), steps[-1])
    if method == "nd_equal":
        # r0 and rn as ProEdit's (same lengths, same periodic edits); the one edit subtask
        # gets the calls of ProEdit's n edit subtasks exactly, spread evenly
        middle = fractional_exchanges(lengths[1], sum(lead["edits"][1:-1]), warmup=warmup,
                                      views=views)
        return ControlConfig.for_mode("nd", warmup=warmup, subtask_steps=lengths,
                                      edit_plan=(None, middle, None), **fixed)
    if method == "nd_replay":
        base = ControlConfig.for_mode("nd", warmup=warmup, **common)
        middle = replay_exchanges(list(steps[1:-1]), warmup=warmup, every=edit_every,
                                  views=views, horizon=lead["horizon"],
                                  timestep_range=tuple(base.timestep_range))
        return ControlConfig.for_mode("nd", warmup=warmup, subtask_steps=lengths,
                                      edit_plan=(None, middle, None), **fixed)
    raise ValueError(method)
