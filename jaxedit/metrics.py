"""Image quality metrics for reporting (NumPy / scikit-image, float64), scores against several
valid outcomes, and confidence intervals. Images: float [H, W, C] in [0, data_range] -> float,
or [N, H, W, C] -> float [N]."""

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
    """scikit-image's Gaussian-weighted SSIM, the reference of :func:`jaxedit.losses.ssim`."""
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
    """Dataset scores of a batch [N, H, W, C] (or one image): mean PSNR, each
    capped at 100 (an identical pair's inf), and mean SSIM."""
    p = np.minimum(np.atleast_1d(psnr(renders, targets, data_range=data_range)), 100.0)
    s = np.atleast_1d(ssim_skimage(renders, targets, data_range=data_range))
    return {"psnr": float(np.mean(p)), "ssim": float(np.mean(s))}


def mode_mixture(renders, mode_targets) -> np.ndarray:
    """Weights w float [K] on the simplex minimising || renders - sum_k w_k T_k ||^2 exactly
    (small K), renders float [N, H, W, C] (or [H, W, C]), mode_targets [K, N, H, W, C]."""
    from itertools import combinations

    r = np.asarray(renders, np.float64)
    t = np.asarray(mode_targets, np.float64)
    if t.ndim != r.ndim + 1 or t.shape[1:] != r.shape:
        raise DataError("mode_targets", f"expected [K, *{list(r.shape)}], got {list(t.shape)}")
    k = t.shape[0]
    flat, y = t.reshape(k, -1), r.reshape(-1)
    best, best_err = None, np.inf
    for size in range(1, k + 1):
        for face in combinations(range(k), size):
            last, others = face[-1], list(face[:-1])
            w = np.zeros(k)
            if others:  # y - T_last = sum_{j in others} w_j (T_j - T_last)
                a = (flat[others] - flat[last]).T
                w[others] = np.linalg.lstsq(a, y - flat[last], rcond=None)[0]
            w[last] = 1.0 - w.sum()
            if w.min() < -1e-9:
                continue  # the optimum of this face lies outside the simplex
            err = float(np.sum((w @ flat - y) ** 2))
            if err < best_err - 1e-12:
                best, best_err = np.clip(w, 0.0, 1.0), err
    return best


def mode_scores(renders, mode_targets, *, data_range: float = 1.0) -> dict:
    """Scores of renders [N, H, W, C] against K valid outcomes [K, N, H, W, C]: {"psnr_best",
    "ssim_best": best mode's mean; "mode": the best-PSNR mode; "psnr_per_mode",
    "ssim_per_mode": [K]; "mode_weights": :func:`mode_mixture`; "mode_mixing": 1 - max_k w_k
    scaled to [0, 1] (0: one mode)}."""
    t = np.asarray(mode_targets)
    per = [image_metrics(renders, t[k], data_range=data_range) for k in range(t.shape[0])]
    psnrs = [p["psnr"] for p in per]
    ssims = [p["ssim"] for p in per]
    w = mode_mixture(renders, t)
    k = len(per)
    mixing = 0.0 if k == 1 else float((1.0 - w.max()) * k / (k - 1))
    return {"psnr_best": max(psnrs), "ssim_best": max(ssims), "mode": int(np.argmax(psnrs)),
            "psnr_per_mode": psnrs, "ssim_per_mode": ssims,
            "mode_weights": [float(x) for x in w], "mode_mixing": mixing}


def mean_ci(values, *, level: float = 0.95) -> dict:
    """Mean and Student-t interval of independent samples: {"mean", "ci" (half-width; None for
    n = 1), "low", "high", "n"}; non-finite values raise."""
    from scipy.stats import t as student_t

    x = np.asarray(values, np.float64).reshape(-1)
    if x.size == 0 or not np.isfinite(x).all():
        raise DataError("mean_ci", f"need finite samples, got {x.tolist()}")
    mean = float(x.mean())
    if x.size < 2:
        return {"mean": mean, "ci": None, "low": None, "high": None, "n": 1}
    half = float(student_t.ppf(0.5 + level / 2, x.size - 1) * x.std(ddof=1) / np.sqrt(x.size))
    return {"mean": mean, "ci": half, "low": mean - half, "high": mean + half, "n": int(x.size)}


def percentile_interval(samples, *, level: float = 0.95) -> list[float]:
    """The central ``level`` percentile interval [low, high] of a bootstrap's samples
    (a 1-D sequence of the statistic, one per resample)."""
    low, high = np.quantile(np.asarray(samples, np.float64), [(1 - level) / 2, (1 + level) / 2])
    return [float(low), float(high)]


def paired_differences(a, b, *, level: float = 0.95) -> dict:
    """:func:`mean_ci` of a_i - b_i for paired samples (same seed / instruction)."""
    a = np.asarray(a, np.float64).reshape(-1)
    b = np.asarray(b, np.float64).reshape(-1)
    if a.shape != b.shape:
        raise DataError("paired_differences", f"{a.size} vs {b.size} samples: not paired")
    return mean_ci(a - b, level=level)
