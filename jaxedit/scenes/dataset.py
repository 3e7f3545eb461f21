"""Write a built-in scene as an ordinary nerfstudio dataset."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..io.files import atomic_write_bytes, atomic_write_text
from ..io.images import read_image_with_alpha
from ..io.nerfstudio import _downscale_image, load_nerfstudio, save_nerfstudio
from . import library
from . import raycast as rc
from .points import sample_points

SCENE_INFO = "jaxedit_scene.json"


def _positive_int(field: str, value, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise DataError(field, f"must be an integer >= {minimum}, got {value!r}")
    return int(value)


#: Defaults of the procedural scenes' make_scene keywords.
PROCEDURAL_DEFAULTS = {"size": 128, "views": 64, "test_views": 8, "num_points": 4000,
                       "supersample": 2}


def size_arguments(name: str, size: int) -> dict[str, int]:
    """:func:`make_scene`'s keyword for ``size`` px images: ``{"size": size}`` (procedural)
    or ``{"downscale": factor}`` (rendered; DataError unless ``size`` divides its width)."""
    from .library import DATASETS, dataset_path

    if name not in DATASETS:
        return {"size": size}
    info = json.loads((dataset_path(name) / SCENE_INFO).read_text(encoding="utf-8"))
    width = int(info["size"])
    if width % size:
        raise DataError("size", f"{name} is rendered at {width} px; the size must divide it "
                        f"(e.g. {width // 4} or {width // 2}), got {size}")
    return {"downscale": width // size}


def make_scene(name: str, out_dir: str | os.PathLike, *, size: int | None = None,
               views: int | None = None, test_views: int | None = None, seed: int = 0,
               num_points: int | None = None, supersample: int | None = None,
               downscale: int = 1) -> Path:
    """Write a built-in scene as a nerfstudio dataset (with ``sparse_pc.ply`` and
    ``jaxedit_scene.json``); the same arguments give byte-identical files. Rendered scenes
    go through :func:`copy_rendered_scene`.

    Args:
      name: one of :func:`jaxedit.scenes.list_scenes`.
      out_dir: the dataset folder (created, or updated in place).
      size: image width and height in pixels (procedural; default 128).
      views, test_views: numbers of training and held-out views (default 64, 8).
      seed: scene variant and point-cloud draws.
      num_points: points in the initial cloud (default 4000).
      supersample: rays per pixel along each axis (default 2).
      downscale: integer image downscale factor (rendered scenes).
    Returns:
      the path of ``transforms.json``.
    """
    if name in library.DATASETS:
        for field, value in (("size", size), ("num_points", num_points),
                             ("supersample", supersample)):
            if value is not None:
                raise DataError(field, f"{name!r} is a rendered dataset of fixed views and "
                                       f"points; only downscale, views and test_views apply")
        return copy_rendered_scene(name, out_dir, downscale=downscale, views=views,
                                   test_views=test_views)
    if downscale != 1:
        raise DataError("downscale", f"applies to rendered scenes "
                                     f"({', '.join(library.DATASETS)}); {name!r} takes size")
    given = {"size": size, "views": views, "test_views": test_views, "num_points": num_points,
             "supersample": supersample}
    v = {k: PROCEDURAL_DEFAULTS[k] if x is None else x for k, x in given.items()}
    size = _positive_int("size", v["size"], 8)
    views = _positive_int("views", v["views"])
    test_views = _positive_int("test_views", v["test_views"], 0)
    num_points = _positive_int("num_points", v["num_points"])
    supersample = _positive_int("supersample", v["supersample"])
    scene = library.get_scene(name, seed)
    cameras, train, test = library.scene_cameras(scene, views=views, test_views=test_views,
                                                 size=size)
    images = rc.render(scene, cameras, supersample=supersample)
    rng = np.random.default_rng(seed)
    points, colors = sample_points(scene, cameras[train], num_points, rng)
    out_dir = Path(out_dir)
    path = save_nerfstudio(out_dir, images, cameras, train_indices=train, test_indices=test,
                           points=points, point_colors=colors)
    info = {"scene": scene.name, "seed": int(seed), "size": size, "views": views,
            "test_views": test_views, "supersample": supersample,
            "background": list(scene.background), "objects": list(scene.object_names),
            "description": scene.description}
    atomic_write_text(out_dir / SCENE_INFO, json.dumps(info, indent=2) + "\n")
    return path


def _spread(indices: np.ndarray, count: int | None, field: str) -> np.ndarray:
    """``count`` of ``indices`` evenly spread along them (all when count is None)."""
    if count is None:
        return indices
    count = _positive_int(field, count, 0)
    if count > len(indices):
        raise DataError(field, f"the scene has {len(indices)} such views, asked for {count}")
    if count == 0:
        return indices[:0]
    return indices[np.round(np.linspace(0, len(indices) - 1, count)).astype(np.int64)]


def _rgba_downscaled(path: Path, factor: int) -> np.ndarray:
    """float32 [H/f, W/f, 4] straight RGBA, averaged premultiplied (as load_nerfstudio does)."""
    colour, alpha = read_image_with_alpha(path)
    alpha = np.ones(colour.shape[:2], np.float32) if alpha is None else alpha
    if factor == 1:
        return np.concatenate([colour, alpha[..., None]], -1)
    premult = _downscale_image(np.concatenate([colour * alpha[..., None], alpha[..., None]], -1),
                               factor)
    a = premult[..., 3:]
    straight = np.where(a > 0, premult[..., :3] / np.maximum(a, 1e-12), 0.0)
    return np.concatenate([np.clip(straight, 0.0, 1.0), a], -1).astype(np.float32)


def copy_rendered_scene(name: str, out_dir: str | os.PathLike, *, downscale: int = 1,
                        views: int | None = None, test_views: int | None = None) -> Path:
    """Copy the rendered scene ``name`` into ``out_dir`` as an RGBA nerfstudio dataset,
    ``downscale`` d, keeping ``views`` / ``test_views`` evenly spread views (default: all).

    Returns:
      the path of ``transforms.json``.
    """
    src = library.dataset_path(name)
    if isinstance(downscale, bool) or not isinstance(downscale, (int, np.integer)) or downscale < 1:
        raise DataError("downscale", f"must be an integer >= 1, got {downscale!r}")
    data = load_nerfstudio(src, downscale=int(downscale), cache=False)  # package data: no cache
    train = _spread(data.train_indices, views, "views")
    test = _spread(data.test_indices, test_views, "test_views")
    if len(train) == 0:
        raise DataError("views", "need at least one training view")
    keep = np.union1d(train, test)
    images = np.stack([_rgba_downscaled(data.path.parent / data.filenames[k], int(downscale))
                       for k in keep])
    out_dir = Path(out_dir)
    path = save_nerfstudio(out_dir, images, data.cameras[keep],
                           filenames=[data.filenames[k] for k in keep],
                           train_indices=np.searchsorted(keep, train),
                           test_indices=np.searchsorted(keep, test),
                           points=data.points, point_colors=data.point_colors)
    info = json.loads((src / SCENE_INFO).read_text(encoding="utf-8"))
    info.update(size=int(data.cameras.width), downscale=int(downscale), views=len(train),
                test_views=len(test))
    atomic_write_text(out_dir / SCENE_INFO, json.dumps(info, indent=1) + "\n")
    for extra in sorted(src.glob("*.txt")):  # credits and licence travel with the images
        atomic_write_bytes(out_dir / extra.name, extra.read_bytes())
    for extra in sorted((src / "images").glob("*.txt")):  # the renders' own licence note
        atomic_write_bytes(out_dir / "images" / extra.name, extra.read_bytes())
    return path


def photo_capture(name: str, out_dir: str | os.PathLike, *, views: int,
                  first: int = 0, last: int | None = None, background=(0.5, 0.5, 0.5),
                  suffix: str = ".png", exif: dict | None = None):
    """``views`` views of rendered scene ``name`` (spread over ``first .. last``) written as
    pose-less photos ``IMG_0000<suffix>``, ... over ``background``, with ``exif`` metadata.

    Returns:
      (the photo paths in order, their true cameras [views]).
    """
    from ..io.images import write_image

    data = load_nerfstudio(library.dataset_path(name), background=background, split_every=0)
    last = len(data.filenames) - 1 if last is None else last
    _positive_int("views", views, 3)
    if not 0 <= first < last < len(data.filenames) or views > last - first + 1:
        raise DataError("views", f"cannot pick {views} of views {first}..{last} of {name} "
                                 f"({len(data.filenames)} views)")
    index = np.round(np.linspace(first, last, views)).astype(np.int64)
    out_dir = Path(out_dir)
    paths = [out_dir / f"IMG_{k:04d}{suffix}" for k in range(views)]
    for path, k in zip(paths, index):
        write_image(path, data.images[k], metadata=exif)
    return paths, data.cameras[index]
