"""The ablation's methods (rows) and how their budgets follow ProEdit's run of the same seed.

Every method runs the same trainer, W, patience, ``edit_every``, ``refine_every`` and step
guard; :func:`method_config` builds each one's :class:`jaxedit.edit.plan.ProEditConfig`.
The followers take ProEdit's steps and training editor calls (:func:`match_edit_every`
counts the calls a schedule of subtasks makes, :func:`edits_per_subtask`), and
:func:`sweep_agreement` measures how consistently the editor's modes were drawn.
"""

from __future__ import annotations

import numpy as np

from ...edit.buffer import SyncEditSource
from ...edit.plan import ProEditConfig

METHODS = ("proedit", "nd", "nd_equal", "nd_k", "uniform", "in2n")
#: The default rows of the mechanism variant (in2n, one more trainer compile and no
#: schedule, is asked for explicitly).
MAIN_METHODS = ("proedit", "nd", "nd_equal", "nd_k", "uniform")
#: Methods that take ProEdit's run of the same seed as their budget.
FOLLOWERS = ("nd_equal", "nd_k", "uniform", "in2n")
#: The rows of the negative-control variants.
CONTROL_METHODS = ("proedit", "nd")
#: ProEdit's subtask count by instruction kind (paper: ~8 for geometry, ~4 for texture edits).
TARGET_SUBTASKS = {"shape": 8}
TARGET_SUBTASKS_DEFAULT = 4


def edits_per_subtask(steps: int, *, warmup: int, every: int, views: int,
                      initial_sweep: bool) -> int:
    """Training edits of a deterministic subtask of ``steps`` steps: the driver exchanges with
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


class ModeLog:
    """An editor that remembers the mode of every ``edit`` call (the mode draw is the
    simulated editor's :meth:`edit_with_mode`); everything else is the editor's."""

    def __init__(self, editor):
        self.editor = editor
        self.modes: list[int] = []

    def __getattr__(self, name):
        return getattr(self.editor, name)

    def edit(self, image, original, embedding, key, **kwargs):
        out, mode = self.editor.edit_with_mode(image, original, embedding, key, **kwargs)
        self.modes.append(mode)
        return out


def method_config(method: str, *, kind: str, lead: dict | None, warmup: int, patience: int,
                  max_steps: int, edit_every: int, views: int):
    """The :class:`ProEditConfig` of ``method``; ``lead`` is ProEdit's run of the same seed
    ({"steps": per subtask, "edits": training edits, "horizon": its annealing horizon})."""
    # the difficulty over 3 views and no plotted curve: the schedule's editor calls are
    # bookkeeping here, not part of any method's training budget
    common = dict(max_steps=max_steps, patience=patience, edit_every=edit_every,
                  asynchronous=False, difficulty_views=3, curve_points=2)
    if method == "proedit":
        return ProEditConfig.for_mode("proedit", warmup=warmup, target_subtasks=TARGET_SUBTASKS.get(
            kind, TARGET_SUBTASKS_DEFAULT), **common)
    if method == "nd":
        return ProEditConfig.for_mode("nd", warmup=warmup, **common)
    steps, n = lead["steps"], len(lead["steps"]) - 2  # r0, n edit subtasks, rn
    if method == "uniform":
        return ProEditConfig.for_mode("proedit", warmup=warmup, subtasks=n, **common)
    if method == "in2n":
        return ProEditConfig.for_mode("in2n", max_steps=sum(steps), patience=patience,
                                      edit_every=edit_every, asynchronous=False, curve_points=2)
    fixed = dict(common, anneal_steps=lead["horizon"])
    if method == "nd_k":
        return ProEditConfig.for_mode("nd", warmup=warmup, nd_subtasks=n,
                                      subtask_steps=tuple(steps), **fixed)
    if method == "nd_equal":
        lengths = (steps[0], sum(steps[1:-1]), steps[-1])
        every = match_edit_every(lead["edits"], list(lengths), warmup=warmup, views=views,
                                 most=edit_every)
        return ProEditConfig.for_mode("nd", warmup=warmup, subtask_steps=lengths,
                                      **dict(fixed, edit_every=every))
    raise ValueError(method)
