"""nerfstudio ``transforms.json`` datasets: load them, write them.

The format (reference.md section 2): intrinsics at the top level or per frame
(``fl_x fl_y cx cy w h camera_model``, distortion ``k1 k2 k3 k4 p1 p2``), ``frames`` with a
``file_path`` and a ``transform_matrix`` (4x4 OpenGL camera-to-world), optional
``ply_file_path`` and ``train/val/test_filenames``. :func:`load_nerfstudio` sorts frames by
``file_path`` (as nerfstudio does); takes PINHOLE, SIMPLE_PINHOLE and OPENCV (undistorted on
load and cropped to the pixels with a source, :mod:`jaxedit.io.distortion`), refusing any other
model; splits by the filename lists, else holds out ``index % split_every == 0``;
downscales by f x f block averages with K / f; turns EXIF-rotated photos upright when
their upright size is the declared one; and with ``normalize="nerfstudio"`` orients up,
centres and scales (``world_transform`` records the similarity). Every problem raises
:class:`DataError` naming the file or field.
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import Camera, check_cameras, opencv_w2c_to_opengl_c2w, opengl_c2w_to_opencv_w2c
from ..errors import DataError
from ..gaussians import Gaussians
from .distortion import (Distortion, source_inside, undistort_image, undistortion_table,
                         valid_rectangle)
from .files import current_umask
from .images import SWAPPING_ORIENTATIONS, photo_header, read_photo, write_image
from .ply import load_points_ply, save_points_ply
from .similarity import transform_cameras, transform_gaussians, transform_points

SUPPORTED_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV")
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
_RIGID_TOL = 1e-3  # max |R^T R - I| accepted as a rotation
NORMALIZE_MODES = ("none", "nerfstudio")
#: nerfstudio's (and 3DGS's) default: a capture's long side is brought to at most this.
MAX_AUTO_SIDE = 1600

log = logging.getLogger("jaxedit.io")


@dataclass(frozen=True)
class Dataset:
    """A loaded posed-image dataset.

    Attributes:
      path: the transforms.json it came from.
      pixels: [N, H, W, 3] the views as loaded: uint8 when every photo is 8-bit, else float32.
      cameras: batched Camera [N], OpenCV world->camera, in the (normalised) world.
      filenames: the frames' ``file_path`` strings as in the json, in dataset order.
      train_indices: int [Ntrain]; test_indices: int [Ntest].
      points: float32 [P, 3] initial points in the (normalised) world, or None.
      point_colors: float32 [P, 3] in [0, 1], or None.
      world_transform: float64 [4, 4] similarity, normalised = world_transform @ original.
      scene_scale: the uniform scale inside ``world_transform`` (1.0 when not normalised).
    """

    path: Path
    pixels: np.ndarray
    cameras: Camera
    filenames: list[str]
    train_indices: np.ndarray
    test_indices: np.ndarray
    points: np.ndarray | None
    point_colors: np.ndarray | None
    world_transform: np.ndarray
    scene_scale: float

    def __len__(self) -> int:
        return len(self.pixels)

    @property
    def images(self) -> np.ndarray:
        """float32 [N, H, W, 3] in [0, 1]: every view, converted on each access (4x the
        memory of uint8 :attr:`pixels`; prefer :meth:`subset` or :attr:`pixels`)."""
        return as_float_images(self.pixels)

    @property
    def image_size(self) -> tuple[int, int]:
        """(height, width) of the views."""
        return int(self.pixels.shape[1]), int(self.pixels.shape[2])

    def subset(self, indices) -> tuple[np.ndarray, Camera]:
        """(images float32 [M, H, W, 3], cameras [M]) for the given view indices."""
        indices = np.asarray(indices, np.int64)
        return as_float_images(self.pixels[indices]), self.cameras[indices]

    def subset_pixels(self, indices) -> tuple[np.ndarray, Camera]:
        """(:attr:`pixels` [M, H, W, 3] as stored, cameras [M]) for the given view indices:
        what :func:`jaxedit.train.fit` takes without a float copy."""
        indices = np.asarray(indices, np.int64)
        return self.pixels[indices], self.cameras[indices]

    def train(self) -> tuple[np.ndarray, Camera]:
        """(images, cameras) of the training views."""
        return self.subset(self.train_indices)

    def test(self) -> tuple[np.ndarray, Camera]:
        """(images, cameras) of the held-out views."""
        return self.subset(self.test_indices)

    def to_original_points(self, points) -> np.ndarray:
        """float [..., 3] normalised-world points -> the dataset's original world."""
        return transform_points(points, np.linalg.inv(self.world_transform))

    def to_original_cameras(self, cameras: Camera) -> Camera:
        """Cameras in the normalised world -> the same cameras in the original world."""
        return transform_cameras(cameras, np.linalg.inv(self.world_transform))

    def to_original_gaussians(self, gaussians: Gaussians) -> Gaussians:
        """A scene fitted in the normalised world -> the dataset's original world."""
        return transform_gaussians(gaussians, np.linalg.inv(self.world_transform))


