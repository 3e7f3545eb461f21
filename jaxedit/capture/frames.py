"""Input frames of a capture: a checked folder of photos, or the sharpest frame of each
window of a video (decoded with ``imageio-ffmpeg``'s ffmpeg)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..io.images import SWAPPING_ORIENTATIONS, photo_header, read_image

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff")
MIN_IMAGES = 3


def list_images(folder: str | os.PathLike) -> list[Path]:
    """The image files (by suffix) directly inside ``folder``, sorted by name."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(folder, "image folder not found" if not folder.exists() else "not a folder")
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def check_images(paths: list[Path], where: str | os.PathLike) -> tuple[int, int]:
    """The images' common upright (width, height), EXIF orientation applied; DataError for
    fewer than :data:`MIN_IMAGES`, an unreadable image or differing sizes."""
    if len(paths) < MIN_IMAGES:
        raise DataError(where, f"found {len(paths)} image(s) ({', '.join(IMAGE_SUFFIXES)}); "
                               f"structure from motion needs at least {MIN_IMAGES}")
    sizes: dict[tuple[int, int], Path] = {}
    for path in paths:
        read_image(path)  # decodable
        h, w, orientation, _ = photo_header(path)
        if orientation in SWAPPING_ORIENTATIONS:
            h, w = w, h
        sizes.setdefault((w, h), path)
    if len(sizes) > 1:
        listed = ", ".join(f"{w}x{h} ({p.name})" for (w, h), p in sorted(sizes.items())[:3])
        raise DataError(where, f"images have {len(sizes)} different sizes ({listed}); "
                               f"resize them to one size first")
    return next(iter(sizes))


def blur_score(image) -> float:
    """Sharpness of an image float [H, W, 3] (or [H, W]): variance of its Laplacian (higher = sharper)."""
    from skimage.color import rgb2gray
    from skimage.filters import laplace

    image = np.asarray(image, np.float64)
    gray = rgb2gray(image) if image.ndim == 3 else image
    return float(laplace(gray).var())


def windows(num_frames: int, target: int) -> np.ndarray:
    """int [num_frames]: the window index of each frame, ``min(target, num_frames)`` equal windows."""
    count = max(1, min(int(target), int(num_frames)))
    return (np.arange(num_frames) * count) // max(num_frames, 1)


def _last_line(error: Exception) -> str:
    """ffmpeg's errors are many lines; the last one says what went wrong."""
    text = str(error).strip()
    return text.splitlines()[-1] if text else type(error).__name__


def sample_video(path: str | os.PathLike, target: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The sharpest frame of each of ``target`` windows of a video, decoded one at a time.

    Args:
      path: any video that ffmpeg reads.
      target: number of frames wanted (fewer when the video is shorter).
    Returns:
      (frames uint8 [M, H, W, 3], source frame indices int [M], blur scores float [M]).
    """
    import imageio_ffmpeg

    path = Path(path)
    if not path.is_file():
        raise DataError(path, "video file not found" if not path.exists() else "not a file")
    if target < MIN_IMAGES:
        raise DataError("num_frames", f"must be >= {MIN_IMAGES}, got {target}")
    try:
        num_frames, _ = imageio_ffmpeg.count_frames_and_secs(str(path))
        reader = imageio_ffmpeg.read_frames(str(path))
        meta = next(reader)
    except (RuntimeError, OSError, StopIteration) as e:
        raise DataError(path, f"cannot read video ({_last_line(e)})") from None
    width, height = meta["size"]
    window_of = windows(num_frames, target)
    best: dict[int, tuple[float, int, np.ndarray]] = {}
    try:
        for index, raw in enumerate(reader):
            frame = np.frombuffer(raw, np.uint8).reshape(height, width, 3)
            # ffmpeg's frame count can be short: extras join the last window
            window = int(window_of[min(index, len(window_of) - 1)]) if len(window_of) else 0
            score = blur_score(frame.astype(np.float32) / 255.0)
            if window not in best or score > best[window][0]:
                best[window] = (score, index, frame.copy())
    except RuntimeError as e:
        raise DataError(path, f"cannot decode video ({_last_line(e)})") from None
    finally:
        reader.close()
    if len(best) < MIN_IMAGES:
        raise DataError(path, f"video has {len(best)} frame(s); structure from motion needs at "
                              f"least {MIN_IMAGES}")
    keys = sorted(best)
    return (np.stack([best[k][2] for k in keys]), np.array([best[k][1] for k in keys], np.int64),
            np.array([best[k][0] for k in keys]))
