"""Structure from motion with COLMAP, through its Python bindings (pycolmap).

Three stages, as in COLMAP's and nerfstudio's pipelines:

1. **extract**: SIFT features of every image, all images sharing one camera
   (one set of intrinsics, as for a photo series or a video from one device);
2. **match**: SIFT matches with geometric verification, for the image pairs of
   :func:`image_pairs` -- every pair ("exhaustive", for photo sets) or each
   frame with its ``overlap`` successors plus those 2, 4, 8, ... frames ahead
   ("sequential", for video frames in order, COLMAP's quadratic overlap);
3. **map**: incremental mapping; of the models it makes, the one with the most
   registered images is kept.

Every stage reports its progress through an optional callback
``report(stage, done, total)``, so callers can draw bars; extraction and
matching run in chunks for that (each chunk is multi-threaded inside COLMAP).
pycolmap is imported only here, inside the functions: it is an optional extra
(``pip install jaxedit[capture]``).
"""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path
from typing import Callable

from ..errors import DataError

MATCHING = ("exhaustive", "sequential")
CAMERA_MODELS = ("SIMPLE_RADIAL", "OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "RADIAL")
Report = Callable[[str, int, int], None]


@dataclasses.dataclass(frozen=True)
class SfmOptions:
    """Settings of :func:`run_sfm`.

    Attributes:
      camera_model: COLMAP camera model shared by all images. SIMPLE_RADIAL (COLMAP's
        default: one focal length, one radial coefficient) is well conditioned with few
        views; OPENCV (nerfstudio's choice) adds fx != fy and k2, p1, p2 for wide lenses.
      matching: "exhaustive" or "sequential" (see the module docstring).
      overlap: successors matched to each frame in sequential matching.
      max_features: SIFT features per image (COLMAP's default 8192).
      max_image_size: images are downscaled to this longer side for SIFT (COLMAP's 3200).
      num_threads: COLMAP threads (-1: all cores).
      seed: COLMAP's random seed (RANSAC, mapper).
      chunk: images per extraction call and pairs per matching call (progress granularity).
    """

    camera_model: str = "SIMPLE_RADIAL"
    matching: str = "exhaustive"
    overlap: int = 10
    max_features: int = 8192
    max_image_size: int = 3200
    num_threads: int = -1
    seed: int = 0
    chunk: int = 64

    def check(self) -> "SfmOptions":
        if self.camera_model not in CAMERA_MODELS:
            raise DataError("camera_model", f"must be one of {', '.join(CAMERA_MODELS)}, "
                                              f"got {self.camera_model!r}")
        if self.matching not in MATCHING:
            raise DataError("matching", f"must be one of {', '.join(MATCHING)}, got "
                                          f"{self.matching!r}")
        for name in ("overlap", "max_features", "max_image_size", "chunk"):
            if getattr(self, name) < 1:
                raise DataError(name, f"must be >= 1, got {getattr(self, name)}")
        return self


@dataclasses.dataclass
class SfmResult:
    """What :func:`run_sfm` found.

    Attributes:
      reconstruction: the largest pycolmap.Reconstruction (None when nothing registered).
      num_images: images given.
      num_registered: images with a pose in ``reconstruction``.
      num_models: models the mapper made.
      seconds: wall seconds of each stage ("extract", "match", "map").
    """

    reconstruction: object
    num_images: int
    num_registered: int
    num_models: int
    seconds: dict


def image_pairs(num_images: int, matching: str, overlap: int = 10) -> list[tuple[int, int]]:
    """Index pairs (i < j) to match: all of them, or sequential with quadratic overlap."""
    if matching == "exhaustive":
        return [(i, j) for i in range(num_images) for j in range(i + 1, num_images)]
    if matching != "sequential":
        raise DataError("matching", f"must be one of {', '.join(MATCHING)}, got {matching!r}")
    ahead = set(range(1, overlap + 1)) | {2 ** k for k in range(max(num_images, 1).bit_length())}
    return sorted((i, i + d) for i in range(num_images) for d in ahead if i + d < num_images)


def _chunks(items: list, size: int) -> list[list]:
    return [items[k:k + size] for k in range(0, len(items), size)]


def run_sfm(image_dir: str | os.PathLike, names: list[str], work_dir: str | os.PathLike,
            options: SfmOptions = SfmOptions(), report: Report | None = None) -> SfmResult:
    """Run the three stages on ``names`` (files in ``image_dir``); COLMAP files go to ``work_dir``.

    ``work_dir`` receives ``database.db`` and ``sparse/<k>/`` (COLMAP's binary models),
    which COLMAP's GUI and nerfstudio's tools open.
    """
    import pycolmap

    options.check()
    report = report or (lambda stage, done, total: None)
    image_dir, work_dir = Path(image_dir), Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    database = work_dir / "database.db"
    if database.exists():
        database.unlink()  # a stale database would mix in other images
    pycolmap.set_random_seed(options.seed)
    device = pycolmap.Device.cpu
    seconds = {}

    start = time.perf_counter()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = options.camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = options.max_features
    extraction.max_image_size = options.max_image_size
    extraction.num_threads = options.num_threads
    done = 0
    report("extract", 0, len(names))
    for chunk in _chunks(list(names), options.chunk):
        pycolmap.extract_features(database, image_dir, image_names=chunk,
                                  camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                  extraction_options=extraction, device=device)
        # Later chunks join the camera that the first chunk created: one set of intrinsics.
        reader.existing_camera_id = 1
        done += len(chunk)
        report("extract", done, len(names))
    seconds["extract"] = time.perf_counter() - start

    start = time.perf_counter()
    pairs = image_pairs(len(names), options.matching, options.overlap)
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = options.num_threads
    pair_file = work_dir / "pairs.txt"
    done = 0
    report("match", 0, len(pairs))
    for chunk in _chunks(pairs, options.chunk):
        pair_file.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in chunk))
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = pair_file
        pycolmap.match_image_pairs(database, matching_options=matching, pairing_options=pairing,
                                   device=device)
        done += len(chunk)
        report("match", done, len(pairs))
    pair_file.unlink(missing_ok=True)
    seconds["match"] = time.perf_counter() - start

    start = time.perf_counter()
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = options.num_threads
    mapping.random_seed = options.seed
    registered = [0]
    report("map", 0, len(names))

    def next_image():
        registered[0] += 1
        report("map", min(registered[0], len(names)), len(names))

    sparse = work_dir / "sparse"
    sparse.mkdir(exist_ok=True)
    models = pycolmap.incremental_mapping(database, image_dir, sparse, options=mapping,
                                          next_image_callback=next_image)
    seconds["map"] = time.perf_counter() - start
    best = max(models.values(), key=lambda r: r.num_reg_images(), default=None)
    count = 0 if best is None else int(best.num_reg_images())
    report("map", count, len(names))
    return SfmResult(best, len(names), count, len(models), seconds)


def quiet_colmap(quiet: bool = True) -> None:
    """Silence COLMAP's own log lines (its failures come back as our one-line errors)."""
    import pycolmap

    pycolmap.logging.minloglevel = 3 if quiet else 0
