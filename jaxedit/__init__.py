"""jaxedit: progressive instruction-guided 3D Gaussian splatting scene editing in JAX.

The functional API, re-exported. ``import jaxedit`` imports only the core
dependencies (jax, numpy, optax, optimistix, OpenImageIO, scikit-image); the
real-model editors live behind optional extras.
"""

__version__ = "0.1.0"

from . import camera, gaussians, io, sh
from .camera import Camera
from .errors import DataError
from .gaussians import Gaussians
from .raster import RenderOutput

__all__ = ["Camera", "DataError", "Gaussians", "RenderOutput", "camera", "gaussians", "io", "sh",
           "__version__"]
