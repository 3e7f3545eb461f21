"""Image quality metrics for reporting (NumPy / scikit-image, float64).

``psnr`` and ``ssim_skimage`` are the numbers that go into ``metrics.json``;
training uses the JAX versions in :mod:`jaxedit.losses`. Perceptual metrics
(LPIPS, CLIP) live in their own modules and may build on these.

Every function takes images float [H, W, C] in [0, data_range] and returns a
float, or a batch [N, H, W, C] and returns float [N] (one value per image;
average them for a dataset score, as the 3DGS papers do).
"""

from __future__ import annotations

import numpy as np

from .errors import DataError


def _pair(a, b, name: str) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    if a.shape != b.shape:
        raise DataError(name, f"images differ in shape: {list(a.shape)} vs {list(b.shape)}")
    if a.ndim not in (3, 4):
        raise DataError(name, f"expected [H, W, C] or [N, H, W, C], got {list(a.shape)}")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise DataError(name, "images contain NaN or inf")
    return a, b


def psnr(a, b, *, data_range: float = 1.0):
    """Peak signal-to-noise ratio in dB, ``10 log10(R^2 / MSE)``; inf for identical images."""
    a, b = _pair(a, b, "psnr")
    mse = np.mean((a - b) ** 2, axis=(-3, -2, -1))
    with np.errstate(divide="ignore"):
        out = 10.0 * np.log10(data_range ** 2 / mse)
    return float(out) if out.ndim == 0 else out


def ssim_skimage(a, b, *, data_range: float = 1.0):
    """scikit-image's Gaussian-weighted SSIM (sigma 1.5, population covariance), the
    reference for :func:`jaxedit.losses.ssim`."""
    from skimage.metrics import structural_similarity

    a, b = _pair(a, b, "ssim")

    def one(x, y):
        return float(structural_similarity(x, y, gaussian_weights=True, sigma=1.5,
                                           use_sample_covariance=False, data_range=data_range,
                                           channel_axis=-1))

    if a.ndim == 3:
        return one(a, b)
    return np.array([one(x, y) for x, y in zip(a, b)])


def image_metrics(renders, targets, *, data_range: float = 1.0) -> dict:
    """Dataset scores: mean PSNR (infinite values capped at 100 dB) and mean SSIM over a
    batch [N, H, W, C] (or one image)."""
    p = np.minimum(np.atleast_1d(psnr(renders, targets, data_range=data_range)), 100.0)
    s = np.atleast_1d(ssim_skimage(renders, targets, data_range=data_range))
    return {"psnr": float(np.mean(p)), "ssim": float(np.mean(s))}