def as_float_images(pixels) -> np.ndarray:
    """float32 [..., 3] in [0, 1] of uint8 or float ``pixels`` (uint8 times 1/255: bit for bit
    OpenImageIO's float read of an 8-bit file)."""
    pixels = np.asarray(pixels)
    if pixels.dtype == np.uint8:
        return pixels.astype(np.float32) * np.float32(1.0 / 255.0)
    return pixels.astype(np.float32, copy=False)


# ---------------------------------------------------------------------------
# nerfstudio's normalisation


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation [3, 3] taking unit vector ``a`` onto unit vector ``b`` (Rodrigues)."""
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if c < -1.0 + 1e-10:  # opposite: half-turn about any axis perpendicular to a
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def nerfstudio_world_transform(c2w_opengl: np.ndarray) -> tuple[np.ndarray, float]:
    """nerfstudio's default pose normalisation as a similarity: mean camera up onto +z,
    centred on the mean camera position, largest |camera coordinate| scaled to 1.

    Args:
      c2w_opengl: float [N, 4, 4] (or [N, 3, 4]) camera-to-world poses.
    Returns:
      (world_transform float64 [4, 4] = diag(s, s, s, 1) @ [R | -R mean], s).
    """
    c2w = np.asarray(c2w_opengl, np.float64)
    centres = c2w[:, :3, 3]
    mean = centres.mean(axis=0)
    up = c2w[:, :3, 1].mean(axis=0)
    norm = np.linalg.norm(up)
    rot = np.eye(3) if norm < 1e-12 else _rotation_between(up / norm, np.array([0.0, 0.0, 1.0]))
    rigid = np.eye(4)
    rigid[:3, :3] = rot
    rigid[:3, 3] = -rot @ mean
    moved = centres @ rot.T + rigid[:3, 3]
    extent = float(np.abs(moved).max()) if len(moved) else 0.0
    scale = 1.0 if extent < 1e-12 else 1.0 / extent
    return np.diag([scale, scale, scale, 1.0]) @ rigid, scale


# ---------------------------------------------------------------------------
# Reading


def _resolve_json(path) -> Path:
    path = Path(path).expanduser()
    if path.is_dir():
        path = path / "transforms.json"
    if not path.exists():
        raise DataError(path, "transforms.json not found")
    if not path.is_file():
        raise DataError(path, "not a file")
    return path


def _load_meta(path: Path) -> dict:
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise DataError(path, "is not UTF-8 text") from None
    except OSError as e:
        raise DataError(path, f"cannot read file ({e.strerror or e})") from None
    try:
        meta = json.loads(text)
    except json.JSONDecodeError as e:
        raise DataError(path, f"malformed JSON at line {e.lineno} column {e.colno}: {e.msg}") from None
    except RecursionError:
        raise DataError(path, "malformed JSON: nested too deeply") from None
    if not isinstance(meta, dict):
        raise DataError(path, f"top level must be a JSON object, got {type(meta).__name__}")
    frames = meta.get("frames")
    if frames is None:
        raise DataError(path, "missing key 'frames'")
    if not isinstance(frames, list) or not frames:
        raise DataError(path, "'frames' must be a non-empty list")
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise DataError(path, f"frames[{i}] must be a JSON object")
    return meta


_MAX_VALUE = 1e30  # larger values cannot be real intrinsics or poses (and overflow float32)


def _number(path: Path, field: str, value, *, positive=False, integer=False, bound=False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise DataError(path, f"{field} must be a number, got {json.dumps(value)[:40]}")
    try:
        value = float(value)
    except OverflowError:
        raise DataError(path, f"{field} is too large") from None
    if not math.isfinite(value):
        raise DataError(path, f"{field} has a non-finite value ({value})")
    if positive and value <= 0:
        raise DataError(path, f"{field} must be positive, got {value}")
    if bound and abs(value) > _MAX_VALUE:
        raise DataError(path, f"{field} is implausibly large ({value:g})")
    if integer and value != int(value):
        raise DataError(path, f"{field} must be a whole number, got {value}")
    return value


@dataclass(frozen=True)
class _Intrinsics:
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: Distortion


def _intrinsics(path: Path, meta: dict, frame: dict, where: str) -> _Intrinsics:
    """Per-frame keys win over top-level ones."""
    def get(key):
        if key in frame:
            return frame[key], f"{where}.{key}"
        return meta.get(key), key

    model, model_field = get("camera_model")
    dist_given = {k: get(k) for k in _DISTORTION_KEYS}
    if model is None:
        # nerfstudio's default is OPENCV; with no coefficients that is a pinhole.
        model = "OPENCV"
    if not isinstance(model, str) or model.upper() not in SUPPORTED_MODELS:
        raise DataError(path, f"{model_field}: unsupported camera model {json.dumps(model)[:40]} "
                              f"(supported: {', '.join(SUPPORTED_MODELS)}; fisheye and other "
                              f"models are not)")
    model = model.upper()

    def required(key, **kw):
        value, field = get(key)
        if value is None:
            raise DataError(path, f"missing intrinsic '{key}' (neither in {where} nor at top level)")
        return _number(path, field, value, **kw)

    fx = required("fl_x", positive=True, bound=True)
    if model == "SIMPLE_PINHOLE" and get("fl_y")[0] is None:
        fy = fx
    else:
        fy = required("fl_y", positive=True, bound=True)
    cx, cy = required("cx", bound=True), required("cy", bound=True)
    w = int(required("w", positive=True, integer=True, bound=True))
    h = int(required("h", positive=True, integer=True, bound=True))
    coeffs = {k: 0.0 if v is None else _number(path, f, v, bound=True)
              for k, (v, f) in dist_given.items()}
    distortion = Distortion(**coeffs)
    if model != "OPENCV" and not distortion.is_zero():
        raise DataError(path, f"{model_field}: camera model {model} declares non-zero distortion "
                              f"coefficients; use OPENCV")
    return _Intrinsics(fx, fy, cx, cy, w, h, distortion)


def _pose(path: Path, frame: dict, where: str) -> np.ndarray:
    if "transform_matrix" not in frame:
        raise DataError(path, f"{where}: missing key 'transform_matrix'")
    raw = frame["transform_matrix"]
    field = f"{where}.transform_matrix"
    shape_ok = (isinstance(raw, list) and len(raw) in (3, 4)
                and all(isinstance(row, list) and len(row) == 4 for row in raw))
    if not shape_ok:
        raise DataError(path, f"{field} must be a 4x4 (or 3x4) list of lists of numbers")
    m = np.array([[_number(path, field, x, bound=True) for x in row] for row in raw], np.float64)
    if not np.isfinite(m).all():
        raise DataError(path, f"{field} has non-finite values")
    if m.shape == (3, 4):
        m = np.concatenate([m, [[0.0, 0.0, 0.0, 1.0]]], axis=0)
    if np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-6:
        raise DataError(path, f"{field} last row must be [0, 0, 0, 1], got {m[3].tolist()}")
    r = m[:3, :3]
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    if err > _RIGID_TOL:
        raise DataError(path, f"{field} is not a rigid transform (rotation part is not "
                              f"orthonormal: max |R^T R - I| = {err:.3g})")
    if np.linalg.det(r) < 0:
        raise DataError(path, f"{field} is not a rigid transform (rotation has determinant < 0, "
                              f"a reflection)")
    return m


def _file_path(path: Path, frame: dict, where: str) -> str:
    fp = frame.get("file_path")
    if fp is None:
        raise DataError(path, f"{where}: missing key 'file_path'")
    if not isinstance(fp, str) or not fp.strip():
        raise DataError(path, f"{where}.file_path must be a non-empty string")
    return fp


def _norm_name(name: str) -> str:
    return os.path.normpath(name)


def _resolve_image(json_path: Path, file_path: str, where: str) -> Path | None:
    """The image file of a frame's ``file_path``, or None when it does not exist."""
    if "\0" in file_path:
        raise DataError(json_path, f"{where}.file_path contains a NUL character")
    p = Path(file_path)
    p = p if p.is_absolute() else json_path.parent / p
    if p.is_file():
        return p
    if not p.suffix:  # Blender/instant-ngp style names without an extension
        for suffix in (".png", ".jpg", ".jpeg", ".exr"):
            if p.with_suffix(suffix).is_file():
                return p.with_suffix(suffix)
    return None


