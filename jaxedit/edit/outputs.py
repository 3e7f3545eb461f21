"""What an edit run measures of a scene state: image scores, multi-view consistency,
distance to the input."""

from __future__ import annotations

import functools

import jax.numpy as jnp
import numpy as np

from ..raster.render import HEADROOM, render_capacity


class Renderer:
    """Render single views over a fixed background, never truncated."""

    def __init__(self, background=(1.0, 1.0, 1.0)):
        self.background = jnp.asarray(background, jnp.float32)
        # largest buffer needed so far: smaller frames reuse its compiled program
        self.max_intersections: int | None = None

    def __call__(self, gaussians, camera):
        """RenderOutput of one camera."""
        from ..raster import render

        out = render(gaussians, camera, background=self.background,
                     max_intersections=self.max_intersections)
        used = render_capacity(int(np.max(np.asarray(out.num_intersections))) * HEADROOM)
        self.max_intersections = max(self.max_intersections or 0, used)
        return out

    def rgb(self, gaussians, camera) -> np.ndarray:
        return np.asarray(self(gaussians, camera).rgb, np.float32)

    def views(self, gaussians, cameras) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rgb [N,H,W,3], alpha [N,H,W], depth [N,H,W]) of a batched camera."""
        outs = [self(gaussians, cameras[i]) for i in range(len(cameras))]
        return (np.stack([np.asarray(o.rgb, np.float32) for o in outs]),
                np.stack([np.asarray(o.alpha, np.float32) for o in outs]),
                np.stack([np.asarray(o.depth, np.float32) for o in outs]))


def image_scores(renders: np.ndarray, targets: np.ndarray) -> dict:
    """Mean PSNR (dB) and SSIM (scikit-image) of renders vs targets, float [N, H, W, 3] in [0, 1]."""
    from skimage.metrics import structural_similarity

    psnrs, ssims = [], []
    for a, b in zip(np.clip(renders, 0, 1), np.clip(targets, 0, 1)):
        mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
        psnrs.append(-10.0 * np.log10(max(mse, 1e-10)))  # finite for identical images
        ssims.append(structural_similarity(b, a, channel_axis=-1, data_range=1.0,
                                           win_size=min(7, min(a.shape[:2]) // 2 * 2 - 1)))
    return {"psnr": float(np.mean(psnrs)), "ssim": float(np.mean(ssims))}


def reprojection_consistency(rgb: np.ndarray, alpha: np.ndarray, depth: np.ndarray, cameras,
                             *, min_alpha: float = 0.5) -> float:
    """PSNR (dB) of colours carried by rendered depth from view i to view i+1 (cyclically)
    where both see the same surface; NaN when no pixel is co-visible.

    Args:
      rgb: float [N, H, W, 3]; alpha, depth: float [N, H, W]; cameras: batched [N].
    """
    n, h, w = depth.shape
    if n < 2:
        return float("nan")
    ys, xs = np.mgrid[0:h, 0:w]
    pix = np.stack([xs + 0.5, ys + 0.5, np.ones_like(xs, dtype=np.float64)], -1).reshape(-1, 3)
    err, count = 0.0, 0
    w2c = np.asarray(cameras.world_to_camera, np.float64)
    k = np.asarray(cameras.intrinsics(), np.float64)
    for i in range(n):
        j = (i + 1) % n
        ok = alpha[i].reshape(-1) > min_alpha
        if not ok.any():
            continue
        rays = pix[ok] @ np.linalg.inv(k[i]).T
        cam_pts = rays * depth[i].reshape(-1)[ok, None]
        c2w = np.linalg.inv(w2c[i])
        world = cam_pts @ c2w[:3, :3].T + c2w[:3, 3]
        pj = world @ w2c[j][:3, :3].T + w2c[j][:3, 3]
        z = pj[:, 2]
        uv = pj @ k[j].T
        front = z > 1e-6
        u = np.floor(uv[:, 0] / np.where(front, z, 1)).astype(np.int64)
        v = np.floor(uv[:, 1] / np.where(front, z, 1)).astype(np.int64)
        inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        u, v, zi = u[inside], v[inside], z[inside]
        seen = (alpha[j][v, u] > min_alpha) & (np.abs(depth[j][v, u] - zi) < 0.05 * zi)
        if not seen.any():
            continue
        ci = rgb[i].reshape(-1, 3)[ok][inside][seen]
        cj = rgb[j][v[seen], u[seen]]
        err += float(np.sum((ci - cj) ** 2))
        count += ci.size
    if count == 0:
        return float("nan")
    mse = max(err / count, 1e-10)
    return float(-10.0 * np.log10(mse))


@functools.lru_cache(maxsize=1)
def bundled_lpips():
    """LPIPS-AlexNet with the package's weights, ``(a, b) [H, W, 3] -> float``, loaded once."""
    from ..io.weights import bundled_lpips_weights
    from ..lpips import lpips_distance

    return lpips_distance(bundled_lpips_weights())


def distance_to_input(renders: np.ndarray, reference: np.ndarray, *, lpips=None) -> dict:
    """Mean {"psnr_vs_input", "ssim_vs_input", "lpips_vs_input"} of ``renders`` vs the input's
    ``reference`` renders, float [N, H, W, 3] in [0, 1]; ValueError when the shapes differ.
    ``lpips``: ``(a, b) -> float`` (None: :func:`bundled_lpips`)."""
    if renders.shape != reference.shape:
        raise ValueError(f"renders {renders.shape} and reference {reference.shape} differ")
    lpips = bundled_lpips() if lpips is None else lpips
    sc = image_scores(renders, reference)
    lp = float(np.mean([lpips(a, b) for a, b in zip(renders, reference)]))
    return {"psnr_vs_input": sc["psnr"], "ssim_vs_input": sc["ssim"], "lpips_vs_input": lp}


def scene_metrics(ctx, gaussians, ratio: float, *, reference: tuple | None = None) -> dict:
    """Metrics of one scene state at the held-out views: vs the editor's targets at r = 1 and
    at ``ratio``, consistency, and with ``reference`` = (input renders [M, H, W, 3], input
    Gaussian count) the :func:`distance_to_input`."""
    rgb, alpha, depth = ctx.renderer.views(gaussians, ctx.data.test_cameras)
    out = {"ratio": float(ratio), "num_gaussians": int(gaussians.num_alive()),
           "multiview_consistency": reprojection_consistency(rgb, alpha, depth,
                                                             ctx.data.test_cameras)}
    if reference is not None:
        ref_rgb, ref_count = reference
        out.update(distance_to_input(rgb, ref_rgb), input_gaussians=int(ref_count),
                   gaussians_vs_input=out["num_gaussians"] / max(int(ref_count), 1))
    target = getattr(ctx.editor, "target", None)
    if target is None:
        out.update(psnr_vs_target=None, ssim_vs_target=None)
        return out
    originals = ctx.data.test_images
    full = np.stack([target(o, 1.0, ctx.prompt) for o in originals])
    sc = image_scores(rgb, full)
    out.update(psnr_vs_target=sc["psnr"], ssim_vs_target=sc["ssim"])
    part = np.stack([target(o, ratio, ctx.prompt) for o in originals])
    sc = image_scores(rgb, part)
    out.update(psnr_vs_subtask_target=sc["psnr"], ssim_vs_subtask_target=sc["ssim"])
    return out
