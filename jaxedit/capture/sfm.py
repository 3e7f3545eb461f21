"""Structure from motion with pycolmap (the optional ``capture`` extra, imported lazily):
SIFT extraction with one shared camera, matching of :func:`image_pairs`, incremental
mapping; progress through ``report(stage, done, total)``. See docs/capture.md."""

from __future__ import annotations

import dataclasses
import math
import os
import time
from pathlib import Path
from typing import Callable

from ..errors import DataError, check_ranges, ranged

MATCHING = ("exhaustive", "sequential")
CAMERA_MODELS = ("SIMPLE_RADIAL", "OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "RADIAL")
Report = Callable[[str, int, int], None]


@dataclasses.dataclass(frozen=True)
class SfmOptions:
    """Settings of :func:`run_sfm`.

    Attributes:
      camera_model: COLMAP camera model shared by all images (OPENCV for wide lenses).
      matching: "exhaustive" (photo sets) or "sequential" (video frames in order).
      overlap: successors matched to each frame in sequential matching.
      max_features: SIFT features per image (COLMAP's default 8192).
      max_image_size: images are downscaled to this longer side for SIFT (COLMAP's 3200).
      num_threads: COLMAP threads (-1: all cores).
      seed: COLMAP's random seed (RANSAC, mapper).
      chunk: images per extraction call and pairs per matching call (progress granularity).
      camera_params: known intrinsics ``(fx, fy, cx, cy[, k1[, k2[, p1, p2]]])`` px, or None.
      focal_px: known focal length in pixels (centred, no distortion); excludes camera_params.
      refine_intrinsics: refine known intrinsics in bundle adjustment instead of fixing them.
    """

    camera_model: str = "SIMPLE_RADIAL"
    matching: str = "exhaustive"
    overlap: int = ranged(10, low=1)
    max_features: int = ranged(8192, low=1)
    max_image_size: int = ranged(3200, low=1)
    num_threads: int = -1
    seed: int = 0
    chunk: int = ranged(64, low=1)
    camera_params: tuple[float, ...] | None = None
    focal_px: float | None = None
    refine_intrinsics: bool = False

    def check(self) -> "SfmOptions":
        if self.camera_model not in CAMERA_MODELS:
            raise DataError("camera_model", f"must be one of {', '.join(CAMERA_MODELS)}, "
                                              f"got {self.camera_model!r}")
        if self.matching not in MATCHING:
            raise DataError("matching", f"must be one of {', '.join(MATCHING)}, got "
                                          f"{self.matching!r}")
        check_ranges(self)
        if self.focal_px is not None and self.camera_params is not None:
            raise DataError("camera_params", "give either focal_px or camera_params, not both")
        if self.focal_px is not None and not (math.isfinite(self.focal_px) and self.focal_px > 0):
            raise DataError("focal_px", f"must be a finite number > 0, got {self.focal_px}")
        if self.camera_params is not None:
            check_camera_params(self.camera_params)
            model_params(self.camera_model, self.camera_params)  # representable in the model
        if self.refine_intrinsics and self.focal_px is None and self.camera_params is None:
            raise DataError("refine_intrinsics", "needs focal_px or camera_params (without "
                                                  "them the intrinsics are always refined)")
        return self

    def known_params(self, width: int, height: int) -> list[float] | None:
        """COLMAP parameters of ``camera_model`` for the known intrinsics (None: unknown)."""
        if self.focal_px is not None:
            f = float(self.focal_px)
            return model_params(self.camera_model, (f, f, width / 2.0, height / 2.0))
        if self.camera_params is not None:
            return model_params(self.camera_model, self.camera_params)
        return None


#: COLMAP's parameter order of each model ("f": a single focal length, fx == fy).
MODEL_PARAMS = {"SIMPLE_PINHOLE": ("f", "cx", "cy"), "PINHOLE": ("fx", "fy", "cx", "cy"),
                "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"), "RADIAL": ("f", "cx", "cy", "k1", "k2"),
                "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")}
PARAM_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")


def parse_camera_params(text: str) -> tuple[float, ...]:
    """``"fx,fy,cx,cy[,k1...]"`` (the --camera-params flag) as floats, checked."""
    try:
        values = tuple(float(t) for t in str(text).split(","))
    except ValueError:
        raise DataError("camera_params", f"expected comma-separated numbers fx,fy,cx,cy[,k1,"
                                           f"k2,p1,p2], got {text!r}") from None
    return check_camera_params(values)


