"""Built-in scenes: procedural ones rendered by an independent NumPy ray caster, and
rendered datasets shipped with the package, written as nerfstudio datasets::

    from jaxedit import scenes
    scenes.make_scene("face", "runs/face")
    scene = scenes.get_scene("face")
    cams, train, test = scenes.scene_cameras(scene, views=64, test_views=8, size=128)
    images = scenes.render_scene(scene, cams)               # float32 [72, 128, 128, 3]
    points, ids, uv = scenes.surface_points_and_ids(scene, cams)

``surface_points_and_ids`` says what every pixel centre sees, so an edit defined on
the surface is 3D-consistent by construction. ``person`` is Reallusion's CC BY 3.0 model
(Sweet Home 3D) rendered by Cycles (``scripts/render_person.py``).
"""

import numpy as np

from . import library, points, raycast, textures
from .dataset import SCENE_INFO, copy_rendered_scene, make_scene, photo_capture, size_arguments
from .library import (DATASETS, SCENES, dataset_path, get_scene, list_scenes, rig_cameras,
                      scene_cameras, split_views)
from .points import sample_points
from .raycast import Decal, Light, Rig, Scene, Shape, surface_points_and_ids
from .textures import Texture


def render_scene(scene: Scene, cameras, *, supersample: int = 2, alpha: bool = False):
    """Ground truth of ``scene`` for ``cameras``: float32 [N, H, W, 3] in [0, 1], each pixel
    averaging ``supersample``^2 rays; ``alpha=True`` adds coverage as a 4th channel."""
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