def _listing(names, limit: int | None = 5) -> str:
    shown = list(names) if limit is None else list(names)[:limit]
    more = len(names) - len(shown)
    return ", ".join(shown) + (f" and {more} more" if more > 0 else "")


def _drop_missing(json_path: Path, parsed: list, skip_missing: bool):
    """(the frames whose image exists, their image paths, the names dropped)."""
    paths = [_resolve_image(json_path, fp, where) for fp, _, _, where in parsed]
    missing = [p[0] for p, path in zip(parsed, paths) if path is None]
    if not missing:
        return parsed, paths, []
    if not skip_missing:
        if len(missing) == 1:
            where = next(p[3] for p in parsed if p[0] == missing[0])
            raise DataError(json_path, f"{where}.file_path: image file {missing[0]!r} not found "
                            f"(1 of {len(parsed)} frames' images is missing; "
                            f"--skip-missing-images drops it)")
        raise DataError(json_path, f"{len(missing)} of {len(parsed)} frames' image files are "
                        f"missing ({_listing(missing)}); --skip-missing-images drops them")
    if len(missing) == len(parsed):
        raise DataError(json_path, f"all {len(parsed)} frames' image files are missing")
    log.warning("%s: dropping %d of %d frames whose image files are missing: %s", json_path,
                len(missing), len(parsed), _listing(missing, None))
    kept = [(p, path) for p, path in zip(parsed, paths) if path is not None]
    return [k[0] for k in kept], [k[1] for k in kept], missing


