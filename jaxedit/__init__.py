"""jaxedit: progressive instruction-guided 3D Gaussian splatting scene editing in JAX.

The functional API, re-exported. ``import jaxedit`` imports only the core
dependencies (jax, numpy, optax, optimistix, OpenImageIO, scikit-image); the
real-model editors live behind optional extras.
"""

__version__ = "0.1.0"

from . import compilation as _compilation
from .errors import DataError as _DataError

# Compile once across runs, and count what compiles (jaxedit.compilation). A bad
# JAXEDIT_COMPILE_CACHE_MB or _MIN_S leaves the cache off here; the commands report it in
# one line.
try:
    _compilation.enable_persistent_cache()
except _DataError:
    pass
_compilation.start_recording()

from . import (camera, clip_metrics, densify, edit, editors, gaussians, io, losses, lpips, metrics, poses,
               raster, scenes, sh, train, viz)
from .camera import Camera
from .errors import DataError
from .gaussians import Gaussians
from .io import (Dataset, load_nerfstudio, load_ply, read_image, save_nerfstudio, save_ply,
                 write_image)
from .edit import decompose, decompose_root
from .editors import SimulatedEditor
from .lpips import load_lpips, lpips_distance
from .pipelines.report import write_report
from .raster import RenderOutput, render, render_reference
from .scenes import make_scene
from .train import TrainConfig, TrainState, evaluate, fit, init_state, train_step
from .pipelines.rundir import resume
from .viz import colorize_depth, image_grid, turntable, write_turntable
from .pipelines.snapshots import write_snapshot

__all__ = [
    "Camera", "DataError", "Dataset", "Gaussians", "RenderOutput", "SimulatedEditor", "TrainConfig", "TrainState",
    "__version__", "camera", "clip_metrics", "colorize_depth", "decompose", "decompose_root", "densify", "edit", "editors", "evaluate", "fit", "init_state",
    "gaussians", "image_grid", "io", "lpips", "lpips_distance", "load_lpips", "load_nerfstudio", "load_ply", "losses", "make_scene",
    "metrics", "poses", "raster", "read_image", "render", "render_reference", "resume", "save_nerfstudio",
    "save_ply", "scenes", "sh", "train", "train_step", "turntable", "viz", "write_image", "write_report",
    "write_snapshot", "write_turntable",
]
