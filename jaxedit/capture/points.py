"""Starting points for a dataset without an SfM cloud: photo-consistent random points.

Uniform candidates in the box the cameras' frusta share (:func:`view_box`); the ones whose
colours agree best across the views that see them are kept (voxel colouring's test), and
with a uniform ``background`` those seen as background by any view are carved away (else
they train into background-coloured floaters).
"""

from __future__ import annotations

import jax
import numpy as np

from ..camera import Camera


def _project(points: np.ndarray, cameras: Camera):
    """(columns int [N, P], rows int [N, P], inside bool [N, P]) of points in every camera."""
    w2c = np.asarray(cameras.world_to_camera, np.float64).reshape(-1, 4, 4)
    n = len(w2c)
    fx, fy, cx, cy = (np.broadcast_to(np.asarray(getattr(cameras, k), np.float64), (n,))[:, None]
                      for k in ("fx", "fy", "cx", "cy"))
    p = np.einsum("nij,pj->npi", w2c[:, :3, :3], points) + w2c[:, None, :3, 3]
    z = np.maximum(p[..., 2], 1e-9)
    u, v = fx * p[..., 0] / z + cx, fy * p[..., 1] / z + cy
    inside = (p[..., 2] > 1e-6) & (u >= 0) & (u < cameras.width) & (v >= 0) & (v < cameras.height)
    cols = np.clip(np.floor(u), 0, cameras.width - 1).astype(np.int64)
    rows = np.clip(np.floor(v), 0, cameras.height - 1).astype(np.int64)
    return cols, rows, inside


def view_box(cameras: Camera, *, grid: int = 32, min_fraction: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """The box where the cameras' view frusta overlap: where a scene they all film must be.

    Bounds the points of a ``grid``^3 lattice seen by at least ``min_fraction`` of the
    best-seen point's camera count.

    Args:
      cameras: batched Camera [N].
    Returns:
      (lo float64 [3], hi float64 [3]) corners of the box.
    """
    w2c = np.asarray(cameras.world_to_camera, np.float64).reshape(-1, 4, 4)
    centres = -np.einsum("nji,nj->ni", w2c[:, :3, :3], w2c[:, :3, 3])
    mid = centres.mean(axis=0)
    spread = float(np.abs(centres - mid).max())
    half = 2.0 * spread if spread > 1e-9 else 1.0
    axis = mid[:, None] + np.linspace(-half, half, grid)[None, :]
    lattice = np.stack(np.meshgrid(axis[0], axis[1], axis[2], indexing="ij"), -1).reshape(-1, 3)
    counts = _project(lattice, cameras)[2].sum(axis=0)
    seen = lattice[counts >= max(1, min_fraction * counts.max())]
    if len(seen) == 0:  # no camera sees any lattice point: the cube itself
        return mid - half, mid + half
    cell = 2.0 * half / (grid - 1)
    return seen.min(axis=0) - cell / 2, seen.max(axis=0) + cell / 2


#: Largest per-channel difference from the background of a pixel that counts as background.
BACKGROUND_TOLERANCE = 0.02


def background_fraction(images, background) -> float:
    """Fraction of the border pixels within :data:`BACKGROUND_TOLERANCE` of ``background``."""
    images = np.asarray(images)
    border = np.concatenate([images[:, 0], images[:, -1], images[:, :, 0], images[:, :, -1]], 1)
    bg = np.asarray(background, np.float64)
    return float(np.mean(np.abs(border - bg).max(-1) <= BACKGROUND_TOLERANCE))


def _score(points: np.ndarray, images: np.ndarray, cameras: Camera, background):
    """(variance float64 [P], mean colour float64 [P, 3], views that see each point int [P]).

    The variance is inf (ranked last) for points seen by < 2 views or carved.
    """
    cols, rows, inside = _project(points, cameras)
    views = np.arange(len(images))[:, None]
    seen = images[views, rows, cols] * inside[..., None]          # [N, P, 3]
    count = inside.sum(axis=0)
    mean = seen.sum(axis=0) / np.maximum(count, 1)[:, None]
    var = ((seen - mean) ** 2 * inside[..., None]).sum(axis=0).sum(-1) / np.maximum(count, 1)
    var = np.where(count >= 2, var, np.inf)
    if background is not None:
        bg = np.asarray(background, np.float64)
        carved = ((np.abs(seen - bg).max(-1) <= BACKGROUND_TOLERANCE) & inside).any(axis=0)
        var = np.where(carved, np.inf, var)
    return var, mean, count


def random_points(images, cameras: Camera, num_points: int, key: jax.Array, *,
                  oversample: int = 4, background=None,
                  max_rounds: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Photo-consistent random starting points (see the module docstring).

    Rounds of ``num_points * oversample`` candidates are drawn until that many are testable
    (or ``max_rounds``); the ``num_points`` lowest-variance ones are kept.

    Args:
      images: float [N, H, W, 3] training images; cameras: batched Camera [N] (same N).
      num_points: points returned.
      key: PRNG key of the candidate draws.
      oversample: candidates drawn per point kept (1: plain uniform points, random colours).
      background: RGB of a uniform background around the scene (carves), or None.
      max_rounds: most rounds of candidates drawn.
    Returns:
      (points float32 [num_points, 3], colours float32 [num_points, 3] in [0, 1]).
    """
    lo, hi = view_box(cameras)
    k_pos, k_col = jax.random.split(key)
    total = num_points * max(1, int(oversample))

    def draw(k):
        pts = lo + np.asarray(jax.random.uniform(jax.random.fold_in(k_pos, k), (total, 3)),
                              np.float64) * (hi - lo)
        rgb = np.asarray(jax.random.uniform(jax.random.fold_in(k_col, k), (total, 3)), np.float64)
        return pts, rgb

    if oversample <= 1:
        points, colors = draw(0)
        return points.astype(np.float32), colors.astype(np.float32)
    images = np.asarray(images, np.float64)
    rounds = []
    for k in range(max(1, int(max_rounds))):
        pts, rgb = draw(k)
        rounds.append((pts, rgb, *_score(pts, images, cameras, background)))
        if sum(int(np.isfinite(r[2]).sum()) for r in rounds) >= total:
            break
    points, colors, var, mean, count = (np.concatenate(parts) for parts in zip(*rounds))
    keep = np.argsort(var, kind="stable")[:num_points]
    colors = np.where(count[keep, None] >= 1, mean[keep], colors[keep])
    return points[keep].astype(np.float32), colors.astype(np.float32)
