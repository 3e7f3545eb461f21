"""Held-out evaluation of trained Gaussians."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from ..camera import Camera
from ..gaussians import Gaussians
from ..metrics import psnr, ssim_skimage
from ..raster import render


def render_views(gaussians: Gaussians, cameras: Camera, *, background=(1.0, 1.0, 1.0),
                 sh_degree: int | None = None) -> np.ndarray:
    """float32 [N, H, W, 3] renders of a camera batch (outside jit, one view at a time)."""
    out = []
    bg = jnp.asarray(background, jnp.float32)
    for i in range(len(cameras)):
        r = render(gaussians, cameras[i], background=bg, sh_degree=sh_degree)
        out.append(np.asarray(jnp.clip(r.rgb, 0.0, 1.0)))
    return np.stack(out) if out else np.zeros((0, cameras.height, cameras.width, 3), np.float32)


def evaluate(gaussians: Gaussians, images, cameras: Camera, *, background=(1.0, 1.0, 1.0),
             sh_degree: int | None = None) -> dict:
    """Held-out quality: mean PSNR and SSIM (scikit-image) over the views, plus per view.

    Returns:
      dict(psnr, ssim, psnr_per_view, ssim_per_view, renders float32 [N, H, W, 3]).
    """
    renders = render_views(gaussians, cameras, background=background, sh_degree=sh_degree)
    images = np.asarray(images, np.float32)
    p = [float(psnr(r, t)) for r, t in zip(renders, images)]
    s = [float(ssim_skimage(r, t)) for r, t in zip(renders, images)]
    return dict(psnr=float(np.mean(p)) if p else math.nan,
                ssim=float(np.mean(s)) if s else math.nan,
                psnr_per_view=p, ssim_per_view=s, renders=renders)