def _split(path: Path, meta: dict, names: list[str], split_every: int, dropped=()):
    """(train_indices, test_indices) from filename lists or the interval rule; names of
    ``dropped`` frames in the lists are passed over."""
    index = {_norm_name(n): i for i, n in enumerate(names)}
    gone = {_norm_name(n) for n in dropped}

    def indices_of(key):
        value = meta.get(key)
        if value is None:
            return None
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise DataError(path, f"{key} must be a list of file paths")
        out = []
        for v in value:
            i = index.get(_norm_name(v))
            if i is None and _norm_name(v) in gone:
                continue
            if i is None:
                raise DataError(path, f"{key}: {v!r} is not the file_path of any frame")
            out.append(i)
        return np.array(sorted(set(out)), np.int64)

    train = indices_of("train_filenames")
    test = indices_of("test_filenames")
    if test is None:
        test = indices_of("val_filenames")
    n = len(names)
    if train is None and test is None:
        all_idx = np.arange(n)
        if split_every is None or split_every <= 0:
            return all_idx, np.zeros((0,), np.int64)
        held = all_idx % split_every == 0
        return all_idx[~held], all_idx[held]
    if test is None:
        test = np.setdiff1d(np.arange(n), train)
    if train is None:
        train = np.setdiff1d(np.arange(n), test)
    return train.astype(np.int64), test.astype(np.int64)


def _downscale_image(image: np.ndarray, factor: int) -> np.ndarray:
    """Area average of factor x factor blocks (right/bottom remainder cropped)."""
    if factor == 1:
        return image
    h, w = image.shape[0] // factor, image.shape[1] // factor
    img = image[:h * factor, :w * factor].astype(np.float64)
    return img.reshape(h, factor, w, factor, -1).mean(axis=(1, 3)).astype(np.float32)


def _parse_frames(json_path: Path, meta: dict):
    """Every frame's (file path, pose, intrinsics, where), parsed and validated before any
    image is decoded (fail fast), in nerfstudio's order; and the one (width, height) of them."""
    parsed = []
    for i, frame in enumerate(meta["frames"]):
        where = f"frames[{i}]"
        fp = _file_path(json_path, frame, where)
        parsed.append((fp, _pose(json_path, frame, where), _intrinsics(json_path, meta, frame, where),
                       where))
    names = [p[0] for p in parsed]
    if len(set(map(_norm_name, names))) != len(names):
        dup = next(n for n in names if sum(_norm_name(m) == _norm_name(n) for m in names) > 1)
        raise DataError(json_path, f"file_path {dup!r} appears in more than one frame")
    # nerfstudio sorts frames by file path (pathlib order: part by part, "./" ignored)
    parsed.sort(key=lambda p: Path(p[0]).parts)
    sizes = {(p[2].width, p[2].height) for p in parsed}
    if len(sizes) != 1:
        raise DataError(json_path, f"frames have different image sizes {sorted(sizes)}; "
                                   f"jaxedit needs one size per dataset")
    return parsed, next(iter(sizes))


def _check_downscale(downscale) -> int:
    if isinstance(downscale, bool) or not isinstance(downscale, (int, np.integer)) or downscale < 1:
        raise DataError("downscale", f"must be an integer >= 1, got {downscale!r}")
    return int(downscale)


