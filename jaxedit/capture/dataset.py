"""A COLMAP reconstruction as a nerfstudio dataset, written the way ``ns-process-data`` does.

As nerfstudio's ``colmap_to_json``: ``transform_matrix`` is the OpenGL camera-to-world in a
world rotated by ``applied_transform`` (COLMAP's y-down world becomes z-up), as are the
points (``sparse_pc.ply``); one shared OPENCV or PINHOLE camera at the top level; frames
``images/frame_00001.png`` ... (EXIF-rotated photos written upright as PNG, as COLMAP
reads the stored pixels), ``images_2/``, ``images_4/`` copies, COLMAP's files in
``colmap/``; unregistered frames are not listed. Staged, so a failure leaves nothing behind.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from ..camera import opencv_w2c_to_opengl_c2w
from ..errors import DataError, check_ranges, ranged
from ..io.files import current_umask
from ..io.images import photo_header, read_image, read_photo, write_image
from ..io.nerfstudio import _downscale_image
from ..io.ply import save_points_ply
from .sfm import Report, SfmOptions, run_sfm
from .triangulate import TriangulateOptions

APPLIED_TRANSFORM = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0]])
DOWNSCALES = (2, 4)


def colmap_intrinsics(model: str, params, width: int, height: int) -> dict:
    """transforms.json intrinsics of a COLMAP camera (nerfstudio's mapping of the models)."""
    p = [float(x) for x in params]
    out = {"w": int(width), "h": int(height)}
    if model == "SIMPLE_PINHOLE":
        return out | {"camera_model": "PINHOLE", "fl_x": p[0], "fl_y": p[0], "cx": p[1], "cy": p[2]}
    if model == "PINHOLE":
        return out | {"camera_model": "PINHOLE", "fl_x": p[0], "fl_y": p[1], "cx": p[2], "cy": p[3]}
    if model == "SIMPLE_RADIAL":
        radial = (p[0], p[0], p[1], p[2], p[3], 0.0, 0.0, 0.0)
    elif model == "RADIAL":
        radial = (p[0], p[0], p[1], p[2], p[3], p[4], 0.0, 0.0)
    elif model == "OPENCV":
        radial = tuple(p[:8])
    else:
        raise DataError("camera_model", f"COLMAP camera model {model} has no nerfstudio equivalent "
                                        f"here (use SIMPLE_RADIAL, RADIAL, OPENCV or a pinhole)")
    keys = ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "p1", "p2")
    return out | {"camera_model": "OPENCV"} | dict(zip(keys, radial))


def reconstruction_views(reconstruction) -> tuple[list[str], np.ndarray, list[dict], list[int]]:
    """The registered images of a pycolmap.Reconstruction, sorted by name.

    Returns:
      (names, world_to_camera float64 [N, 4, 4] OpenCV in COLMAP's world,
        transforms.json intrinsics of each image, COLMAP image ids).
    """
    rows = []
    for image_id, image in reconstruction.images.items():
        if not image.has_pose:
            continue
        w2c = np.eye(4)
        w2c[:3] = image.cam_from_world().matrix()
        cam = reconstruction.cameras[image.camera_id]
        rows.append((image.name, w2c, colmap_intrinsics(cam.model.name, cam.params, cam.width,
                                                         cam.height), int(image_id)))
    rows.sort(key=lambda r: r[0])
    return ([r[0] for r in rows], np.stack([r[1] for r in rows]) if rows else np.zeros((0, 4, 4)),
            [r[2] for r in rows], [r[3] for r in rows])


def reconstruction_points(reconstruction) -> tuple[np.ndarray, np.ndarray]:
    """(points float64 [P, 3] in COLMAP's world, colours float32 [P, 3] in [0, 1])."""
    pts = list(reconstruction.points3D.values())
    xyz = np.array([p.xyz for p in pts], np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in pts], np.float32).reshape(-1, 3) / 255.0
    return xyz, rgb


def transforms_meta(names: list[str], w2c: np.ndarray, intrinsics: list[dict],
                    image_ids: list[int] | None = None,
                    originals: dict[str, str] | None = None) -> dict:
    """The transforms.json object (without ``ply_file_path``) of registered views.

    Args:
      names: image file names inside ``images/``.
      w2c: float [N, 4, 4] OpenCV world-to-camera in COLMAP's world.
      intrinsics: N dicts from :func:`colmap_intrinsics`; shared ones go to the top level.
      image_ids: COLMAP image ids (``colmap_im_id``), or None.
      originals: ``{name: the photo's own file name}`` (``original_file_path``), or None.
    """
    applied = np.vstack([APPLIED_TRANSFORM, [0.0, 0.0, 0.0, 1.0]])
    c2w = applied @ opencv_w2c_to_opengl_c2w(np.asarray(w2c, np.float64))
    shared = all(i == intrinsics[0] for i in intrinsics)
    meta = dict(intrinsics[0]) if shared else {}
    frames = []
    for k, name in enumerate(names):
        frame = {"file_path": f"images/{name}", "transform_matrix": c2w[k].tolist()}
        if image_ids is not None:
            frame["colmap_im_id"] = int(image_ids[k])
        if originals and name in originals:
            frame["original_file_path"] = originals[name]
        if not shared:
            frame.update(intrinsics[k])
        frames.append(frame)
    meta["frames"] = frames
    meta["applied_transform"] = APPLIED_TRANSFORM.tolist()
    return meta


