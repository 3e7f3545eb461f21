"""Points for a posed dataset that has none: SIFT features triangulated at the known poses.

COLMAP extracts SIFT features, matches each view with its ``neighbors`` nearest cameras
and triangulates at the given poses (``point_triangulator``), leaving the cameras alone.
The views are the loaded ones (:class:`jaxedit.io.Dataset`, OpenCV world-to-camera, as is
COLMAP's ``cam_from_world``), read again from larger photos when they were loaded smaller
than features need (:func:`feature_views`), so the points come out in the dataset's world.
pycolmap is imported only inside the functions (the optional extra ``capture``).
"""

from __future__ import annotations

import dataclasses
import json
import tempfile
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import DataError, check_ranges, ranged


@dataclasses.dataclass(frozen=True)
class TriangulateOptions:
    """Settings of :func:`triangulate`.

    Attributes:
      neighbors: views each view is matched with (its nearest camera centres).
      max_features: SIFT features per view.
      peak_threshold: SIFT's contrast threshold (lower finds more features on smooth views).
      feature_side: long side SIFT runs at: views loaded smaller are read again from larger
        photos (:func:`feature_views`), then enlarged (at most 4x).
      min_track: fewest views that must see a point for it to be kept.
      max_error: largest mean reprojection error in pixels of a kept point.
      min_points: fewer points than this is an error (too little texture or overlap).
      num_threads: COLMAP threads (-1: all cores; only 1 gives the same points every run).
      seed: COLMAP's random seed (RANSAC).
      max_side: ``process-data --triangulate`` downscales the photos' long side to at most this.
    """

    neighbors: int = ranged(20, low=1)
    max_features: int = ranged(8192, low=1)
    peak_threshold: float = ranged(0.002, low=0.0)
    feature_side: int = ranged(512, low=1)
    min_track: int = ranged(2, low=2)
    max_error: float = ranged(2.0, low=0.0)
    min_points: int = ranged(100, low=1)
    num_threads: int = 1
    seed: int = 0
    max_side: int = ranged(1600, low=1)

    def __post_init__(self):
        check_ranges(self)


def neighbor_pairs(cameras: Camera, neighbors: int) -> list[tuple[int, int]]:
    """Sorted pairs ``(i, j)``, ``i < j``: each view with its ``neighbors`` nearest camera
    centres (every pair when there are at most ``neighbors + 1`` views)."""
    w2c = np.asarray(cameras.world_to_camera, np.float64).reshape(-1, 4, 4)
    centres = -np.einsum("nji,nj->ni", w2c[:, :3, :3], w2c[:, :3, 3])
    n = len(centres)
    dist = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    np.fill_diagonal(dist, np.inf)
    pairs = set()
    for i in range(n):
        for j in np.argsort(dist[i], kind="stable")[:min(neighbors, n - 1)]:
            pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


#: Largest factor views are enlarged by for feature extraction.
MAX_ENLARGE = 4


