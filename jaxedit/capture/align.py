"""Estimated camera poses compared with reference poses after a least-squares similarity
alignment of their centres (SfM recovers a scene only up to a similarity)."""

from __future__ import annotations

import numpy as np

from ..camera import Camera
from ..errors import DataError
from ..io.similarity import transform_cameras


def umeyama(src, dst) -> np.ndarray:
    """float64 [4, 4] similarity (Umeyama) minimising sum |dst_i - (s R src_i + t)|^2 for
    ``src``, ``dst`` float [N, 3], N >= 3, not all collinear."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise DataError("umeyama", f"need two [N, 3] point sets with N >= 3, got "
                                   f"{list(src.shape)} and {list(dst.shape)}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    var_s = float((xs ** 2).sum() / len(src))
    if var_s < 1e-18:
        raise DataError("umeyama", "the source points all coincide")
    u, d, vt = np.linalg.svd(xd.T @ xs / len(src))
    # Flip the weakest axis when the best orthogonal map would be a reflection.
    sign = np.diag([1.0, 1.0, np.sign(np.linalg.det(u) * np.linalg.det(vt)) or 1.0])
    rot = u @ sign @ vt
    scale = float(np.trace(np.diag(d) @ sign) / var_s)
    out = np.eye(4)
    out[:3, :3] = scale * rot
    out[:3, 3] = mu_d - scale * rot @ mu_s
    return out


def camera_extent(cameras: Camera) -> float:
    """Diagonal of the bounding box of the camera centres (the scene's size for errors)."""
    centres = np.asarray(cameras.center(), np.float64)
    return float(np.linalg.norm(centres.max(0) - centres.min(0)))


def pose_errors(estimated: Camera, reference: Camera) -> dict:
    """Pose errors of ``estimated`` [N] aligned to ``reference`` [N]: ``rotation_deg`` and
    ``centre_error`` float64 [N], ``extent``, ``similarity`` float64 [4, 4] (estimated ->
    reference world) and medians (``median_centre_error_rel`` over ``extent``)."""
    est_c = np.asarray(estimated.center(), np.float64)
    ref_c = np.asarray(reference.center(), np.float64)
    if est_c.shape != ref_c.shape:
        raise DataError("cameras", f"{len(est_c)} estimated views but {len(ref_c)} reference views")
    sim = umeyama(est_c, ref_c)
    moved = transform_cameras(estimated, sim)
    r_est = np.asarray(moved.world_to_camera, np.float64)[:, :3, :3]
    r_ref = np.asarray(reference.world_to_camera, np.float64)[:, :3, :3]
    rotation_deg = rotation_angle_deg(r_est @ np.swapaxes(r_ref, -1, -2))
    centre_error = np.linalg.norm(np.asarray(moved.center(), np.float64) - ref_c, axis=1)
    extent = camera_extent(reference)
    return {"rotation_deg": rotation_deg, "centre_error": centre_error, "extent": extent,
            "similarity": sim, "median_rotation_deg": float(np.median(rotation_deg)),
            "median_centre_error_rel": float(np.median(centre_error) / max(extent, 1e-12)),
            "median_relative_rotation_deg": float(np.median(
                relative_rotation_errors(estimated, reference)))}


def rotation_angle_deg(rel) -> np.ndarray:
    """Angles in degrees of rotation matrices float [..., 3, 3]."""
    rel = np.asarray(rel, np.float64)
    # atan2, not arccos: accurate for small angles
    sin = 0.5 * np.linalg.norm(np.stack([rel[..., 2, 1] - rel[..., 1, 2],
                                         rel[..., 0, 2] - rel[..., 2, 0],
                                         rel[..., 1, 0] - rel[..., 0, 1]], -1), axis=-1)
    cos = (np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arctan2(sin, cos))


def relative_rotation_errors(estimated: Camera, reference: Camera) -> np.ndarray:
    """float64 [N (N - 1) / 2]: rotation error (degrees) of every view pair's relative
    rotation; needs no alignment, so nearly collinear centres don't inflate it."""
    r_est = np.asarray(estimated.world_to_camera, np.float64)[:, :3, :3]
    r_ref = np.asarray(reference.world_to_camera, np.float64)[:, :3, :3]
    i, j = np.triu_indices(len(r_est), 1)
    rel_est = r_est[i] @ np.swapaxes(r_est[j], -1, -2)
    rel_ref = r_ref[i] @ np.swapaxes(r_ref[j], -1, -2)
    return rotation_angle_deg(rel_est @ np.swapaxes(rel_ref, -1, -2))