def frame_names(sources: list, suffix: str = ".png") -> list[str]:
    """nerfstudio's names ``frame_00001<ext>`` ...: file sources keep their suffix."""
    return [f"frame_{k + 1:05d}" + (Path(s).suffix.lower() if isinstance(s, (str, Path)) else suffix)
            for k, s in enumerate(sources)]


def check_out_dir(out_dir: Path) -> None:
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise DataError(out_dir, "already exists and is not an empty folder; choose a new output")


def min_registered(num_images: int, fraction: float) -> int:
    """Registered views required of ``num_images``: ``ceil(fraction * n)``, at least 3."""
    return max(3, math.ceil(fraction * num_images - 1e-9))


@dataclasses.dataclass(frozen=True)
class CaptureConfig:
    """``process-data``'s settings.

    Attributes:
      sfm: structure-from-motion settings (:class:`~jaxedit.capture.sfm.SfmOptions`).
      triangulation: settings of ``--triangulate`` (points for a posed dataset).
      num_frames: a video is cut into this many windows and the sharpest frame of each is kept.
      min_registered: fewer registered views than this fraction of the images (or 3) is an error.
    """

    sfm: SfmOptions = SfmOptions()
    triangulation: TriangulateOptions = TriangulateOptions()
    num_frames: int = ranged(300, low=1)
    min_registered: float = ranged(0.5, low=0.0, high=1.0)

    def __post_init__(self):
        check_ranges(self)


def process_capture(out_dir: str | os.PathLike, sources: list, *, options: SfmOptions = SfmOptions(),
                    min_fraction: float = CaptureConfig.min_registered, downscales=DOWNSCALES,
                    report: Report | None = None) -> dict:
    """Make a nerfstudio dataset in ``out_dir`` from images, by structure from motion.

    Args:
      out_dir: the dataset folder; must not exist or be empty.
      sources: image files and/or uint8 [H, W, 3] frames (PNG), in order.
      options: SfM settings (:class:`SfmOptions`).
      min_fraction: fewer registered views than this fraction of the images (or 3) is an error.
      downscales: factors of the ``images_<f>/`` copies.
      report: progress callback ``(stage, done, total)``; stages "extract", "match",
        "map", "write".
    Returns:
      a summary: ``num_images``, ``num_registered``, ``num_models``, ``num_points``,
      ``seconds`` per stage, ``camera`` (the shared intrinsics), ``focal_source`` and
      ``focal_start_px`` (see :class:`~jaxedit.capture.sfm.SfmResult`), ``transforms`` (path).
    """
    out_dir = Path(out_dir)
    check_out_dir(out_dir)
    options.check()
    if not 0.0 <= min_fraction <= 1.0:
        raise DataError("min_fraction", f"must be in [0, 1], got {min_fraction}")
    report = report or (lambda stage, done, total: None)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".tmp", dir=out_dir.parent))
    os.chmod(staging, 0o777 & ~current_umask())
    try:
        names = frame_names(sources)
        images = staging / "images"
        images.mkdir()
        for k, source in enumerate(sources):
            if not isinstance(source, (str, Path)):
                write_image(images / names[k], np.asarray(source, np.float32) / 255.0)
                continue
            orientation = photo_header(source)[2]
            if orientation == 1:
                shutil.copyfile(source, images / names[k])
            else:  # COLMAP ignores EXIF orientation: it gets the upright pixels, losslessly
                names[k] = str(Path(names[k]).with_suffix(".png"))
                write_image(images / names[k], read_photo(source, orientation=orientation))
        height, width = read_image(images / names[0]).shape[:2]
        sfm = run_sfm(images, names, staging / "colmap", options, report, (width, height))
        need = min_registered(len(names), min_fraction)
        if sfm.num_registered < need:
            raise DataError("structure from motion", f"registered {sfm.num_registered} of "
                            f"{len(names)} images (need {need}); the views may overlap too little, "
                            f"be blurry or lack texture")
        reg_names, w2c, intrinsics, ids = reconstruction_views(sfm.reconstruction)
        originals = {name: Path(source).name for name, source in zip(names, sources)
                     if isinstance(source, (str, Path))}
        meta = transforms_meta(reg_names, w2c, intrinsics, ids, originals)
        points, colors = reconstruction_points(sfm.reconstruction)
        save_points_ply(staging / "sparse_pc.ply", points @ APPLIED_TRANSFORM[:, :3].T, colors)
        meta["ply_file_path"] = "sparse_pc.ply"
        for k, name in enumerate(names):
            image = read_image(images / name)
            for factor in downscales:
                write_image(staging / f"images_{factor}" / name, _downscale_image(image, factor))
            report("write", k + 1, len(names))
        (staging / "transforms.json").write_text(json.dumps(meta, indent=2), encoding="utf-8")
        check_out_dir(out_dir)  # nobody wrote there meanwhile
        if out_dir.exists():
            out_dir.rmdir()
        os.replace(staging, out_dir)
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
    camera = {k: v for k, v in meta.items() if k not in ("frames", "applied_transform",
                                                         "ply_file_path")}
    return {"num_images": len(names), "num_registered": sfm.num_registered,
            "num_models": sfm.num_models, "num_points": int(len(points)),
            "seconds": {k: round(v, 3) for k, v in sfm.seconds.items()}, "camera": camera,
            "focal_source": sfm.focal_source, "focal_start_px": sfm.focal_start_px,
            "transforms": str(out_dir / "transforms.json")}
