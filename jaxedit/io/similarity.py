"""Similarity transforms of the world (q = s R p + t) applied to points, cameras and
Gaussians, e.g. to undo ``Dataset.world_transform``."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from .. import sh as shlib
from ..camera import Camera
from ..errors import DataError
from ..gaussians import Gaussians

_RIGID_TOL = 1e-3
# One compiled basis per SH degree (the direction set has a fixed shape).
_basis = jax.jit(shlib.basis, static_argnums=0)


def split_similarity(matrix) -> tuple[np.ndarray, float, np.ndarray]:
    """4x4 similarity [s R | t; 0 0 0 1] -> (R float64 [3, 3], s, t [3]); DataError otherwise."""
    m = np.asarray(matrix, np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise DataError("world_transform", f"expected a finite 4x4 matrix, got shape {list(m.shape)}")
    a = m[:3, :3]
    det = np.linalg.det(a)
    if det <= 0:
        raise DataError("world_transform", "not a similarity (determinant <= 0)")
    s = float(np.cbrt(det))
    r = a / s
    if np.abs(r.T @ r - np.eye(3)).max() > _RIGID_TOL or np.abs(m[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise DataError("world_transform", "not a similarity (rotation part is not orthogonal)")
    return r, s, m[:3, 3]


def transform_points(points, matrix) -> np.ndarray:
    """Apply a 4x4 similarity to float [..., 3] points (returns float64 [..., 3])."""
    m = np.asarray(matrix, np.float64)
    p = np.asarray(points, np.float64)
    return p @ m[:3, :3].T + m[:3, 3]


def transform_cameras(cameras: Camera, matrix) -> Camera:
    """The same cameras (single or batched) after the world is mapped by ``matrix``;
    intrinsics unchanged, float32 ``world_to_camera``."""
    r, s, t = split_similarity(matrix)
    w2c = np.asarray(cameras.world_to_camera, np.float64)
    # x = R_c p + t_c with p = R^T (q - t) / s, in new units x' = s x:
    # x' = (R_c R^T) q + (s t_c - R_c R^T t).
    rc, tc = w2c[..., :3, :3], w2c[..., :3, 3]
    new_r = rc @ r.T
    new_t = s * tc - np.einsum("...ij,j->...i", new_r, t)
    out = np.zeros_like(w2c)
    out[..., :3, :3] = new_r
    out[..., :3, 3] = new_t
    out[..., 3, 3] = 1.0
    return dataclasses.replace(cameras, world_to_camera=out.astype(np.float32))


def rotmat_to_quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) float64 [4] of a rotation matrix [3, 3], w >= 0."""
    r = np.asarray(r, np.float64)
    tr = np.trace(r)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of (w, x, y, z) quaternions, broadcasting over [..., 4]."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, np.float64), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, np.float64), -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def _fibonacci_directions(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def sh_rotation_matrices(rotation: np.ndarray, degree: int) -> list[np.ndarray]:
    """Per band l = 0..degree, X_l [2l+1, 2l+1] with Y_l(R^T d) = X_l^T Y_l(d), fitted by least
    squares on the basis itself (exact: each band is closed under rotation)."""
    r = np.asarray(rotation, np.float64)
    dirs = _fibonacci_directions(64)
    full = np.asarray(_basis(degree, jnp.asarray(dirs, jnp.float32)), np.float64)
    full_rot = np.asarray(_basis(degree, jnp.asarray(dirs @ r, jnp.float32)), np.float64)
    out = []
    for band in range(degree + 1):
        sl = slice(band * band, (band + 1) * (band + 1))
        x, *_ = np.linalg.lstsq(full[:, sl], full_rot[:, sl], rcond=None)
        out.append(x)
    return out


def rotate_sh(sh, rotation) -> np.ndarray:
    """SH coefficients float [..., K, 3] whose colour follows a rotation R of the world."""
    sh = np.asarray(sh, np.float64)
    degree = shlib.degree_from_coeffs(sh.shape[-2])
    out = np.empty_like(sh)
    for band, x in enumerate(sh_rotation_matrices(rotation, degree)):
        sl = slice(band * band, (band + 1) * (band + 1))
        out[..., sl, :] = np.einsum("ij,...jc->...ic", x, sh[..., sl, :])
    return out


#: Axis names of :func:`upright`.
AXES = ("+x", "-x", "+y", "-y", "+z", "-z")


def upright(up: str) -> np.ndarray:
    """4x4 rotation taking the world's ``up`` axis (one of :data:`AXES`) to -y, the up of
    the 3DGS .ply convention (an OpenCV / COLMAP world) that splat viewers show upright:
    the quarter turn about ``up`` x (-y), a half turn about x for +y, identity for -y."""
    if up not in AXES:
        raise DataError("--up", f"must be one of {', '.join(AXES)}, got {up!r}")
    u = np.zeros(3)
    u["xyz".index(up[1])] = 1.0 if up[0] == "+" else -1.0
    v = np.array([0.0, -1.0, 0.0])
    if u @ v > 0.5:
        r = np.eye(3)
    elif u @ v < -0.5:
        r = np.diag([1.0, -1.0, -1.0])
    else:  # Rodrigues' formula for a quarter turn about the unit axis u x v
        k = np.cross(u, v)
        kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
        r = np.eye(3) + kx + kx @ kx
    m = np.eye(4)
    m[:3, :3] = r
    return m


def transform_gaussians(g: Gaussians, matrix) -> Gaussians:
    """The same scene (float32) after the world is mapped by ``matrix`` (q = s R p + t),
    SH bands rotated so view-dependent colour follows."""
    r, s, t = split_similarity(matrix)
    means = transform_points(np.asarray(g.means), matrix)
    q = np.asarray(g.quats, np.float64)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(norm > 1e-12, q / np.maximum(norm, 1e-12), [1.0, 0.0, 0.0, 0.0])
    quats = quat_multiply(rotmat_to_quat(r), q)
    f32 = lambda a: jnp.asarray(np.asarray(a, np.float32))  # noqa: E731
    return dataclasses.replace(
        g, means=f32(means), log_scales=f32(np.asarray(g.log_scales, np.float64) + np.log(s)),
        quats=f32(quats), sh=f32(rotate_sh(g.sh, r)))
