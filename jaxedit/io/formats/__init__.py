"""The splat file formats people share scenes in, read and written in NumPy.

INRIA .ply (:mod:`jaxedit.io.ply`), PlayCanvas compressed .ply, Niantic .spz, PlayCanvas SOG and
antimatter15 .splat; :func:`load_scene` / :func:`save_scene` pick the format by name (and, for a
.ply, by its header). Field layouts and conventions are in each module's docstring.
"""

from .common import Splats, from_gaussians, morton_order, to_gaussians
from .compressed_ply import load_compressed_ply, save_compressed_ply
from .scene import FORMATS, SUFFIXES, format_from_name, load_scene, save_scene, scene_format
from .sog import load_sog, save_sog
from .splat import load_splat, save_splat
from .spz import load_spz, save_spz

__all__ = [
    "FORMATS", "SUFFIXES", "Splats", "format_from_name", "from_gaussians", "load_compressed_ply", "load_scene",
    "load_sog", "load_splat", "load_spz", "morton_order", "save_compressed_ply", "save_scene",
    "save_sog", "save_splat", "save_spz", "scene_format", "to_gaussians",
]
