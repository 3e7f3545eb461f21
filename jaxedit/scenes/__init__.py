"""Built-in scenes (procedural ones from a NumPy ray caster, and shipped rendered
datasets), written as nerfstudio datasets with :func:`make_scene`."""

import numpy as np

from . import library, points, raycast, textures
from .dataset import SCENE_INFO, copy_rendered_scene, make_scene, photo_capture, size_arguments
from .library import (DATASETS, SCENES, dataset_path, get_scene, list_scenes, rig_cameras,
                      scene_cameras, split_views)
from .points import sample_points
from .raycast import Decal, Light, Rig, Scene, Shape, surface_points_and_ids
from .textures import Texture


def render_scene(scene: Scene, cameras, *, supersample: int = 2, alpha: bool = False):
    """float32 [N, H, W, 3] ground truth of ``scene`` (``alpha``: coverage as a 4th channel)."""
    return raycast.render(scene, cameras, supersample=supersample, alpha=alpha)


def surface_views(scene: Scene, cameras, images=None) -> tuple:
    """``(images, points)``: the views (float32 [N, H, W, 3]; default :func:`render_scene`)
    and the world point each pixel centre sees (0 on the background)."""
    if images is None:
        images = render_scene(scene, cameras)
    points, ids, _ = surface_points_and_ids(scene, cameras)
    return images, np.where((np.asarray(ids) >= 0)[..., None], points, 0.0)


__all__ = ["DATASETS", "Decal", "Light", "Rig", "SCENES", "SCENE_INFO", "Scene", "Shape",
           "Texture", "copy_rendered_scene", "dataset_path", "get_scene", "library", "list_scenes",
           "make_scene", "photo_capture", "points", "raycast", "render_scene", "rig_cameras",
           "sample_points", "scene_cameras", "size_arguments", "split_views",
           "surface_points_and_ids", "surface_views", "textures"]
