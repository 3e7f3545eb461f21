"""Views, turntables and figures as ``data:`` URIs, so the page refers to no file."""

from __future__ import annotations

import base64
import io
from pathlib import Path

import numpy as np

from ...errors import DataError


def _load_thumb(path: Path, thumb_px: int) -> np.ndarray:
    """float32 [h, w, 3] in [0, 1], the image at ``path`` shrunk to fit thumb_px."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            im = im.convert("RGBA")
            flat = Image.new("RGBA", im.size, (255, 255, 255, 255))
            flat.alpha_composite(im)
            im = flat.convert("RGB")
            # enlarge tiny views (at most 4x) so they stay legible
            scale = min(thumb_px / max(im.size), 4.0)
            if scale < 1.0 or scale >= 1.25:
                size = (max(1, round(im.size[0] * scale)), max(1, round(im.size[1] * scale)))
                im = im.resize(size, Image.Resampling.LANCZOS)
            return np.asarray(im, np.float32) / 255.0
    except (OSError, ValueError) as e:
        raise DataError(path, f"cannot read image ({e})") from None


def data_uri(data: bytes, mime: str) -> str:
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"


def image_uri(image, *, fmt: str = "JPEG", quality: int = 88) -> str:
    """A float [H, W, 3] in [0, 1] (or uint8) image as a data URI (JPEG or PNG)."""
    from PIL import Image

    from ...viz import to_uint8

    buf = io.BytesIO()
    Image.fromarray(to_uint8(image)).save(buf, format=fmt, quality=quality, optimize=True)
    return data_uri(buf.getvalue(), "image/jpeg" if fmt == "JPEG" else "image/png")


def _grid_uri(paths: list[Path], thumb_px: int, max_views: int, ncols: int | None = None) -> str | None:
    from ...viz import image_grid

    if not paths:
        return None
    paths = _spread(paths, max_views)
    thumbs = [_load_thumb(p, thumb_px) for p in paths]
    return image_uri(image_grid(thumbs, ncols or len(thumbs), pad=2))


def _spread(items: list, k: int) -> list:
    """At most ``k`` items evenly spread over the list (first and last kept)."""
    if len(items) <= k:
        return list(items)
    idx = np.unique(np.round(np.linspace(0, len(items) - 1, k)).astype(int))
    return [items[i] for i in idx]


def _turntable_uri(path: Path, turntable_px: int, max_frames: int) -> str | None:
    """The turntable WebP inlined; re-encoded smaller when it is large."""
    from PIL import Image

    from ...viz import encode_webp, read_webp

    if not path.is_file():
        return None
    frames, durations = read_webp(path)
    seconds = float(durations.sum()) / 1000.0 or len(frames) / 12.0
    if frames.shape[1] <= turntable_px and frames.shape[2] <= turntable_px and len(frames) <= max_frames:
        return data_uri(path.read_bytes(), "image/webp")
    frames = frames[np.round(np.linspace(0, len(frames), min(len(frames), max_frames),
                                         endpoint=False)).astype(int)]
    scale = min(1.0, turntable_px / max(frames.shape[1:3]))
    size = (max(1, round(frames.shape[2] * scale)), max(1, round(frames.shape[1] * scale)))
    small = np.stack([np.asarray(Image.fromarray(f).resize(size, Image.Resampling.LANCZOS))
                      for f in frames])
    return data_uri(encode_webp(small, fps=len(small) / max(seconds, 1e-3)), "image/webp")


def _figure_uri(fig) -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return data_uri(buf.getvalue(), "image/png")
