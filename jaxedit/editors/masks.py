"""Relevance masks from difference maps, shared by the editors, and the mask file check."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import DataError

#: Bytes a decoded pixel channel takes while a mask is read (float32, decoded and as RGB).
_DECODED_BYTES = 4 * 2


def _gaussian_kernel(sigma: float) -> jnp.ndarray:
    radius = max(1, int(math.ceil(3.0 * sigma)))
    x = np.arange(-radius, radius + 1, dtype=np.float32)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    return jnp.asarray(k / k.sum())


def blur(x, sigma: float):
    """Separable Gaussian blur of float [H, W] or [H, W, C] with edge padding."""
    if sigma <= 0:
        return x
    k = _gaussian_kernel(sigma)
    r = (k.shape[0] - 1) // 2
    squeeze = x.ndim == 2
    if squeeze:
        x = x[..., None]

    def conv_axis(img, axis):
        pad = [(0, 0)] * img.ndim
        pad[axis] = (r, r)
        p = jnp.pad(img, pad, mode="edge")
        n = img.shape[axis]
        out = 0.0
        for i in range(k.shape[0]):
            out = out + k[i] * jax.lax.slice_in_dim(p, i, i + n, axis=axis)
        return out

    y = conv_axis(conv_axis(x, 0), 1)
    return y[..., 0] if squeeze else y


def relevance_mask(difference, *, sigma: float = 1.5, threshold: float = 0.3) -> jax.Array:
    """Difference map float [H, W] or [B, H, W], >= 0 -> float32 mask of its shape: 1 where the
    map blurred by ``sigma`` pixels is >= ``threshold`` x its per-view peak, else 0."""
    d = jnp.asarray(difference, jnp.float32)
    single = d.ndim == 2
    d = d[None] if single else d
    peak = jnp.max(d, axis=(1, 2), keepdims=True)
    d = jnp.moveaxis(blur(jnp.moveaxis(d / jnp.maximum(peak, 1e-12), 0, -1), sigma), -1, 0)
    peak = jnp.max(d, axis=(1, 2), keepdims=True)
    m = ((d >= threshold * peak) & (peak > 1e-6)).astype(jnp.float32)
    return m[0] if single else m


def check_mask_file(path, hw: tuple[int, int]) -> tuple[int, int]:
    """(height, width) of a mask file from its header for a view of size ``hw``; DataError
    naming ``path`` unless it is ``hw`` or a whole multiple and decodable in free memory."""
    from ..io.images import image_header
    from ..memory import require_memory

    h, w, channels = image_header(path)
    (H, W) = hw
    k = h // H if H else 0
    if (h, w) != (H, W) and not (k > 1 and (h, w) == (k * H, k * W)):
        raise DataError(path, f"mask is {w}x{h} px, its view {W}x{H} (or a whole multiple of it)")
    require_memory(path, float(h) * w * max(channels, 3) * _DECODED_BYTES,
                   f"decoding a {w}x{h} px mask")
    return h, w
