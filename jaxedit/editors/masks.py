"""Relevance masks from difference maps, shared by the Editor protocol, the simulated
editor and :meth:`.jax_ip2p.JaxIP2PEditor.relevance` without one importing another; and
the size check of a mask file (:func:`check_mask_file`).
"""

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
    """A difference map as a relevance mask.

    Args:
      difference: float [H, W] or [B, H, W], >= 0 (e.g. |eps(e) - eps(E(""))|).
      sigma: blur in pixels; threshold: on the map normalised to [0, 1] per view.
    Returns:
      float32 of the input's shape, 1 where relevant, else 0.
    """
    d = jnp.asarray(difference, jnp.float32)
    single = d.ndim == 2
    d = d[None] if single else d
    peak = jnp.max(d, axis=(1, 2), keepdims=True)
    # blur works on [H, W, C]: the views ride along as channels.
    d = jnp.moveaxis(blur(jnp.moveaxis(d / jnp.maximum(peak, 1e-12), 0, -1), sigma), -1, 0)
    peak = jnp.max(d, axis=(1, 2), keepdims=True)
    m = ((d >= threshold * peak) & (peak > 1e-6)).astype(jnp.float32)
    return m[0] if single else m


def check_mask_file(path, hw: tuple[int, int]) -> tuple[int, int]:
    """The (height, width) of a mask file for a view of size ``hw``, read from its
    header: the view's size or a whole multiple, and decodable within free memory.

    Raises:
      DataError naming ``path``.
    """
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
