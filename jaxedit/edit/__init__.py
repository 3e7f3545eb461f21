"""The ProEdit method: difficulty, the subtask scheduler, the plan, one subtask's run.

The 2D editors it drives are :mod:`jaxedit.editors`. A whole edit with its run directory
is :func:`jaxedit.pipelines.edit.run_edit`.
"""

from .buffer import (AsyncEditSource, EditedView, EditJob, EditorThreadError, SyncEditSource,
                     Utilisation)
from .difficulty import DifficultyOracle, default_distance, l1_distance, ms_ssim_distance
from .driver import EditData
from .plan import ProEditConfig, SubtaskSpec, anneal_timestep, plan_subtasks
from .schedule import Schedule, decompose, decompose_root, prune_ratios, spread, uniform
from .trainer import TrainSettings

__all__ = [
    "AsyncEditSource", "EditData", "EditJob", "EditedView", "EditorThreadError", "ProEditConfig",
    "SubtaskSpec", "SyncEditSource", "TrainSettings", "Utilisation", "anneal_timestep",
    "plan_subtasks",
    "DifficultyOracle", "Schedule", "decompose",
    "decompose_root", "default_distance", "l1_distance",
    "ms_ssim_distance", "prune_ratios", "spread", "uniform",
]
