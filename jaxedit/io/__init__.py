"""Reading and writing scenes: nerfstudio datasets, splat files (.ply, compressed .ply, .spz, SOG,
.splat), images."""

from .distortion import Distortion, distort_points, undistort_image, undistort_points
from .formats import FORMATS, load_scene, save_scene
from .files import atomic_path, atomic_write_bytes, atomic_write_text
from .images import read_image, read_image_with_alpha, write_image
from .nerfstudio import (Dataset, load_nerfstudio, load_nerfstudio_cameras, nerfstudio_view_size,
                         nerfstudio_world_transform, save_nerfstudio)
from .ply import load_ply, load_points_ply, save_ply, save_points_ply
from .similarity import rotate_sh, transform_cameras, transform_gaussians, transform_points, upright

__all__ = [
    "Dataset", "Distortion", "FORMATS", "atomic_path", "atomic_write_bytes", "atomic_write_text",
    "distort_points", "load_nerfstudio", "load_nerfstudio_cameras", "load_ply", "load_scene",
    "load_points_ply", "nerfstudio_view_size",
    "nerfstudio_world_transform",
    "read_image", "read_image_with_alpha", "rotate_sh", "save_nerfstudio", "save_ply", "save_scene", "save_points_ply",
    "transform_cameras", "transform_gaussians", "transform_points", "undistort_image", "upright",
    "undistort_points", "write_image",
]