def _scaled_size(full_w: int, full_h: int, downscale: int) -> tuple[int, int]:
    """(height, width) of the images after ``downscale``, or a DataError if none is left."""
    if full_w // downscale < 1 or full_h // downscale < 1:
        raise DataError("downscale", f"factor {downscale} is larger than the {full_w}x{full_h} "
                        "images: no pixels would be left")
    return full_h // downscale, full_w // downscale


def auto_downscale(width: int, height: int, max_side: int = MAX_AUTO_SIDE) -> int:
    """The smallest power of two that brings the long side of ``width`` x ``height`` to at
    most ``max_side`` (nerfstudio's rule for a capture loaded without a factor)."""
    factor = 1
    while max(width, height) / factor > max_side:
        factor *= 2
    return factor


def _scaled_intrinsics(intr: _Intrinsics, f: int) -> tuple[float, float, float, float]:
    # Pixel centres at integer + 0.5: an f x f block average is exact with K / f.
    return intr.fx / f, intr.fy / f, intr.cx / f, intr.cy / f


def _crop(parsed: list, height: int, width: int, downscale: int) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) at the loaded size: the pixels of every frame whose undistorted
    source lies in its photo (the whole image without distortion)."""
    x0, y0, x1, y1 = 0, 0, width, height
    seen = set()
    for _, _, intr, _ in parsed:
        if intr.distortion.is_zero() or intr in seen:
            continue
        seen.add(intr)
        inside = source_inside(height, width, *_scaled_intrinsics(intr, downscale),
                               intr.distortion)
        a, b, c, d = valid_rectangle(inside)
        x0, y0, x1, y1 = max(x0, a), max(y0, b), min(x1, c), min(y1, d)
    return x0, y0, x1, y1


def _view_geometry(json_path: Path, parsed: list, full_w: int, full_h: int, downscale: int):
    """((height, width) as loaded, the crop (x0, y0, x1, y1) at the downscaled size)."""
    height, width = _scaled_size(full_w, full_h, downscale)
    crop = _crop(parsed, height, width, downscale)
    x0, y0, x1, y1 = crop
    if x1 <= x0 or y1 <= y0:
        raise DataError(json_path, "the lens distortion leaves no undistorted pixel with a "
                                   "source inside the photo (check k1..k4, p1, p2)")
    return (y1 - y0, x1 - x0), crop


def nerfstudio_view_size(path: str | os.PathLike, *, downscale: int = 1) -> tuple[int, int]:
    """(height, width) of the views :func:`load_nerfstudio` would give, from transforms.json
    alone (no image decoded), with its errors."""
    downscale = _check_downscale(downscale)
    json_path = _resolve_json(path)
    parsed, (full_w, full_h) = _parse_frames(json_path, _load_meta(json_path))
    return _view_geometry(json_path, parsed, full_w, full_h, downscale)[0]


def dataset_downscale(path: str | os.PathLike, downscale: int | None) -> int:
    """``downscale``, or when None the factor :func:`auto_downscale` picks for the photos of
    the dataset at ``path`` (from transforms.json alone; a factor above 1 is logged)."""
    if downscale is not None:
        return int(downscale)
    width, height = nerfstudio_photo_size(path)
    factor = auto_downscale(width, height)
    if factor > 1:
        log.warning("downscale %d: the %dx%d photos are used at %dx%d (long side <= %d px, "
                    "nerfstudio's default); --downscale 1 keeps full size", factor, width,
                    height, width // factor, height // factor, MAX_AUTO_SIDE)
    return factor


def nerfstudio_photo_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) that transforms.json declares for its photos (nothing decoded)."""
    json_path = _resolve_json(path)
    return _parse_frames(json_path, _load_meta(json_path))[1]


def nerfstudio_frame_count(path: str | os.PathLike) -> tuple[int, int]:
    """(frames listed, bytes a loaded view's channel takes: 1 when the first photo found is
    8-bit, else 4), from transforms.json and one image header: a load's memory ahead of it."""
    json_path = _resolve_json(path)
    parsed, _ = _parse_frames(json_path, _load_meta(json_path))
    for fp, _, _, where in parsed:
        image = _resolve_image(json_path, fp, where)
        if image is not None:
            return len(parsed), 1 if photo_header(image)[3] else 4
    return len(parsed), 1


def _orientation(image_path: Path, header, intr: _Intrinsics, where: str) -> int:
    """The EXIF orientation to apply: the photo's own when its upright size is the declared
    one, none when only its stored size is (posed as stored, as COLMAP reads photos)."""
    h, w, tag, _ = header
    upright = (w, h) if tag in SWAPPING_ORIENTATIONS else (h, w)
    if upright == (intr.height, intr.width):
        return tag
    if (h, w) == (intr.height, intr.width):
        return 1
    raise DataError(image_path, f"image is {upright[1]}x{upright[0]} but {where} declares "
                                f"w={intr.width}, h={intr.height}")


