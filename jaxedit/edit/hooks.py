"""Seams where a custom scheduler or a study changes an edit without the method's
config knowing: an :class:`EditHooks` passed to :func:`jaxedit.pipelines.edit.run_edit`.
Every hook is optional; None keeps the method's own way.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

from .plan import SubtaskLimits, SubtaskSpec


@dataclasses.dataclass(frozen=True)
class EditHooks:
    """A study's changes to an edit.

    Attributes:
      schedule: ``schedule(difficulty) -> Schedule``: the ratios of a ProEdit run from r = 0
        instead of the configured scheduler (:mod:`jaxedit.edit.schedule`); ``difficulty``
        is the run's memoised d(r_a, r_b).
      plan: ``plan(specs) -> specs``: the laid-out subtasks (r_0, the edit steps, r_n) of a run
        from r = 0, replaced before any training (may raise :class:`jaxedit.DataError`).
      limits: ``limits(spec, limits) -> SubtaskLimits``: subtask ``spec``'s step guard and
        plateau test, given the method's.
      edit_source: ``edit_source(spec, edit_fn, order, *, edit_many, trainer_device)`` -> an
        edit source (:mod:`jaxedit.edit.buffer`'s protocol) for subtask ``spec``, or None for
        the method's periodic one.
    """

    schedule: Callable | None = None
    plan: Callable[[tuple[SubtaskSpec, ...]], tuple[SubtaskSpec, ...]] | None = None
    limits: Callable[[SubtaskSpec, SubtaskLimits], SubtaskLimits] | None = None
    edit_source: Callable | None = None

    def planned(self, specs: tuple[SubtaskSpec, ...]) -> tuple[SubtaskSpec, ...]:
        """The subtasks a run from r = 0 trains."""
        return specs if self.plan is None else tuple(self.plan(specs))

    def limits_of(self, spec: SubtaskSpec, limits: SubtaskLimits) -> SubtaskLimits:
        """Subtask ``spec``'s limits."""
        return limits if self.limits is None else self.limits(spec, limits)


#: No change: the method as configured.
NO_HOOKS = EditHooks()
