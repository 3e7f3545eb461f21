"""COLMAP-like initial point clouds for the built-in scenes."""

from __future__ import annotations

import numpy as np

from ..camera import Camera
from ..errors import DataError
from . import raycast as rc


def _visible_from(scene: rc.Scene, points: np.ndarray, ids: np.ndarray, cam: Camera,
                  tol: float) -> np.ndarray:
    """bool [P]: which surface points (on shapes ``ids``) camera ``cam`` sees."""
    w2c = np.asarray(cam.world_to_camera, np.float64)
    pc = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = float(cam.fx) * pc[:, 0] / z + float(cam.cx)
        v = float(cam.fy) * pc[:, 1] / z + float(cam.cy)
    inside = (z > 1e-6) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    seen = np.zeros(len(points), bool)
    idx = np.flatnonzero(inside)
    if idx.size == 0:
        return seen
    origin = -w2c[:3, :3].T @ w2c[:3, 3]
    delta = points[idx] - origin
    dist = np.linalg.norm(delta, axis=-1)
    t, hit_ids = rc.intersect(scene, origin, delta / dist[:, None])
    seen[idx] = (hit_ids == ids[idx]) & (np.abs(t - dist) < tol)
    return seen


def sample_points(scene: rc.Scene, cameras: Camera, num_points: int, rng: np.random.Generator, *,
                  position_noise: float = 0.004, color_noise: float = 0.03,
                  outlier_fraction: float = 0.05, min_views: int = 2,
                  max_cameras: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """A COLMAP-like sparse cloud of ``scene`` as seen by ``cameras``.

    Args:
      scene: the scene.
      cameras: batched Camera [N]; at most ``max_cameras`` of them decide visibility.
      num_points: total number of points, outliers included.
      rng: the random generator (all draws come from it).
      position_noise: std of the positional noise, as a fraction of the scene's radius.
      color_noise: std of the additive colour noise (colours in [0, 1]).
      outlier_fraction: fraction of ``num_points`` drawn uniformly in the bounding box.
      min_views: a surface point is kept only if this many cameras see it.
    Returns:
      (points float32 [num_points, 3], colors float32 [num_points, 3] in [0, 1]).
    """
    if num_points < 1:
        raise DataError("num_points", f"must be >= 1, got {num_points}")
    if not 0.0 <= outlier_fraction <= 1.0:
        raise DataError("outlier_fraction", f"must lie in [0, 1], got {outlier_fraction}")
    n_cams = len(cameras)
    pick = np.unique(np.linspace(0, n_cams - 1, min(max_cameras, n_cams)).round().astype(np.int64))
    cams = [cameras[int(i)] for i in pick]
    min_views = min(min_views, len(cams))
    lo, hi = scene.bounds()
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    n_out = int(round(outlier_fraction * num_points))
    n_surf = num_points - n_out

    areas = np.array([rc.surface_area(s) for s in scene.shapes])
    kept_pts, kept_ids, kept_view = [], [], []
    total, rounds = 0, 0
    while total < n_surf and n_surf > 0:
        rounds += 1
        if rounds > 8:
            raise DataError(f"scene {scene.name!r}", "cameras see too little of the surfaces to "
                            f"place {n_surf} points seen by {min_views} views")
        want = 2 * (n_surf - total) + 64
        counts = rng.multinomial(want, areas / areas.sum())
        pts = np.concatenate([rc.sample_surface(s, int(k), rng) for s, k in zip(scene.shapes, counts)])
        ids = np.repeat(np.arange(len(scene.shapes)), counts)
        seen = np.stack([_visible_from(scene, pts, ids, c, 1e-5 * max(radius, 1.0)) for c in cams])
        ok = seen.sum(axis=0) >= min_views
        first_view = np.argmax(seen, axis=0)
        kept_pts.append(pts[ok])
        kept_ids.append(ids[ok])
        kept_view.append(first_view[ok])
        total += int(ok.sum())
    if n_surf > 0:
        pts = np.concatenate(kept_pts)
        ids = np.concatenate(kept_ids)
        view = np.concatenate(kept_view)
        order = rng.permutation(len(pts))[:n_surf]
        pts, ids, view = pts[order], ids[order], view[order]
        # shaded as seen from the first camera that sees it
        cam_centres = np.stack([np.asarray(c.center(), np.float64) for c in cams])
        centres = cam_centres[view]
        colors = rc.shaded_color(scene, pts, ids, centres).astype(np.float64)
        pts = pts + rng.normal(scale=position_noise * radius, size=pts.shape)
        colors = np.clip(colors + rng.normal(scale=color_noise, size=colors.shape), 0.0, 1.0)
    else:
        pts = np.zeros((0, 3))
        colors = np.zeros((0, 3))
    margin = 0.1 * (hi - lo)
    out_pts = rng.uniform(lo - margin, hi + margin, size=(n_out, 3))
    out_cols = rng.uniform(0.0, 1.0, size=(n_out, 3))
    all_pts = np.concatenate([pts, out_pts])
    all_cols = np.concatenate([colors, out_cols])
    order = rng.permutation(len(all_pts))
    return all_pts[order].astype(np.float32), all_cols[order].astype(np.float32)
