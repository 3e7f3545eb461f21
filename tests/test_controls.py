"""The lab's controls reach the method only through its public seams (EditHooks)."""

import numpy as np
import pytest

from jaxedit import DataError
from jaxedit.edit.hooks import NO_HOOKS
from jaxedit.edit.plan import ProEditConfig, SubtaskLimits, plan_subtasks
from jaxedit_lab.ablation.controls import ControlConfig, ScheduledEditSource


def test_the_methods_config_holds_no_field_only_a_control_reads():
    import dataclasses

    method = {f.name for f in dataclasses.fields(ProEditConfig)}
    assert not method & {"nd_subtasks", "subtask_steps", "edit_plan"}


def test_a_plain_control_changes_nothing():
    hooks = ControlConfig.for_mode("proedit").hooks()
    plan = plan_subtasks("proedit", [0.0, 0.5, 1.0], [0.1, 0.2])
    assert hooks.planned(plan) == plan and hooks.limits is None and hooks.edit_source is None
    assert NO_HOOKS.planned(plan) == plan


def test_nd_k_repeats_the_one_edit_at_r_1_k_times():
    nd = plan_subtasks("nd", [0.0, 1.0], [0.3])
    specs = ControlConfig.for_mode("nd", nd_subtasks=3).hooks().planned(nd)
    assert [(s.index, s.name, s.ratio, s.difficulty, s.kind) for s in specs] == [
        (0, "r0", 0.0, None, "refine"), (1, "r1", 1.0, 0.3, "edit"), (2, "r2", 1.0, 0.0, "edit"),
        (3, "r3", 1.0, 0.0, "edit"), (4, "rn", 1.0, None, "consolidate")]


def test_fixed_lengths_replace_the_guard_and_the_plateau_and_must_match_the_plan():
    cfg = ControlConfig.for_mode("nd", subtask_steps=(5, 9, 4))
    hooks = cfg.hooks()
    plan = hooks.planned(plan_subtasks("nd", [0.0, 1.0], [0.3]))
    assert [hooks.limits_of(s, SubtaskLimits(600, True)) for s in plan] == [
        SubtaskLimits(5, False), SubtaskLimits(9, False), SubtaskLimits(4, False)]
    with pytest.raises(DataError, match="subtask_steps"):
        hooks.planned(plan_subtasks("proedit", [0.0, 0.5, 1.0], [0.1, 0.2]))


def test_explicit_exchanges_make_a_scheduled_source_for_their_subtasks_only():
    cfg = ControlConfig.for_mode("nd", edit_plan=(None, ((0, 2, None), (7, 1, 0.5)), None))
    hooks = cfg.hooks()
    plan = hooks.planned(plan_subtasks("nd", [0.0, 1.0], [0.3]))
    order = np.array([2, 0, 1])
    edit = lambda job, scene: np.zeros((2, 2, 3), np.float32)  # noqa: E731
    assert hooks.edit_source(plan[0], edit, order) is None
    src = hooks.edit_source(plan[1], edit, order)
    assert isinstance(src, ScheduledEditSource)
    assert [src.due(s) for s in (0, 1, 7)] == [True, False, True]
    assert [(j.view, j.iteration, j.timestep) for j in src.jobs_at(7)] == [(1, 2, 0.5)]


@pytest.mark.parametrize("kwargs, field", [
    ({"mode": "proedit", "nd_subtasks": 2}, "nd_subtasks"),
    ({"mode": "nd", "subtask_steps": (0,)}, "subtask_steps"),
    ({"mode": "nd", "edit_plan": (((3, 1, None), (2, 1, None)),)}, "edit_plan"),
    ({"mode": "nd", "edit_plan": (None,), "asynchronous": True}, "edit_plan"),
])
def test_bad_controls_are_refused(kwargs, field):
    with pytest.raises(DataError, match=field):
        ControlConfig.for_mode(**kwargs)
