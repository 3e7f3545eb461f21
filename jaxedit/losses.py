"""Image losses in JAX (jit-, grad- and vmap-able): L1, SSIM, D-SSIM and the 3DGS loss, on
images float [..., H, W, C] in [0, data_range]. SSIM is scikit-image's
``structural_similarity(gaussian_weights=True, use_sample_covariance=False)``."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np


@functools.lru_cache(maxsize=16)
def gaussian_window(window: int = 11, sigma: float = 1.5) -> np.ndarray:
    """float32 [window] normalised 1-D Gaussian taps (odd ``window``)."""
    if window < 1 or window % 2 == 0:
        raise ValueError(f"SSIM window must be a positive odd number, got {window}")
    r = (window - 1) // 2
    x = np.arange(-r, r + 1, dtype=np.float64)
    w = np.exp(-0.5 * (x / sigma) ** 2)
    return (w / w.sum()).astype(np.float32)


@functools.lru_cache(maxsize=64)
def _band(rows: int, taps: tuple[float, ...]) -> np.ndarray:
    """float32 [rows, rows + k - 1]: row i holds the taps at columns i .. i + k - 1."""
    k = len(taps)
    m = np.zeros((rows, rows + k - 1), np.float32)
    for i in range(rows):
        m[i, i:i + k] = taps
    return m


def _filter_axis(x, taps: tuple[float, ...], axis: int, block: int = 64):
    """Correlate ``x`` with ``taps`` along ``axis``, 'valid' part (n - k + 1 outputs), as
    banded matrix products over blocks of ``block`` outputs."""
    k = len(taps)
    x = jnp.moveaxis(x, axis, 0)
    n = x.shape[0]
    n_out = n - k + 1
    b = min(n_out, block)
    nb = -(-n_out // b)
    total = nb * b + k - 1
    if total > n:  # zero rows only feed outputs that are cut off below
        x = jnp.pad(x, [(0, total - n)] + [(0, 0)] * (x.ndim - 1))
    if nb == 1:
        windows = x[None]
    else:
        windows = x[np.arange(nb)[:, None] * b + np.arange(b + k - 1)[None, :]]
    band = jnp.asarray(_band(b, taps), x.dtype)
    # HIGHEST: TF32 (a GPU's DEFAULT) makes E[x^2] - E[x]^2 noise next to C2 in flat areas.
    out = jnp.tensordot(band, windows, axes=[[1], [1]],
                        precision=jax.lax.Precision.HIGHEST)  # [b, nb, ...]
    out = jnp.moveaxis(out, 0, 1).reshape((nb * b,) + x.shape[1:])[:n_out]
    return jnp.moveaxis(out, 0, axis)


def _filter_valid(x, taps: np.ndarray):
    """Separable filter of x [..., H, W, C] over H and W, 'valid' part: [..., H-2r, W-2r, C]."""
    t = tuple(float(v) for v in taps)
    return _filter_axis(_filter_axis(x, t, x.ndim - 3), t, x.ndim - 2)


def ssim_map(a, b, *, window: int = 11, sigma: float = 1.5, data_range: float = 1.0):
    """Per-pixel SSIM on the valid region: float [..., H - window + 1, W - window + 1, C]."""
    a = jnp.asarray(a)
    b = jnp.asarray(b)
    if a.shape != b.shape:
        raise ValueError(f"SSIM needs images of one shape, got {a.shape} and {b.shape}")
    if a.ndim < 3 or min(a.shape[-3], a.shape[-2]) < window:
        raise ValueError(f"SSIM needs images [..., H, W, C] with H, W >= {window}, got {a.shape}")
    taps = gaussian_window(window, sigma)
    stats = _filter_valid(jnp.stack([a, b, a * a, b * b, a * b]), taps)
    mu_a, mu_b, e_aa, e_bb, e_ab = stats
    var_a = e_aa - mu_a * mu_a
    var_b = e_bb - mu_b * mu_b
    cov = e_ab - mu_a * mu_b
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    num = (2 * mu_a * mu_b + c1) * (2 * cov + c2)
    den = (mu_a * mu_a + mu_b * mu_b + c1) * (var_a + var_b + c2)
    return num / den


_STATIC = ("window", "sigma", "data_range")


@functools.partial(jax.jit, static_argnames=_STATIC)
def ssim(a, b, *, window: int = 11, sigma: float = 1.5, data_range: float = 1.0):
    """Mean SSIM of images [..., H, W, C] -> float [...], scikit-image's to float32 rounding."""
    return jnp.mean(ssim_map(a, b, window=window, sigma=sigma, data_range=data_range),
                    axis=(-3, -2, -1))


def dssim(a, b, *, window: int = 11, sigma: float = 1.5, data_range: float = 1.0):
    """Structural dissimilarity ``1 - ssim(a, b)`` (3DGS convention, not halved): float [...]."""
    return 1.0 - ssim(a, b, window=window, sigma=sigma, data_range=data_range)


def l1(a, b):
    """Mean absolute error over every element: float scalar."""
    return jnp.mean(jnp.abs(jnp.asarray(a) - jnp.asarray(b)))


def mse(a, b):
    """Mean squared error over every element: float scalar."""
    return jnp.mean(jnp.square(jnp.asarray(a) - jnp.asarray(b)))


@functools.partial(jax.jit, static_argnames=_STATIC)
def photometric_loss(render, target, lambda_dssim: float = 0.2, *, weight=None,
                     window: int = 11, sigma: float = 1.5, data_range: float = 1.0):
    """The 3DGS / Splatfacto training loss ``(1 - l) L1 + l (1 - SSIM)``, a float scalar.

    Args:
      render, target: float [..., H, W, 3] in [0, 1]; batches are averaged.
      lambda_dssim: l, the D-SSIM weight; may be traced.
      weight: float [..., H, W] or None: each term's pixel weights (0 for all-zero weights).
      window, sigma, data_range: SSIM settings (static).
    """
    if weight is None:
        d = dssim(render, target, window=window, sigma=sigma, data_range=data_range)
        return (1.0 - lambda_dssim) * l1(render, target) + lambda_dssim * jnp.mean(d)
    w = jnp.asarray(weight, jnp.float32)
    r = window // 2
    w_valid = w[..., r:w.shape[-2] - r, r:w.shape[-1] - r]
    err = jnp.mean(jnp.abs(jnp.asarray(render) - jnp.asarray(target)), axis=-1)
    d = 1.0 - jnp.mean(ssim_map(render, target, window=window, sigma=sigma,
                                data_range=data_range), axis=-1)

    def mean(x, v):
        return jnp.sum(x * v) / jnp.maximum(jnp.sum(v), 1e-12)

    return (1.0 - lambda_dssim) * mean(err, w) + lambda_dssim * mean(d, w_valid)
