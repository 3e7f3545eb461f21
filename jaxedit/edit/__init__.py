"""The ProEdit method: difficulty, the subtask scheduler, the plan, its run.

In the order an edit calls them: :mod:`.plan` (configuration, subtasks), :mod:`.schedule`
and :mod:`.difficulty` (the scheduler, 3.2), :mod:`.trainer`, :mod:`.context` (what a
run reads), :mod:`.state` (where it is), :mod:`.progressive` (a whole edit's plan and
:func:`run_plan`, the one loop over its subtasks), :mod:`.subtask` (one subtask's state
machine), :mod:`.buffer` (the edit sources), :mod:`.hooks` (where a new scheduler or a
study's control plugs in). The 2D editors it drives are
:mod:`jaxedit.editors`. A whole edit with its run directory is
:func:`jaxedit.pipelines.edit.run_edit`.
"""

from .buffer import (AsyncEditSource, EditedView, EditJob, EditorThreadError, SweepEditSource,
                     SyncEditSource, Utilisation)
from .context import EditContext, EditData
from .hooks import NO_HOOKS, EditHooks
from .difficulty import DifficultyOracle, default_distance, l1_distance, ms_ssim_distance
from .plan import ProEditConfig, SubtaskSpec, anneal_timestep, plan_subtasks
from .schedule import Schedule, decompose, decompose_root, prune_ratios, spread, uniform
from .trainer import TrainSettings

__all__ = [
    "AsyncEditSource", "EditContext", "EditData", "EditHooks", "EditJob", "EditedView",
    "EditorThreadError", "NO_HOOKS", "SweepEditSource",
    "ProEditConfig", "SubtaskSpec", "SyncEditSource", "TrainSettings", "Utilisation", "anneal_timestep",
    "plan_subtasks",
    "DifficultyOracle", "Schedule", "decompose",
    "decompose_root", "default_distance", "l1_distance",
    "ms_ssim_distance", "prune_ratios", "spread", "uniform",
]
