"""Float views of 8-bit images that stay 8-bit in memory: converted where they are read."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .nerfstudio import as_float_images


class FloatViews:
    """float32 [N, H, W, 3] images in [0, 1], kept as ``stored`` (uint8, or float32 as is).

    A read-only array for ``len``, ``shape``, ``ndim``, ``dtype``, indexing, iteration and
    ``np.asarray``: what is read is converted then (:func:`as_float_images`, uint8 times
    1/255), so the host holds one byte a channel, and a view read is bit for bit the float
    image. :func:`stored_views` and :func:`device_float` do the same on a device.
    """

    def __init__(self, stored):
        self.stored = np.asarray(stored)

    shape = property(lambda self: self.stored.shape)
    ndim = property(lambda self: self.stored.ndim)
    dtype = property(lambda self: np.dtype(np.float32))

    def __len__(self) -> int:
        return len(self.stored)

    def __getitem__(self, index) -> np.ndarray:
        return as_float_images(self.stored[index])

    def __iter__(self):
        return (as_float_images(view) for view in self.stored)

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        out = as_float_images(self.stored)
        return out if dtype is None else out.astype(dtype, copy=False)

    def astype(self, dtype) -> np.ndarray:
        return np.asarray(self, dtype)

    def __repr__(self) -> str:
        return f"FloatViews({self.stored.dtype} {list(self.stored.shape)})"


def stored_views(images) -> np.ndarray:
    """The array ``images`` keeps: a :class:`FloatViews`' stored one, else ``images``."""
    return images.stored if isinstance(images, FloatViews) else images


def device_float(images):
    """float32 of ``images`` on their device: uint8 times 1/255 (as :func:`as_float_images`,
    bit for bit), float as it is."""
    if images.dtype == jnp.uint8:
        return images.astype(jnp.float32) * jnp.float32(1.0 / 255.0)
    return images
