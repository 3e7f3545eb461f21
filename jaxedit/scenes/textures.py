"""Mip-mapped textures for the built-in scenes from pictures shipped inside scikit-image
(no download), sampled trilinearly by footprint so minified textures don't alias."""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import numpy as np

from ..errors import DataError

# Images inside the scikit-image wheel (checked offline); anything needing a download is excluded.
SHIPPED_IMAGES = ("astronaut", "brick", "camera", "chelsea", "coffee", "grass", "gravel",
                  "rocket", "hubble_deep_field", "logo", "retina", "page", "text", "coins", "moon",
                  "horse", "cell")


@dataclasses.dataclass(frozen=True)
class Texture:
    """How a surface takes its albedo from a scikit-image picture.

    Attributes:
      image: name of a ``skimage.data`` image (see :data:`SHIPPED_IMAGES`).
      crop: (row0, row1, col0, col1) region of the picture, or None for all of it.
      tint: RGB multiplier (grey pictures become tinted; colour ones are scaled).
      tile: world units per repetition on boxes and planes; None stretches the crop.
      repeat: (u, v) repetitions over the surface parameterisation of spheres.
      wrap: "repeat", "mirror" (seamless for any picture) or "clamp".
      max_size: longest side in pixels the picture is downsampled to.
    """

    image: str
    crop: tuple[int, int, int, int] | None = None
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    tile: float | None = None
    repeat: tuple[float, float] = (1.0, 1.0)
    wrap: str = "mirror"
    max_size: int = 512

    def __post_init__(self):
        if self.wrap not in ("repeat", "mirror", "clamp"):
            raise DataError("Texture.wrap", f"unknown wrap mode {self.wrap!r} (repeat, mirror, clamp)")


def _load_image(name: str) -> np.ndarray:
    """float32 [H, W, 3] in [0, 1] from a picture shipped with scikit-image."""
    import skimage.data

    if name not in SHIPPED_IMAGES or not hasattr(skimage.data, name):
        raise DataError("Texture.image", f"{name!r} is not a picture shipped inside scikit-image "
                        f"(use one of {', '.join(SHIPPED_IMAGES[:8])}, ...)")
    folder = Path(skimage.data.__file__).parent
    if not any(folder.glob(f"{name}.*")):
        raise DataError("Texture.image", f"{name!r} is not stored inside scikit-image "
                        "(it would need a download)")
    img = np.asarray(getattr(skimage.data, name)())
    if img.dtype == bool:
        img = img.astype(np.float32)
    elif img.dtype.kind in "ui":
        img = img.astype(np.float32) / np.iinfo(img.dtype).max
    else:
        img = img.astype(np.float32)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    if img.shape[-1] == 4:  # composite RGBA pictures (logo) over white
        img = img[..., :3] * img[..., 3:] + (1.0 - img[..., 3:])
    return np.clip(img[..., :3], 0.0, 1.0)


def _downsample2(img: np.ndarray) -> np.ndarray:
    """2x2 box filter (odd sizes: the last row/column is repeated)."""
    h, w = img.shape[:2]
    if h % 2:
        img = np.concatenate([img, img[-1:]], axis=0)
    if w % 2:
        img = np.concatenate([img, img[:, -1:]], axis=1)
    return 0.25 * (img[0::2, 0::2] + img[1::2, 0::2] + img[0::2, 1::2] + img[1::2, 1::2])


@functools.lru_cache(maxsize=64)
def pyramid(tex: Texture) -> tuple[np.ndarray, ...]:
    """The mip pyramid, float32 [H_k, W_k, 3] levels halving down to 1 pixel (cached, read-only)."""
    img = _load_image(tex.image)
    if tex.crop is not None:
        r0, r1, c0, c1 = tex.crop
        if not (0 <= r0 < r1 <= img.shape[0] and 0 <= c0 < c1 <= img.shape[1]):
            raise DataError("Texture.crop", f"{tex.crop} is outside the {img.shape[0]}x"
                            f"{img.shape[1]} picture {tex.image!r}")
        img = img[r0:r1, c0:c1]
    while max(img.shape[:2]) > tex.max_size:
        img = _downsample2(img)
    img = (img * np.asarray(tex.tint, np.float32)).astype(np.float32)
    levels = [img]
    while max(levels[-1].shape[:2]) > 1:
        levels.append(_downsample2(levels[-1]).astype(np.float32))
    for level in levels:
        level.setflags(write=False)
    return tuple(levels)


def mean_color(tex: Texture) -> np.ndarray:
    """float [3], the average albedo of a texture (its coarsest mip level)."""
    return pyramid(tex)[-1].reshape(3).astype(np.float64)


def _wrap(i: np.ndarray, n: int, mode: str) -> np.ndarray:
    if mode == "repeat":
        return np.mod(i, n)
    if mode == "mirror":
        m = np.mod(i, 2 * n)
        return np.where(m < n, m, 2 * n - 1 - m)
    return np.clip(i, 0, n - 1)


def _bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray, mode: str) -> np.ndarray:
    """Bilinear lookup of float [H, W, 3] at texture coordinates u, v (in repetitions, [0, 1) once)."""
    h, w = img.shape[:2]
    x = u * w - 0.5  # texel centres at integer + 0.5 in texel units
    y = v * h - 0.5
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = (x - x0)[:, None].astype(np.float32)
    fy = (y - y0)[:, None].astype(np.float32)
    x0 = x0.astype(np.int64)
    y0 = y0.astype(np.int64)
    xa, xb = _wrap(x0, w, mode), _wrap(x0 + 1, w, mode)
    ya, yb = _wrap(y0, h, mode), _wrap(y0 + 1, h, mode)
    top = img[ya, xa] * (1 - fx) + img[ya, xb] * fx
    bottom = img[yb, xa] * (1 - fx) + img[yb, xb] * fx
    return top * (1 - fy) + bottom * fy


def sample(tex: Texture, uv: np.ndarray, footprint: np.ndarray | None = None) -> np.ndarray:
    """float32 [P, 3] albedo at ``uv`` float [P, 2] (1.0 = one repetition; v down), trilinear
    by ``footprint`` float [P] in uv units (None: the sharpest level)."""
    levels = pyramid(tex)
    uv = np.asarray(uv, np.float64)
    if footprint is None:
        return _bilinear(levels[0], uv[:, 0], uv[:, 1], tex.wrap)
    size0 = max(levels[0].shape[:2])
    lod = np.log2(np.maximum(np.asarray(footprint, np.float64) * size0, 1e-12))
    lod = np.clip(lod, 0.0, len(levels) - 1.0)
    lo = np.floor(lod).astype(np.int64)
    frac = (lod - lo).astype(np.float32)[:, None]
    hi = np.minimum(lo + 1, len(levels) - 1)
    out = np.zeros((uv.shape[0], 3), np.float32)
    for k in np.unique(np.concatenate([lo, hi])):
        sel_lo = lo == k
        if sel_lo.any():
            out[sel_lo] += (1 - frac[sel_lo]) * _bilinear(levels[k], uv[sel_lo, 0], uv[sel_lo, 1], tex.wrap)
        sel_hi = hi == k
        if sel_hi.any():
            out[sel_hi] += frac[sel_hi] * _bilinear(levels[k], uv[sel_hi, 0], uv[sel_hi, 1], tex.wrap)
    return out
