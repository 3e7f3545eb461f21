"""Instruction editing: editors, difficulty, the subtask scheduler, the ProEdit driver.

InstructPix2Pix: ``jaxedit.edit.jax_ip2p`` (JAX, no torch) and its torch + diffusers
reference ``jaxedit.edit.ip2p``, both imported on demand; their shared arithmetic is
``jaxedit.edit.diffusion``.
"""

from .buffer import (AsyncEditSource, EditedView, EditJob, EditorThreadError, SyncEditSource,
                     Utilisation)
from .difficulty import DifficultyOracle, default_distance, l1_distance, ms_ssim_distance
from .editors import Editor, interpolate_embedding
from .progressive import (EditData, ProEditConfig, SubtaskSpec, TrainSettings, anneal_timestep,
                          plan_subtasks, run_edit, select_snapshot)
from .schedule import Schedule, decompose, decompose_root, prune_ratios, spread, uniform
from .keys import view_key
from .simulated import VOCABULARY, SimulatedEditor

__all__ = [
    "AsyncEditSource", "EditData", "EditJob", "EditedView", "EditorThreadError", "ProEditConfig",
    "SubtaskSpec", "SyncEditSource", "TrainSettings", "Utilisation", "anneal_timestep",
    "plan_subtasks", "run_edit", "select_snapshot",
    "DifficultyOracle", "Editor", "Schedule", "SimulatedEditor", "VOCABULARY", "decompose",
    "decompose_root", "default_distance", "interpolate_embedding", "l1_distance",
    "ms_ssim_distance", "prune_ratios", "spread", "uniform", "view_key",
]