def enlargement(width: int, height: int, feature_side: int) -> int:
    """The integer factor (1 to :data:`MAX_ENLARGE`) that brings a view's long side to at
    least ``feature_side``."""
    return int(min(MAX_ENLARGE, max(1, -(-int(feature_side) // max(int(width), int(height))))))


def _write_views(images, folder: Path, scale: int = 1) -> list[str]:
    """PNGs of ``images`` enlarged ``scale`` times (bicubic), named view_NNNNN.png."""
    from PIL import Image

    names = [f"view_{k:05d}.png" for k in range(len(images))]
    for name, image in zip(names, images):
        image = np.asarray(image)
        if image.dtype != np.uint8:
            image = np.round(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8)
        pil = Image.fromarray(image[..., :3])
        if scale > 1:
            pil = pil.resize((pil.width * scale, pil.height * scale), Image.BICUBIC)
        pil.save(folder / name)
    return names


def _known_reconstruction(database: Path, cameras: Camera, scale: int = 1):
    """A pycolmap.Reconstruction of the database's images at the known cameras and poses,
    the views enlarged ``scale`` times (pixel edges at integers: intrinsics times ``scale``)."""
    import pycolmap

    w2c = np.asarray(cameras.world_to_camera, np.float64).reshape(-1, 4, 4)
    n = len(w2c)
    fx, fy, cx, cy = (scale * np.broadcast_to(np.asarray(getattr(cameras, k), np.float64), (n,))
                      for k in ("fx", "fy", "cx", "cy"))
    db = pycolmap.Database.open(database)
    try:
        images = db.read_all_images()
    finally:
        db.close()
    rec = pycolmap.Reconstruction()
    for image in sorted(images, key=lambda im: im.name):
        k = int(Path(image.name).stem.split("_")[1])
        camera = pycolmap.Camera(model="PINHOLE", width=scale * int(cameras.width),
                                 height=scale * int(cameras.height),
                                 params=[fx[k], fy[k], cx[k], cy[k]], camera_id=image.camera_id)
        rec.add_camera_with_trivial_rig(camera)
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=image.name, camera_id=image.camera_id, image_id=image.image_id),
            pycolmap.Rigid3d(w2c[k, :3]))
    return rec


def triangulate(images, cameras: Camera, *, options: TriangulateOptions = TriangulateOptions(),
                where="dataset", work_dir=None) -> tuple[np.ndarray, np.ndarray]:
    """SIFT features of ``images`` matched and triangulated at the known ``cameras``.

    Args:
      images: [N, H, W, 3] uint8 or float in [0, 1], undistorted (PINHOLE) views.
      cameras: batched Camera [N] of those views (OpenCV world-to-camera).
      options: :class:`TriangulateOptions`.
      where: what the views are (named by the error).
      work_dir: folder for COLMAP's images and database (None: a temporary one, removed).
    Returns:
      (points float32 [P, 3] in the cameras' world, colours float32 [P, 3] in [0, 1]).
    Raises:
      DataError: fewer than 2 views, or fewer than ``options.min_points`` points.
    """
    if work_dir is None:
        with tempfile.TemporaryDirectory(prefix="jaxedit-triangulate-") as tmp:
            return triangulate(images, cameras, options=options, where=where, work_dir=tmp)
    import pycolmap

    if len(images) < 2:
        raise DataError(where, f"triangulating needs at least 2 views, got {len(images)}; "
                               f"use --init random")
    work = Path(work_dir)
    image_dir, database = work / "images", work / "database.db"
    image_dir.mkdir(parents=True, exist_ok=True)
    database.unlink(missing_ok=True)
    scale = enlargement(cameras.width, cameras.height, options.feature_side)
    names = _write_views(images, image_dir, scale)
    pycolmap.set_random_seed(options.seed)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = options.max_features
    extraction.sift.peak_threshold = options.peak_threshold
    extraction.max_image_size = scale * max(int(cameras.width), int(cameras.height))
    extraction.num_threads = options.num_threads
    pycolmap.extract_features(database, image_dir, image_names=names,
                              camera_mode=pycolmap.CameraMode.PER_IMAGE, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    pair_file = work / "pairs.txt"
    pair_file.write_text("".join(f"{names[i]} {names[j]}\n"
                                 for i, j in neighbor_pairs(cameras, options.neighbors)))
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = options.num_threads
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = pair_file
    pycolmap.match_image_pairs(database, matching_options=matching, pairing_options=pairing,
                               device=pycolmap.Device.cpu)
    known = _known_reconstruction(database, cameras, scale)
    pipeline = pycolmap.IncrementalPipelineOptions()
    pipeline.num_threads = options.num_threads
    pipeline.random_seed = options.seed
    sparse = work / "sparse"
    sparse.mkdir(exist_ok=True)
    rec = pycolmap.triangulate_points(known, database, image_dir, sparse, clear_points=True,
                                      options=pipeline)
    kept = [p for p in rec.points3D.values()
            if p.track.length() >= options.min_track and p.error <= options.max_error]
    if len(kept) < options.min_points:
        raise DataError(where, f"triangulated {len(kept)} points at the known poses (need "
                               f"{options.min_points}): the views may lack texture or overlap; "
                               f"use --init random")
    xyz = np.array([p.xyz for p in kept], np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in kept], np.float32).reshape(-1, 3) / 255.0
    return xyz.astype(np.float32), rgb


def feature_views(data, feature_side: int, background=(1.0, 1.0, 1.0)):
    """(images [T, H, W, 3], cameras [T]): ``data``'s training views to extract features from.

    Views loaded with a long side under ``feature_side`` from larger photos are read again
    from the photos (same frames, poses and world), at the largest integer downscale that
    keeps the long side at least ``feature_side`` (the photo's own size when smaller);
    otherwise, or when they cannot be read alike, the views as loaded.

    Args:
      data: a :class:`jaxedit.io.Dataset` read from a nerfstudio transforms.json.
      feature_side: the long side features are wanted at (:class:`TriangulateOptions`).
      background: RGB that RGBA photos are composited over (as for ``data``).
    """
    import logging

    from ..io import load_nerfstudio
    from ..io.nerfstudio import nerfstudio_frame_count, nerfstudio_photo_size

    images, cameras = data.train()
    loaded = max(np.shape(images)[1:3])
    if loaded >= feature_side or getattr(data, "path", None) is None:
        return images, cameras
    try:
        photo = max(nerfstudio_photo_size(data.path))
        listed = nerfstudio_frame_count(data.path)[0]
    except (DataError, OSError, TypeError):
        return images, cameras
    factor = max(1, photo // int(feature_side))
    if photo // factor <= loaded:
        return images, cameras
    normalized = not np.allclose(data.world_transform, np.eye(4))
    try:
        full = load_nerfstudio(data.path, downscale=factor, background=background,
                               normalize="nerfstudio" if normalized else "none",
                               split_every=0, skip_missing=listed > len(data))
    except DataError as e:
        logging.getLogger(__name__).info("features on the views as loaded: %s", e)
        return images, cameras
    index = {name: k for k, name in enumerate(full.filenames)}
    names = [data.filenames[k] for k in data.train_indices]
    if not all(name in index for name in names):
        return images, cameras
    pick = np.array([index[name] for name in names], np.int64)
    same = (np.allclose(full.world_transform, data.world_transform)
            and np.allclose(np.asarray(full.cameras.world_to_camera)[pick],
                            np.asarray(cameras.world_to_camera), atol=1e-5))
    return full.subset(pick) if same else (images, cameras)


#: The file :func:`write_dataset_points` writes beside transforms.json.
POINTS_FILE = "sparse_pc.ply"


def triangulate_dataset(path, *, options: TriangulateOptions = TriangulateOptions(),
                        skip_missing: bool = False) -> tuple[np.ndarray, np.ndarray, dict]:
    """Points triangulated at the poses of the nerfstudio dataset at ``path``.

    Every listed view is read unnormalised, long side at most ``options.max_side``.

    Returns:
      (points float32 [P, 3], colours float32 [P, 3] in [0, 1], a summary: ``num_points``,
      ``num_views``, ``downscale``, ``seconds``).
    Raises:
      DataError: the dataset's own errors, or too few points (see :func:`triangulate`).
    """
    import time

    from ..io import load_nerfstudio
    from ..io.nerfstudio import auto_downscale, nerfstudio_photo_size

    start = time.perf_counter()
    factor = auto_downscale(*nerfstudio_photo_size(path), max_side=options.max_side)
    data = load_nerfstudio(path, downscale=factor, split_every=0, skip_missing=skip_missing)
    points, colors = triangulate(data.pixels, data.cameras, options=options, where=data.path)
    return points, colors, {"num_points": int(len(points)), "num_views": int(len(data)),
                            "downscale": int(factor),
                            "seconds": round(time.perf_counter() - start, 3)}


def write_dataset_points(path, points, colors) -> Path:
    """Write ``points`` as the ``ply_file_path`` of the nerfstudio dataset at ``path``.

    Writes :data:`POINTS_FILE`, then transforms.json (both atomically); a dataset that
    already has points, or an unlisted :data:`POINTS_FILE`, is refused.

    Returns:
      the path of the cloud.
    """
    from ..io.files import atomic_write_text
    from ..io.nerfstudio import _load_meta, _resolve_json
    from ..io.ply import save_points_ply

    json_path = _resolve_json(path)
    meta = _load_meta(json_path)
    if meta.get("ply_file_path") is not None:
        raise DataError(json_path, f"already has points (ply_file_path: "
                                   f"{meta['ply_file_path']!r}); remove that key to triangulate")
    ply = json_path.parent / POINTS_FILE
    if ply.exists():
        raise DataError(ply, "exists but transforms.json does not list it; move it away or "
                             "set it as ply_file_path")
    save_points_ply(ply, points, colors)
    try:
        atomic_write_text(json_path, json.dumps(meta | {"ply_file_path": POINTS_FILE},
                                                indent=2) + "\n")
    except BaseException:
        ply.unlink(missing_ok=True)
        raise
    return ply
