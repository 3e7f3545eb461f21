"""The ablation's controls as the method sees them: a :class:`ProEditConfig` plus what only a
control reads, plugged into an edit through :class:`jaxedit.edit.hooks.EditHooks`.

- ND-k (``nd_subtasks``): the same edit at r = 1 as k subtasks (a plan transformation);
- subtasks of fixed length (``subtask_steps``): each runs exactly that many steps, no plateau;
- editor calls at chosen steps (``edit_plan``): :class:`ScheduledEditSource`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxedit.edit.buffer import EditFn, EditJob, EditManyFn, SyncEditSource
from jaxedit.edit.hooks import EditHooks
from jaxedit.edit.plan import ProEditConfig, SubtaskLimits, plan_subtasks
from jaxedit.errors import DataError


@dataclasses.dataclass(frozen=True)
class ControlConfig(ProEditConfig):
    """A control's settings: the method's, and what only the control reads.

    Attributes:
      nd_subtasks: ND mode only: k edit subtasks, all at r = 1 (ND-k: ND with the opacity
        resets, initial sweeps and subtask count of a k-subtask ProEdit run).
      subtask_steps: fixed lengths of the subtasks in plan order (the equal-budget
        controls): each runs exactly that many steps, no plateau test, no guard (None: the
        plateau and ``max_steps`` decide).
      edit_plan: explicit editor exchanges per subtask in plan order: each entry None
        (every ``edit_every`` steps) or a tuple of ``(step, count, timestep)``: at ``step``
        steps after the warm-up edit the next ``count`` views of the cyclic order, at
        ``timestep`` (None: annealed by the step) (:class:`ScheduledEditSource`).
      refine_reset: the method's field, on here: the registered study resets the opacities
        at r_0 as at every other subtask, the protocol its seeds were run with.
    """

    refine_reset: bool = True
    nd_subtasks: int = 1
    subtask_steps: tuple[int, ...] | None = None
    edit_plan: tuple | None = None

    def __post_init__(self):
        super().__post_init__()
        if self.nd_subtasks < 1 or (self.nd_subtasks > 1 and self.mode != "nd"):
            raise DataError("nd_subtasks", f"must be >= 1, and 1 unless mode is nd, got "
                                           f"{self.nd_subtasks} ({self.mode})")
        if self.subtask_steps is not None and (
                not len(self.subtask_steps) or min(self.subtask_steps) < 1):
            raise DataError("subtask_steps", f"need lengths >= 1, got {self.subtask_steps}")
        if self.edit_plan is not None:
            if self.asynchronous:
                raise DataError("edit_plan", "an explicit edit schedule is deterministic: "
                                             "not with asynchronous")
            for entry in self.edit_plan:
                steps = [] if entry is None else [int(x[0]) for x in entry]
                if entry is not None and (not steps or steps[0] < 0 or any(
                        b <= a for a, b in zip(steps, steps[1:])) or any(
                        int(x[1]) < 1 for x in entry)):
                    raise DataError("edit_plan", f"each subtask's exchanges need increasing "
                                                 f"steps >= 0 and counts >= 1, got {entry}")

    def hooks(self) -> EditHooks:
        """The seams this control changes (none for a plain method's settings)."""
        return EditHooks(plan=self._plan, limits=None if self.subtask_steps is None else self._limits,
                         edit_source=None if self.edit_plan is None else self._edit_source)

    def _plan(self, specs):
        if self.nd_subtasks > 1:  # ND-k: the one edit at r = 1, k times
            edit = next(s for s in specs if s.kind == "edit")
            specs = plan_subtasks("nd", [0.0] + [1.0] * self.nd_subtasks,
                                  [edit.difficulty] + [0.0] * (self.nd_subtasks - 1),
                                  refine_first=specs[0].kind == "refine",
                                  consolidate=specs[-1].kind == "consolidate")
        for name, given in (("subtask_steps", self.subtask_steps), ("edit_plan", self.edit_plan)):
            if given is not None and len(given) != len(specs):
                raise DataError(name, f"{len(given)} entries for a plan of {len(specs)} subtasks")
        return specs

    def _limits(self, spec, limits: SubtaskLimits) -> SubtaskLimits:
        return SubtaskLimits(int(self.subtask_steps[spec.index]), False)

    def _edit_source(self, spec, edit_fn, order, *, edit_many=None, trainer_device=None):
        exchanges = self.edit_plan[spec.index]
        if exchanges is None:
            return None
        return ScheduledEditSource(edit_fn, order, exchanges=exchanges,
                                   trainer_device=trainer_device, edit_many=edit_many)


class ScheduledEditSource(SyncEditSource):
    """Deterministic edits at an explicit list of exchanges instead of every ``every`` steps.

    ``exchanges``: ``(step, count, timestep)`` triples with strictly increasing steps; at
    ``step`` the next ``count`` views of the cyclic ``order`` are edited (edits are numbered
    through the subtask, as :class:`SyncEditSource` numbers them), at ``timestep`` (None: the
    subtask's annealing of the step). The equal-budget controls of the ablation use it: a
    fractional schedule (edit k at step round(k L / calls)) matches any number of editor
    calls exactly, and ProEdit's own exchanges replayed in one subtask match its sweeps and
    timesteps (:mod:`.methods`).
    """

    def __init__(self, edit_fn: EditFn, order: np.ndarray, *, exchanges, trainer_device=None,
                 edit_many: EditManyFn | None = None):
        super().__init__(edit_fn, order, every=1, initial_sweep=False,
                         trainer_device=trainer_device, edit_many=edit_many)
        self.exchanges = tuple((int(s), int(c), None if t is None else float(t))
                               for s, c, t in exchanges)
        steps = [s for s, _, _ in self.exchanges]
        if any(b <= a for a, b in zip(steps, steps[1:])) or (steps and steps[0] < 0) or any(
                c < 1 for _, c, _ in self.exchanges):
            raise ValueError(f"exchanges need increasing steps >= 0 and counts >= 1, got "
                             f"{self.exchanges}")
        self._at = {}
        first = 0
        for s, c, t in self.exchanges:
            self._at[s] = (first, c, t)
            first += c

    def due(self, step: int) -> bool:
        return step in self._at

    def next_due(self, step: int) -> int | None:
        later = [s for s in self._at if s > step]
        return min(later) if later else None

    def jobs_at(self, step: int) -> list[EditJob]:
        if step not in self._at:
            return []
        first, count, t = self._at[step]
        n = len(self.order)
        return [EditJob(int(self.order[i % n]), i, step, t) for i in range(first, first + count)]
