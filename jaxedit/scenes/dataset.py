"""Write a built-in scene as an ordinary nerfstudio dataset."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..io.files import atomic_write_text
from . import library
from . import raycast as rc
from .points import sample_points

SCENE_INFO = "jaxedit_scene.json"


def _positive_int(field: str, value, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise DataError(field, f"must be an integer >= {minimum}, got {value!r}")
    return int(value)


def make_scene(name: str, out_dir: str | os.PathLike, *, size: int = 128, views: int = 64,
               test_views: int = 8, seed: int = 0, num_points: int = 4000,
               supersample: int = 2) -> Path:
    """Render a built-in scene and write it as a nerfstudio dataset.

    Writes ``out_dir/transforms.json`` (PINHOLE intrinsics, OpenGL camera-to-world,
    ``train_filenames`` / ``val_filenames`` / ``test_filenames``), ``images/frame_*.png``
    (``views + test_views`` frames, test views interleaved along the camera spiral),
    ``sparse_pc.ply`` (a COLMAP-like initial cloud, see :mod:`jaxedit.scenes.points`)
    and ``jaxedit_scene.json`` (scene name, seed, background, object names: what an editor
    needs to rebuild the scene with :func:`jaxedit.scenes.get_scene`).

    The same arguments give byte-identical files.

    Args:
      name: one of :func:`jaxedit.scenes.list_scenes`.
      out_dir: the dataset folder (created, or updated in place).
      size: image width and height in pixels.
      views, test_views: numbers of training and held-out views.
      seed: scene variant and point-cloud draws.
      num_points: points in the initial cloud (5% of them outliers).
      supersample: rays per pixel along each axis (anti-aliasing).
    Returns:
      the path of ``transforms.json``.
    """
    size = _positive_int("size", size, 8)
    views = _positive_int("views", views)
    test_views = _positive_int("test_views", test_views, 0)
    num_points = _positive_int("num_points", num_points)
    supersample = _positive_int("supersample", supersample)
    scene = library.get_scene(name, seed)
    cameras, train, test = library.scene_cameras(scene, views=views, test_views=test_views,
                                                 size=size)
    images = rc.render(scene, cameras, supersample=supersample)
    rng = np.random.default_rng(seed)
    points, colors = sample_points(scene, cameras[train], num_points, rng)
    out_dir = Path(out_dir)
    from ..io.nerfstudio import save_nerfstudio

    path = save_nerfstudio(out_dir, images, cameras, train_indices=train, test_indices=test,
                           points=points, point_colors=colors)
    info = {"scene": scene.name, "seed": int(seed), "size": size, "views": views,
            "test_views": test_views, "supersample": supersample,
            "background": list(scene.background), "objects": list(scene.object_names),
            "description": scene.description}
    atomic_write_text(out_dir / SCENE_INFO, json.dumps(info, indent=2) + "\n")
    return path
