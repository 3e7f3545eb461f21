"""jaxedit: progressive instruction-guided 3D Gaussian splatting scene editing in JAX.

The functional API, re-exported. ``import jaxedit`` imports only the core
dependencies (jax, numpy, optax, optimistix, OpenImageIO, scikit-image); the
real-model editors live behind optional extras.
"""

__version__ = "0.1.0"

from . import camera, gaussians, io, raster, sh
from .camera import Camera
from .errors import DataError
from .gaussians import Gaussians
from .io import (Dataset, load_nerfstudio, load_ply, read_image, save_nerfstudio, save_ply,
                 write_image)
from .raster import RenderOutput, render, render_reference

__all__ = [
    "Camera", "DataError", "Dataset", "Gaussians", "RenderOutput", "__version__", "camera",
    "gaussians", "io", "load_nerfstudio", "load_ply", "raster", "read_image", "render",
    "render_reference", "save_nerfstudio", "save_ply", "sh", "write_image",
]