def _load_view(image_path: Path, intr: _Intrinsics, orientation: int, downscale: int, crop,
               bg: np.ndarray, eight_bit: bool, tables: dict) -> np.ndarray:
    """One view as loaded: decoded at 1/downscale, undistorted there, cropped; uint8 or
    float32 [h, w, 3]. ``tables``: the undistortion remaps by camera, filled as needed."""
    image = read_photo(image_path, downscale, orientation=orientation, background=bg)
    expect = (intr.height // downscale, intr.width // downscale)
    if image.shape[:2] != expect:
        raise DataError(image_path, f"decoded {image.shape[1]}x{image.shape[0]} pixels at 1/"
                                    f"{downscale}, expected {expect[1]}x{expect[0]}")
    if not intr.distortion.is_zero():
        k = _scaled_intrinsics(intr, downscale)
        if intr not in tables:  # one remap per camera, not per photo
            tables[intr] = undistortion_table(*expect, *k, intr.distortion)
        image = undistort_image(image, *k, intr.distortion, fill=bg, table=tables[intr])
    x0, y0, x1, y1 = crop
    image = image[y0:y1, x0:x1]
    if eight_bit:
        return np.round(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8)
    return np.ascontiguousarray(image, np.float32)


def _cameras(json_path: Path, parsed: list, downscale: int, crop, normalize: str):
    """(batched Camera of the views as loaded, world transform [4, 4], scale)."""
    x0, y0, x1, y1 = crop
    intr_arr = np.asarray([_scaled_intrinsics(p[2], downscale) for p in parsed], np.float64)
    intr_arr[:, 2] -= x0
    intr_arr[:, 3] -= y0

    c2w = np.stack([p[1] for p in parsed])
    if normalize == "nerfstudio":
        world_transform, scale = nerfstudio_world_transform(c2w)
    else:
        world_transform, scale = np.eye(4), 1.0
    cameras = Camera(
        world_to_camera=opengl_c2w_to_opencv_w2c(c2w).astype(np.float32),
        fx=intr_arr[:, 0].astype(np.float32), fy=intr_arr[:, 1].astype(np.float32),
        cx=intr_arr[:, 2].astype(np.float32), cy=intr_arr[:, 3].astype(np.float32),
        width=x1 - x0, height=y1 - y0)
    check_cameras(cameras, json_path)
    if normalize != "none":
        cameras = transform_cameras(cameras, world_transform)
    return cameras, world_transform, scale


def load_nerfstudio_cameras(path: str | os.PathLike, *, downscale: int = 1,
                            normalize: str = "none", split_every: int = 8
                            ) -> tuple[Camera, np.ndarray, np.ndarray]:
    """The cameras of every frame as :func:`load_nerfstudio` gives them, from transforms.json
    alone (frames whose image is missing keep their cameras).

    Returns:
      (batched Camera [N], train_indices int64 [T], test_indices int64 [E]).
    """
    downscale = _check_downscale(downscale)
    if normalize not in NORMALIZE_MODES:
        raise DataError("normalize", f"must be one of {NORMALIZE_MODES}, got {normalize!r}")
    json_path = _resolve_json(path)
    meta = _load_meta(json_path)
    parsed, (full_w, full_h) = _parse_frames(json_path, meta)
    crop = _view_geometry(json_path, parsed, full_w, full_h, downscale)[1]
    train_idx, test_idx = _split(json_path, meta, [p[0] for p in parsed], split_every)
    return _cameras(json_path, parsed, downscale, crop, normalize)[0], train_idx, test_idx


def load_nerfstudio(path: str | os.PathLike, *, downscale: int = 1, background=(1.0, 1.0, 1.0),
                    normalize: str = "none", split_every: int = 8, skip_missing: bool = False,
                    cache: bool = True) -> Dataset:
    """Load a nerfstudio dataset (see the module docstring for the exact rules).

    Args:
      path: the dataset folder or its transforms.json.
      downscale: integer factor >= 1 (area average; intrinsics divided by it).
      background: RGB in [0, 1] for compositing RGBA images.
      normalize: "none" (poses as in the file) or "nerfstudio".
      split_every: hold out ``index % split_every == 0`` without filename lists (0: none).
      skip_missing: drop (with a warning) the frames whose image is missing instead of raising.
      cache: use the dataset's view cache (:mod:`jaxedit.io.view_cache`); False decodes every photo.
    Returns:
      a :class:`Dataset`.
    Raises:
      DataError: for any problem with the json, the images or the points.
    """
    from .view_cache import ViewCache, cache_folder

    downscale = _check_downscale(downscale)
    if normalize not in NORMALIZE_MODES:
        raise DataError("normalize", f"must be one of {NORMALIZE_MODES}, got {normalize!r}")
    bg = np.asarray(background, np.float64)
    if bg.shape != (3,) or not np.isfinite(bg).all():
        raise DataError("background", "must be three finite numbers")
    json_path = _resolve_json(path)
    meta = _load_meta(json_path)

    parsed, (full_w, full_h) = _parse_frames(json_path, meta)
    (height, width), crop = _view_geometry(json_path, parsed, full_w, full_h, downscale)
    parsed, image_paths, dropped = _drop_missing(json_path, parsed, skip_missing)
    names = [p[0] for p in parsed]
    train_idx, test_idx = _split(json_path, meta, names, split_every, dropped)

    headers = [photo_header(p) for p in image_paths]  # sizes checked before any decoding
    orientations = [_orientation(path, header, p[2], p[3])
                    for path, header, p in zip(image_paths, headers, parsed)]
    eight_bit = all(h[3] for h in headers)
    # At full size without distortion a cached view would be the photo again, uncompressed.
    transformed = downscale > 1 or any(not p[2].distortion.is_zero() for p in parsed)
    views = ViewCache(cache_folder(json_path.parent) if cache and transformed else None)
    pixels = np.empty((len(parsed), height, width, 3), np.uint8 if eight_bit else np.float32)
    tables: dict = {}
    for k, ((name, _, intr, _), image_path, o) in enumerate(zip(parsed, image_paths,
                                                               orientations)):
        entry = views.entry(image_path, _norm_name(name), {
            "downscale": downscale, "intrinsics": [intr.fx, intr.fy, intr.cx, intr.cy,
                                                   intr.width, intr.height],
            "distortion": list(intr.distortion), "crop": list(crop), "orientation": o,
            "background": bg.tolist(), "uint8": eight_bit})
        view = views.get(entry, (height, width, 3), pixels.dtype)
        if view is None:
            view = _load_view(image_path, intr, o, downscale, crop, bg, eight_bit, tables)
            views.put(entry, view)
        pixels[k] = view
    cameras, world_transform, scale = _cameras(json_path, parsed, downscale, crop, normalize)

    points = colors = None
    if meta.get("ply_file_path") is not None:
        ply = meta["ply_file_path"]
        if not isinstance(ply, str) or not ply.strip():
            raise DataError(json_path, "ply_file_path must be a non-empty string")
        if "\0" in ply:
            raise DataError(json_path, "ply_file_path contains a NUL character")
        ply_path = Path(ply) if Path(ply).is_absolute() else json_path.parent / ply
        if not ply_path.is_file():
            raise DataError(json_path, f"ply_file_path: {ply!r} not found")
        points, colors = load_points_ply(ply_path)
        points = transform_points(points, world_transform).astype(np.float32)

    return Dataset(path=json_path, pixels=pixels, cameras=cameras, filenames=names,
                   train_indices=train_idx, test_indices=test_idx, points=points,
                   point_colors=colors, world_transform=world_transform, scene_scale=float(scale))


# ---------------------------------------------------------------------------
# Writing


def save_nerfstudio(out_dir: str | os.PathLike, images, cameras: Camera, *, filenames=None,
                    train_indices=None, test_indices=None, points=None, point_colors=None,
                    image_format: str = "png") -> Path:
    """Write a nerfstudio dataset: ``transforms.json``, ``images/*`` and ``sparse_pc.ply``.

    nerfstudio's dataparser reads it, and :func:`load_nerfstudio` reads it back to the same
    images (up to PNG's 8 bits), cameras and split (PINHOLE, OpenGL camera-to-world).

    Args:
      out_dir: folder to create or update (staged; a failure leaves nothing half-written).
      images: float [N, H, W, 3] in [0, 1], or [N, H, W, 4] with straight alpha.
      cameras: batched Camera [N] of size W x H.
      filenames: N relative paths (default ``images/frame_00000.<fmt>``).
      train_indices, test_indices: int arrays; one given, the other is its complement.
      points, point_colors: float [P, 3] initial points (colours in [0, 1]).
      image_format: "png" (8-bit), "exr" (float) or "jpg" for default names.
    Returns:
      the path of the written transforms.json.
    """
    out_dir = Path(out_dir)
    images = np.asarray(images)
    if images.ndim != 4 or images.shape[-1] not in (3, 4):
        raise DataError("images", f"expected float [N, H, W, 3] or [N, H, W, 4], got shape "
                                  f"{list(images.shape)}")
    n, h, w = images.shape[:3]
    w2c = np.asarray(cameras.world_to_camera, np.float64)
    if w2c.shape != (n, 4, 4):
        raise DataError("cameras", f"expected a batch of {n} cameras, got world_to_camera "
                                   f"shape {list(w2c.shape)}")
    if (cameras.width, cameras.height) != (w, h):
        raise DataError("cameras", f"camera size {cameras.width}x{cameras.height} differs from "
                                   f"image size {w}x{h}")
    if not np.isfinite(w2c).all():
        raise DataError("cameras", "non-finite world_to_camera")
    if image_format not in ("png", "exr", "jpg"):
        raise DataError("image_format", f"must be png, exr or jpg, got {image_format!r}")
    if filenames is None:
        filenames = [f"images/frame_{i:05d}.{image_format}" for i in range(n)]
    filenames = [str(f) for f in filenames]
    if len(filenames) != n:
        raise DataError("filenames", f"expected {n} names, got {len(filenames)}")
    for f in filenames:
        norm = _norm_name(f)
        if Path(f).is_absolute() or norm.startswith(".."):
            raise DataError("filenames", f"{f!r} must be a relative path inside the dataset")
        if norm == "transforms.json":
            raise DataError("filenames", "an image cannot be called transforms.json")
    if len(set(map(_norm_name, filenames))) != n:
        raise DataError("filenames", "file names must be unique")

    def index_array(value, field):
        arr = np.asarray(value, np.int64).reshape(-1)
        if arr.size and (arr.min() < 0 or arr.max() >= n):
            raise DataError(field, f"indices must lie in [0, {n})")
        return np.unique(arr)

    split = None
    if train_indices is not None or test_indices is not None:
        train = None if train_indices is None else index_array(train_indices, "train_indices")
        test = None if test_indices is None else index_array(test_indices, "test_indices")
        train = np.setdiff1d(np.arange(n), test) if train is None else train
        test = np.setdiff1d(np.arange(n), train) if test is None else test
        split = (train, test)

    c2w = opencv_w2c_to_opengl_c2w(w2c)
    intr = np.stack([np.broadcast_to(np.asarray(getattr(cameras, k), np.float64), (n,))
                     for k in ("fx", "fy", "cx", "cy")], axis=1)
    shared = bool(np.all(intr == intr[:1]))
    meta: dict = {"camera_model": "PINHOLE", "w": int(w), "h": int(h)}
    if shared:
        meta.update(fl_x=float(intr[0, 0]), fl_y=float(intr[0, 1]), cx=float(intr[0, 2]),
                    cy=float(intr[0, 3]))
    frames = []
    for i in range(n):
        frame = {"file_path": filenames[i], "transform_matrix": c2w[i].tolist()}
        if not shared:
            frame.update(fl_x=float(intr[i, 0]), fl_y=float(intr[i, 1]), cx=float(intr[i, 2]),
                         cy=float(intr[i, 3]))
        frames.append(frame)
    meta["frames"] = frames
    if split is not None:
        meta["train_filenames"] = [filenames[i] for i in split[0]]
        meta["val_filenames"] = [filenames[i] for i in split[1]]
        meta["test_filenames"] = [filenames[i] for i in split[1]]

    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".tmp", dir=out_dir.parent))
    # mkdtemp makes an owner-only folder; the dataset is an ordinary folder once renamed.
    os.chmod(staging, 0o777 & ~current_umask())
    try:
        if points is not None:
            pts = np.asarray(points)
            cols = np.full(pts.shape, 0.5) if point_colors is None else point_colors
            save_points_ply(staging / "sparse_pc.ply", pts, cols)
            meta["ply_file_path"] = "sparse_pc.ply"
        for i in range(n):
            write_image(staging / filenames[i], images[i])
        (staging / "transforms.json").write_text(json.dumps(meta, indent=2), encoding="utf-8")
        if not out_dir.exists():
            os.replace(staging, out_dir)
        else:
            _merge_into(staging, out_dir)
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
    return out_dir / "transforms.json"


def _merge_into(staging: Path, out_dir: Path) -> None:
    """Move every staged file into ``out_dir``, transforms.json last."""
    files = sorted(p for p in staging.rglob("*") if p.is_file() and p.name != "transforms.json")
    for src in files + [staging / "transforms.json"]:
        dst = out_dir / src.relative_to(staging)
        dst.parent.mkdir(parents=True, exist_ok=True)
        os.replace(src, dst)
