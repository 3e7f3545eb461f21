"""Instruction editing: editors, difficulty, the subtask scheduler, the ProEdit driver.

A whole edit with its run directory is :func:`jaxedit.pipelines.edit.run_edit`.

InstructPix2Pix: ``jaxedit.edit.jax_ip2p`` (JAX, no torch) and its torch + diffusers
reference ``jaxedit.edit.ip2p``, both imported on demand; their shared arithmetic is
``jaxedit.edit.diffusion``.
"""

from .buffer import (AsyncEditSource, EditedView, EditJob, EditorThreadError, SyncEditSource,
                     Utilisation)
from .difficulty import DifficultyOracle, default_distance, l1_distance, ms_ssim_distance
from .editors import Editor, interpolate_embedding
from .driver import EditData
from .plan import ProEditConfig, SubtaskSpec, anneal_timestep, plan_subtasks
from .schedule import Schedule, decompose, decompose_root, prune_ratios, spread, uniform
from .keys import view_key
from .simulated import VOCABULARY, SimulatedEditor
from .trainer import TrainSettings

__all__ = [
    "AsyncEditSource", "EditData", "EditJob", "EditedView", "EditorThreadError", "ProEditConfig",
    "SubtaskSpec", "SyncEditSource", "TrainSettings", "Utilisation", "anneal_timestep",
    "plan_subtasks",
    "DifficultyOracle", "Editor", "Schedule", "SimulatedEditor", "VOCABULARY", "decompose",
    "decompose_root", "default_distance", "interpolate_embedding", "l1_distance",
    "ms_ssim_distance", "prune_ratios", "spread", "uniform", "view_key",
]
