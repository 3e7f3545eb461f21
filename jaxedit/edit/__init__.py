"""The ProEdit method: difficulty, the subtask scheduler, the plan, its run.

:mod:`.plan` (config, subtasks), :mod:`.schedule` and :mod:`.difficulty` (the
scheduler), :mod:`.progressive` (:func:`run_plan`, the loop over subtasks),
:mod:`.subtask` (one subtask), :mod:`.buffer` (edit sources), :mod:`.hooks` (where a
scheduler or a study plugs in). A whole edit with its run directory is
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
