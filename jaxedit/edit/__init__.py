"""The ProEdit method: difficulty, the subtask scheduler, the plan and its run."""

from .buffer import (AsyncEditSource, EditedView, EditJob, EditorThreadError, SweepEditSource,
                     SyncEditSource, Utilisation)
from .context import EditContext, EditData
from .hooks import NO_HOOKS, EditHooks
from .difficulty import DifficultyOracle, default_distance, l1_distance, ms_ssim_distance
from .plan import ProEditConfig, SubtaskSpec, anneal_timestep, plan_subtasks
from .schedule import Schedule, decompose, decompose_root, prune_ratios, spread, uniform
from .trainer import EditTrainConfig

__all__ = [
    "AsyncEditSource", "EditContext", "EditData", "EditHooks", "EditJob", "EditedView",
    "EditorThreadError", "NO_HOOKS", "SweepEditSource",
    "ProEditConfig", "SubtaskSpec", "SyncEditSource", "EditTrainConfig", "Utilisation",
    "anneal_timestep",
    "plan_subtasks",
    "DifficultyOracle", "Schedule", "decompose",
    "decompose_root", "default_distance", "l1_distance",
    "ms_ssim_distance", "prune_ratios", "spread", "uniform",
]
