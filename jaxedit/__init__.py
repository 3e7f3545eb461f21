"""jaxedit: progressive instruction-guided 3D Gaussian splatting scene editing in JAX.

The functional API, re-exported. ``import jaxedit`` changes nothing in the caller's
program; call :func:`enable_compilation` for the persistent compilation cache. The
run-directory helpers are imported on first use.
"""

__version__ = "0.1.0"

from . import (camera, clip_metrics, densify, edit, editors, gaussians, io, losses, lpips, metrics, poses,
               raster, scenes, sh, train, viz)
from .camera import Camera
from .compilation import enable as enable_compilation
from .errors import DataError
from .gaussians import Gaussians
from .io import (Dataset, load_nerfstudio, load_ply, load_scene, read_image, save_nerfstudio,
                 save_ply, save_scene, write_image)
from .edit import decompose, decompose_root
from .lpips import load_lpips, lpips_distance
from .raster import RenderOutput, render, render_reference
from .scenes import make_scene
from .train import TrainConfig, TrainState, evaluate, fit, init_state, train_step
from .viz import colorize_depth, image_grid, turntable, write_turntable

#: Names served from the run-directory layer (:mod:`jaxedit.pipelines`) on first use.
_PIPELINE_NAMES = {"write_report": "report", "write_snapshot": "snapshots", "resume": "rundir"}


def __getattr__(name: str):
    if name in _PIPELINE_NAMES:
        import importlib

        module = importlib.import_module(f".pipelines.{_PIPELINE_NAMES[name]}", __name__)
        return getattr(module, name)
    raise AttributeError(f"module 'jaxedit' has no attribute {name!r}")


__all__ = [
    "Camera", "DataError", "Dataset", "Gaussians", "RenderOutput", "TrainConfig", "TrainState",
    "__version__", "camera", "clip_metrics", "colorize_depth", "decompose", "decompose_root",
    "densify", "edit", "editors", "enable_compilation", "evaluate", "fit", "init_state",
    "gaussians", "image_grid", "io", "lpips", "lpips_distance", "load_lpips", "load_nerfstudio",
    "load_ply", "load_scene", "losses", "make_scene", "metrics", "poses", "raster", "read_image", "render",
    "render_reference", "resume", "save_nerfstudio", "save_ply", "save_scene", "scenes", "sh", "train",
    "train_step", "turntable", "viz", "write_image", "write_report", "write_snapshot",
    "write_turntable",
]