def check_camera_params(values) -> tuple[float, ...]:
    """``values`` if it is 4 to 8 finite numbers with positive focal lengths, else DataError."""
    values = tuple(float(v) for v in values)
    if not 4 <= len(values) <= len(PARAM_NAMES) or len(values) == 7:
        raise DataError("camera_params", f"expected fx,fy,cx,cy then optionally k1, k2 and "
                                           f"p1,p2 (4, 5, 6 or 8 numbers), got {len(values)}")
    if not all(math.isfinite(v) for v in values):
        raise DataError("camera_params", f"must be finite numbers, got {values}")
    if values[0] <= 0 or values[1] <= 0:
        raise DataError("camera_params", f"focal lengths fx, fy must be > 0, got {values[:2]}")
    return values


def model_params(model: str, values) -> list[float]:
    """COLMAP parameters of ``model`` for intrinsics ``(fx, fy, cx, cy[, k1, k2, p1, p2])``;
    DataError for terms the model cannot hold, rather than dropping them."""
    named = dict(zip(PARAM_NAMES, (list(values) + [0.0] * len(PARAM_NAMES))[:len(PARAM_NAMES)]))
    wanted = MODEL_PARAMS[model]
    if "f" in wanted and not math.isclose(named["fx"], named["fy"], rel_tol=1e-9):
        raise DataError("camera_params", f"fx != fy but camera_model {model} has one focal "
                                           f"length; use PINHOLE or OPENCV")
    dropped = [k for k in PARAM_NAMES[4:] if k not in wanted and named[k] != 0.0]
    if dropped:
        raise DataError("camera_params", f"camera_model {model} has no {', '.join(dropped)}; "
                                           f"use OPENCV")
    return [named["fx"] if k == "f" else named[k] for k in wanted]


@dataclasses.dataclass
class SfmResult:
    """What :func:`run_sfm` found.

    Attributes:
      reconstruction: the largest pycolmap.Reconstruction (None when nothing registered).
      num_images: images given.
      num_registered: images with a pose in ``reconstruction``.
      num_models: models the mapper made.
      seconds: wall seconds of each stage ("extract", "match", "map").
      focal_source: where the starting focal length came from: "given", "exif" or "guess".
      focal_start_px: that starting focal length in pixels (before bundle adjustment).
    """

    reconstruction: object
    num_images: int
    num_registered: int
    num_models: int
    seconds: dict
    focal_source: str = "guess"
    focal_start_px: float | None = None


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
            options: SfmOptions = SfmOptions(), report: Report | None = None,
            image_size: tuple[int, int] | None = None) -> SfmResult:
    """SfM of ``names`` (files in ``image_dir``); ``work_dir`` receives ``database.db`` and
    ``sparse/<k>/``. ``image_size`` (width, height) is needed only with ``focal_px``."""
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
    if options.focal_px is not None and image_size is None:
        raise ValueError("run_sfm: focal_px needs image_size")
    known = options.known_params(*(image_size or (0, 0)))
    if known is not None:
        reader.camera_params = ",".join(repr(float(v)) for v in known)
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
        # later chunks join the first chunk's camera: one set of intrinsics
        reader.existing_camera_id = 1
        done += len(chunk)
        report("extract", done, len(names))
    seconds["extract"] = time.perf_counter() - start
    has_prior, focal_start = _starting_focal(database)
    focal_source = "given" if known is not None else ("exif" if has_prior else "guess")

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
    if known is not None:  # held fixed, or refined from there
        refine = bool(options.refine_intrinsics)
        mapping.ba_refine_focal_length = refine
        mapping.ba_refine_extra_params = refine
        mapping.ba_refine_principal_point = False  # COLMAP's default: poorly constrained
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
    return SfmResult(best, len(names), count, len(models), seconds, focal_source, focal_start)


def _starting_focal(database: Path) -> tuple[bool, float | None]:
    """(whether EXIF gave a focal length, the starting focal length px) from ``database``."""
    import pycolmap

    db = pycolmap.Database.open(database)
    try:
        cameras = db.read_all_cameras()
    finally:
        db.close()
    if not cameras:
        return False, None
    return (any(c.has_prior_focal_length for c in cameras),
            float(cameras[0].mean_focal_length()))


def quiet_colmap(quiet: bool = True) -> None:
    """Silence COLMAP's own log lines (its failures come back as our one-line errors)."""
    import pycolmap

    pycolmap.logging.minloglevel = 3 if quiet else 0
