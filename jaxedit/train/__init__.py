"""3DGS training: a pure, jit-compiled train step, a resumable fit loop, checkpoints.

:mod:`.config` (:class:`TrainConfig`), :mod:`.state` (:class:`TrainState`), :mod:`.step`
(:func:`train_step`), :mod:`.room` (buffer and capacity), :mod:`.loop` (:func:`fit`),
:mod:`.checkpoint`, :mod:`.evaluation`.
"""

from ..densify import DensifyConfig
from .checkpoint import (CHECKPOINT_VERSION, load_checkpoint, load_checkpoint_with_extra,
                         save_checkpoint)
from .config import BACKGROUNDS, TrainConfig
from .evaluation import evaluate, render_views
from .loop import (CHUNK, GUARD_WINDOW, TrainProgress, divergence, epoch_view, fit, put_image,
                   scan_steps, select_batch, train_chunk, view_and_key)
from .room import (GROWTH_ROOM, HEADROOM, ROOM, default_room, grow_for_redo,
                   measure_intersections, plan_room, planned_capacity, planned_headroom,
                   size_buffer, step_with_retry)
from .state import (Batch, TrainState, init_state, lr_schedule, means_lr, optimizer,
                    scene_extent)
from .step import (GUARDED, active_sh_degree, apply_step, background_color, camera_lr,
                   psnr_from_mse, sh_mask, train_step)

__all__ = [
    "BACKGROUNDS", "Batch", "CHECKPOINT_VERSION", "CHUNK", "DensifyConfig", "GROWTH_ROOM",
    "GUARDED", "GUARD_WINDOW", "HEADROOM", "ROOM", "TrainConfig", "TrainProgress", "TrainState",
    "active_sh_degree", "apply_step", "background_color", "camera_lr",
    "default_room", "divergence", "epoch_view", "evaluate", "fit", "grow_for_redo", "init_state",
    "load_checkpoint", "load_checkpoint_with_extra", "lr_schedule", "means_lr",
    "measure_intersections", "optimizer", "plan_room", "planned_capacity", "planned_headroom",
    "psnr_from_mse", "put_image", "render_views", "save_checkpoint", "scan_steps",
    "scene_extent", "select_batch", "sh_mask", "size_buffer", "step_with_retry", "train_chunk",
    "train_step", "view_and_key",
]
