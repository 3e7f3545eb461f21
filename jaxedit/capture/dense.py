"""A dense start on the surfaces that a sparse triangulated cloud marks.

Each training view interpolates a depth map from the triangulated points it sees (the
nearest layer of them: points hidden behind nearer ones are dropped), draws pixels and
back-projects them at the interpolated depth with the pixel's colour. Inverse depth is
interpolated linearly over the image (piecewise-planar surfaces come out exact; nearest
point outside the points' hull). Pixels of a uniform ``background`` are not drawn; points
that a view sees as background, or fewer than 2 views see, are ranked last, and with
``oversample`` > 1 the most photo-consistent of more candidates are kept (the random
start's test, :mod:`jaxedit.capture.points`).
"""

from __future__ import annotations

import jax
import numpy as np

from ..camera import Camera
from .points import BACKGROUND_TOLERANCE, _score


def _view(cameras: Camera, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(world-to-camera float64 [4, 4], (fx, fy, cx, cy) float64 [4]) of view ``k``."""
    w2c = np.asarray(cameras.world_to_camera, np.float64).reshape(-1, 4, 4)
    n = len(w2c)
    intr = np.stack([np.broadcast_to(np.asarray(getattr(cameras, a), np.float64), (n,))
                     for a in ("fx", "fy", "cx", "cy")], -1)
    return w2c[k], intr[k]


def project(points: np.ndarray, w2c: np.ndarray, intr: np.ndarray):
    """(u, v, z) float64 [P] of world ``points`` [P, 3] in one view (w2c [4, 4], intr
    (fx, fy, cx, cy)); pixel k spans [k, k + 1)."""
    p = np.asarray(points, np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
    z = p[:, 2]
    safe = np.where(np.abs(z) > 1e-12, z, 1e-12)
    return intr[0] * p[:, 0] / safe + intr[2], intr[1] * p[:, 1] / safe + intr[3], z


def back_project(u: np.ndarray, v: np.ndarray, depth: np.ndarray, w2c: np.ndarray,
                 intr: np.ndarray) -> np.ndarray:
    """World points float64 [Q, 3] at image positions (u, v) [Q] and camera ``depth`` [Q];
    the inverse of :func:`project`."""
    cam = np.stack([(u - intr[2]) / intr[0] * depth, (v - intr[3]) / intr[1] * depth, depth], -1)
    return (cam - w2c[:3, 3]) @ w2c[:3, :3]


def front_layer(u: np.ndarray, v: np.ndarray, z: np.ndarray, width: int, height: int, *,
                cell: int | None = None, tolerance: float = 0.05,
                margin: float = 0.25) -> np.ndarray:
    """bool [P]: the projected points (u, v, z [P]) in front of the camera, in the image
    widened by ``margin`` of its long side on each edge (they bound the interpolation at
    the borders), within ``tolerance`` (relative depth) of the nearest point of their
    ``cell`` px cell (None: 1/32 of the long side, at least 2) and its 8 neighbours (the rest
    are taken as hidden)."""
    from scipy.ndimage import minimum_filter

    if cell is None:
        cell = max(2, max(int(width), int(height)) // 32)

    pad = int(np.ceil(margin * max(int(width), int(height)) / cell)) * cell
    inside = ((z > 1e-9) & (u >= -pad) & (u < width + pad) & (v >= -pad)
              & (v < height + pad))
    gw, gh = -(-(int(width) + 2 * pad) // cell), -(-(int(height) + 2 * pad) // cell)
    gx = np.clip(np.floor((np.where(inside, u, 0) + pad) / cell), 0, gw - 1).astype(np.int64)
    gy = np.clip(np.floor((np.where(inside, v, 0) + pad) / cell), 0, gh - 1).astype(np.int64)
    nearest = np.full((gh, gw), np.inf)
    np.minimum.at(nearest, (gy[inside], gx[inside]), z[inside])
    nearest = minimum_filter(nearest, size=3, mode="constant", cval=np.inf)
    return inside & (z <= nearest[gy, gx] * (1.0 + tolerance))


def interpolate_depth(u: np.ndarray, v: np.ndarray, z: np.ndarray, qu: np.ndarray,
                      qv: np.ndarray) -> np.ndarray:
    """Depth float64 [Q] at (qu, qv) [Q] from points at (u, v) [P] of depth ``z`` [P] > 0:
    inverse depth linear over their triangulation, the nearest point's outside it (or
    everywhere when the points span no triangle)."""
    from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator
    from scipy.spatial import QhullError

    known = np.stack([u, v], -1)
    query = np.stack([qu, qv], -1)
    inv = NearestNDInterpolator(known, 1.0 / z)(query)
    if len(z) >= 3:
        try:
            linear = LinearNDInterpolator(known, 1.0 / z)(query)
            inv = np.where(np.isfinite(linear), linear, inv)
        except QhullError:  # collinear points: no triangle to interpolate over
            pass
    return 1.0 / inv


#: Fewest front-layer points a view needs to interpolate a depth map from.
MIN_VIEW_POINTS = 3


def view_candidates(points: np.ndarray, image: np.ndarray, cameras: Camera, k: int, count: int,
                    key: jax.Array, background=None):
    """(points float64 [Q, 3], colours float64 [Q, 3]) of up to ``count`` pixels of view ``k``
    (``image`` float [H, W, 3]) drawn with ``key``, back-projected at the depth interpolated
    from the sparse ``points`` [P, 3] it sees; Q = 0 when it sees fewer than
    :data:`MIN_VIEW_POINTS` or every pixel is ``background``."""
    height, width = image.shape[:2]
    w2c, intr = _view(cameras, k)
    u, v, z = project(points, w2c, intr)
    front = front_layer(u, v, z, width, height)
    empty = np.zeros((0, 3))
    if front.sum() < MIN_VIEW_POINTS:
        return empty, empty
    allowed = np.ones((height, width), bool)
    if background is not None:
        bg = np.asarray(background, np.float64)
        allowed = np.abs(np.asarray(image, np.float64) - bg).max(-1) > BACKGROUND_TOLERANCE
    flat = np.flatnonzero(allowed.ravel())
    if len(flat) == 0:
        return empty, empty
    k_pix, k_off = jax.random.split(key)
    pick = flat[np.asarray(jax.random.randint(k_pix, (count,), 0, len(flat)))]
    rows, cols = np.divmod(pick, width)
    offset = np.asarray(jax.random.uniform(k_off, (count, 2)), np.float64)
    qu, qv = cols + offset[:, 0], rows + offset[:, 1]
    depth = interpolate_depth(u[front], v[front], z[front], qu, qv)
    ok = np.isfinite(depth) & (depth > 0)
    world = back_project(qu[ok], qv[ok], depth[ok], w2c, intr)
    return world, np.asarray(image, np.float64)[rows[ok], cols[ok], :3]


def surface_points(points, images, cameras: Camera, num_points: int, key: jax.Array, *,
                   oversample: int = 1, background=None,
                   max_rounds: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Dense starting points on the surfaces the sparse ``points`` mark (module docstring).

    Rounds of ``num_points * oversample`` candidates, spread evenly over the views that see
    enough points, are drawn until that many are photo-consistently testable (or
    ``max_rounds``); the ``num_points`` lowest-variance ones are kept.

    Args:
      points: float [P, 3] sparse (triangulated) points in the cameras' world.
      images: float [N, H, W, 3] training images in [0, 1]; cameras: batched Camera [N].
      num_points: most points returned (fewer when few views see enough sparse points).
      key: PRNG key of the pixel draws.
      oversample: candidates drawn per point kept (1: every drawn pixel, the carved and those
        seen by fewer than 2 views ranked last).
      background: RGB of a uniform background (its pixels are not drawn; carves), or None.
      max_rounds: most rounds of candidates drawn.
    Returns:
      (points float32 [M, 3], colours float32 [M, 3] in [0, 1]), M <= num_points (0 when
      no view sees :data:`MIN_VIEW_POINTS`).
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    images = np.asarray(images, np.float64)
    n = len(images)
    total = max(1, int(num_points)) * max(1, int(oversample))
    per_view = -(-total // max(n, 1))
    rounds = []
    for r in range(max(1, int(max_rounds))):
        drawn = [view_candidates(points, images[k], cameras, k, per_view,
                                 jax.random.fold_in(jax.random.fold_in(key, r), k), background)
                 for k in range(n)]
        pts = np.concatenate([d[0] for d in drawn])
        if len(pts) == 0:
            break
        rgb = np.concatenate([d[1] for d in drawn])
        var = _score(pts, images, cameras, background)[0]
        rounds.append((pts, rgb, var))
        if sum(int(np.isfinite(x[2]).sum()) for x in rounds) >= total:
            break
    if not rounds:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
    pts, rgb, var = (np.concatenate(parts) for parts in zip(*rounds))
    keep = np.argsort(var, kind="stable")[:num_points]
    return pts[keep].astype(np.float32), rgb[keep].astype(np.float32)
