"""Hooks through which a study changes an edit (None keeps the method's own way)."""

from __future__ import annotations

import dataclasses
from typing import Callable

from .plan import SubtaskLimits, SubtaskSpec


@dataclasses.dataclass(frozen=True)
class EditHooks:
    """A study's changes to an edit.

    Attributes:
      schedule: ``schedule(difficulty) -> Schedule`` replacing the configured scheduler.
      plan: ``plan(specs) -> specs``: replaces the laid-out subtasks before training.
      limits: ``limits(spec, limits) -> SubtaskLimits``: a subtask's step guard and plateau.
      edit_source: ``edit_source(spec, edit_fn, order, *, edit_many, trainer_device)`` -> an
        edit source for subtask ``spec``, or None for the method's periodic one.
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
