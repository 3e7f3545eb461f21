"""3DGS training: a pure, jit-compiled train step, a resumable fit loop, checkpoints.

The pieces, from the inside out (one module each):

* :mod:`.config` -- :class:`TrainConfig` (with :class:`jaxedit.densify.DensifyConfig`):
  every hyper-parameter, Splatfacto defaults, JSON-serialisable (stored in checkpoints).
* :mod:`.state` -- :class:`TrainState`: the whole training state as one pytree
  (Gaussians, optax state with one Adam per attribute, densify statistics, the step
  count, the run's base PRNG key, camera corrections); the config, the scene extent
  and the intersection-buffer size are static fields. :func:`init_state`, :func:`optimizer`.
* :mod:`.step` -- :func:`apply_step` / :func:`train_step` ``(state, batch, key) ->
  (state, metrics)``: render one view, 0.8 L1 + 0.2 D-SSIM, Adam, then density
  control. Pure. A step that needs a larger intersection buffer or capacity
  returns its input state with ``metrics["redo"]`` set.
* :mod:`.room` -- the buffer and the capacity: sized from the views, planned for a
  densifying run, grown after a redo (:func:`step_with_retry` for single steps).
* :mod:`.loop` -- :func:`train_chunk` (up to ``length`` steps in one ``lax.scan``,
  views picked on the device) and :func:`fit`, the loop over chunks with log
  records, progress events, checkpoint calls and the divergence guard
  (:func:`divergence`); it writes no files (:mod:`jaxedit.pipelines.rundir` does). The
  view of step ``s`` and its key are pure functions of ``(base key, s)``, so a run
  resumed from any checkpoint ends with bit-identical Gaussians, whatever the chunking.
* :mod:`.checkpoint` -- :func:`save_checkpoint` / :func:`load_checkpoint` (the
  shared format of :mod:`jaxedit.io.checkpoint`).
* :mod:`.evaluation` -- :func:`evaluate`, :func:`render_views`.

The ProEdit driver swaps the ``images`` array between chunks (:func:`put_image`
updates one view of a device array in place) and runs its own scan of
:func:`apply_step` (:func:`scan_steps`).
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
from .state import Batch, TrainState, init_state, optimizer, scene_extent
from .step import (GUARDED, active_sh_degree, apply_step, background_color, camera_lr, means_lr,
                   psnr_from_mse, sh_mask, train_step)

__all__ = [
    "BACKGROUNDS", "Batch", "CHECKPOINT_VERSION", "CHUNK", "DensifyConfig", "GROWTH_ROOM",
    "GUARDED", "GUARD_WINDOW", "HEADROOM", "ROOM", "TrainConfig", "TrainProgress", "TrainState",
    "active_sh_degree", "apply_step", "background_color", "camera_lr",
    "default_room", "divergence", "epoch_view", "evaluate", "fit", "grow_for_redo", "init_state",
    "load_checkpoint", "load_checkpoint_with_extra", "means_lr",
    "measure_intersections", "optimizer", "plan_room", "planned_capacity", "planned_headroom",
    "psnr_from_mse", "put_image", "render_views", "save_checkpoint", "scan_steps",
    "scene_extent", "select_batch", "sh_mask", "size_buffer", "step_with_retry", "train_chunk",
    "train_step", "view_and_key",
]
