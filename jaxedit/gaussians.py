"""The Gaussians pytree: a fixed-capacity set of 3D Gaussians with an ``alive`` mask, so one
compiled train step serves a run; dead slots hold finite values and never render."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from . import sh as shlib
from .errors import DataError


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Gaussians:
    """3D Gaussians in the INRIA 3DGS parameterisation, capacity ``C``.

    Attributes:
      means: float [C, 3], world-space centres.
      log_scales: float [C, 3], per-axis log standard deviations.
      quats: float [C, 4], rotation quaternions (w, x, y, z), not necessarily unit.
      opacity_logits: float [C], logit of opacity.
      sh: float [C, (D+1)^2, 3], spherical-harmonic colour coefficients, DC first.
      alive: bool [C], which slots hold a Gaussian.
    """

    means: jax.Array
    log_scales: jax.Array
    quats: jax.Array
    opacity_logits: jax.Array
    sh: jax.Array
    alive: jax.Array

    @property
    def capacity(self) -> int:
        return self.means.shape[-2]

    @property
    def sh_degree(self) -> int:
        return shlib.degree_from_coeffs(self.sh.shape[-2])

    def num_alive(self) -> jax.Array:
        """Number of live Gaussians (int scalar)."""
        return jnp.sum(self.alive.astype(jnp.int32), axis=-1)

    def scales(self) -> jax.Array:
        """float [C, 3], per-axis standard deviations."""
        return jnp.exp(self.log_scales)

    def opacities(self) -> jax.Array:
        """float [C], opacity in (0, 1); exactly 0 for dead slots."""
        return jnp.where(self.alive, jax.nn.sigmoid(self.opacity_logits), 0.0)

    def rotations(self) -> jax.Array:
        """float [C, 3, 3], rotation matrices from the normalised quaternions."""
        return quat_to_rotmat(self.quats)

    def covariances(self) -> jax.Array:
        """float [C, 3, 3], world covariances R S S^T R^T."""
        return covariance(self.quats, self.log_scales)

    def colors(self) -> jax.Array:
        """float [C, 3], view-independent (DC) colour."""
        return jnp.maximum(shlib.dc_to_rgb(self.sh[..., 0, :]), 0.0)


def quat_to_rotmat(quats: jax.Array) -> jax.Array:
    """Rotation matrices float [..., 3, 3] from quaternions [..., 4] (w, x, y, z),
    normalised here; a zero quaternion maps to the identity without NaNs."""
    norm2 = jnp.sum(quats * quats, axis=-1, keepdims=True)
    safe = norm2 > 1e-24
    identity = jnp.array([1.0, 0.0, 0.0, 0.0], dtype=quats.dtype)
    q = jnp.where(safe, quats, identity) / jnp.sqrt(jnp.where(safe, norm2, 1.0))
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def covariance(quats: jax.Array, log_scales: jax.Array) -> jax.Array:
    """float [..., 3, 3] covariance R diag(s^2) R^T from quats [..., 4] and log-scales [..., 3]."""
    rot = quat_to_rotmat(quats)
    m = rot * jnp.exp(log_scales)[..., None, :]
    return m @ jnp.swapaxes(m, -1, -2)


def empty(capacity: int, sh_degree: int = 3, dtype=jnp.float32) -> Gaussians:
    """A pytree of ``capacity`` dead slots with finite placeholder values."""
    k = shlib.num_coeffs(sh_degree)
    quats = jnp.zeros((capacity, 4), dtype).at[:, 0].set(1.0)
    return Gaussians(
        means=jnp.zeros((capacity, 3), dtype),
        log_scales=jnp.full((capacity, 3), -10.0, dtype),
        quats=quats,
        opacity_logits=jnp.full((capacity,), -20.0, dtype),
        sh=jnp.zeros((capacity, k, 3), dtype),
        alive=jnp.zeros((capacity,), bool),
    )


def mean_knn_distance(points: np.ndarray, k: int = 3) -> np.ndarray:
    """float [N], mean distance from each point to its ``k`` nearest neighbours (others)."""
    from scipy.spatial import cKDTree  # scipy ships with scikit-image

    points = np.asarray(points, np.float64)
    n = len(points)
    if n <= 1:
        return np.full((n,), 0.01)
    kk = min(k, n - 1)
    dist, _ = cKDTree(points).query(points, k=kk + 1)
    return dist[:, 1:].mean(axis=1)


def from_points(points, colors, *, sh_degree: int = 3, capacity: int | None = None,
                init_opacity: float = 0.1, dtype=jnp.float32) -> Gaussians:
    """Gaussians at ``points`` float [N, 3], Splatfacto style: isotropic scale from the mean
    distance to 3 neighbours, identity rotation, opacity ``init_opacity``, DC colour ``colors``
    float [N, 3] in [0, 1] (uint8 rescaled); ``capacity`` slots (>= N), default N."""
    points = np.asarray(points, np.float64)
    colors = np.asarray(colors)
    if colors.dtype == np.uint8:
        colors = colors.astype(np.float64) / 255.0
    n = len(points)
    capacity = n if capacity is None else capacity
    if capacity < n:
        raise ValueError(f"capacity {capacity} is smaller than the {n} points")
    dist = np.maximum(mean_knn_distance(points), 1e-7)
    g = empty(capacity, sh_degree, dtype)
    logit = float(np.log(init_opacity / (1.0 - init_opacity)))
    dc = shlib.rgb_to_dc(np.clip(colors, 0.0, 1.0))
    return dataclasses.replace(
        g,
        means=g.means.at[:n].set(points.astype(np.float32)),
        log_scales=g.log_scales.at[:n].set(np.log(dist)[:, None].repeat(3, 1).astype(np.float32)),
        opacity_logits=g.opacity_logits.at[:n].set(logit),
        sh=g.sh.at[:n, 0, :].set(dc.astype(np.float32)),
        alive=g.alive.at[:n].set(True),
    )


def subsample_points(points, colors, max_count: int, key: jax.Array):
    """At most ``max_count`` (>= 1) of ``points`` float [N, 3] and their ``colors`` [N, 3],
    drawn uniformly without replacement by ``key``, in their original order: (points,
    colors) NumPy [min(N, max_count), 3] each."""
    points, colors = np.asarray(points), np.asarray(colors)
    if max_count < 1:
        raise DataError("max_count", f"must be >= 1, got {max_count}")
    if len(points) <= max_count:
        return points, colors
    keep = np.sort(np.asarray(jax.random.permutation(key, len(points))[:max_count]))
    return points[keep], colors[keep]


def grow(g: Gaussians, capacity: int) -> Gaussians:
    """Copy ``g`` into a larger pytree of ``capacity`` slots (new slots dead)."""
    if capacity < g.capacity:
        raise ValueError(f"cannot grow capacity {g.capacity} down to {capacity}")
    pad = empty(capacity - g.capacity, g.sh_degree, g.means.dtype)
    return jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b], axis=0), g, pad)


def compact(g: Gaussians) -> Gaussians:
    """The alive Gaussians only, in slot order (outside jit; shape depends on data)."""
    keep = np.asarray(g.alive)
    return jax.tree_util.tree_map(lambda a: a[keep], g)


def splat_arrays(g: Gaussians) -> dict[str, np.ndarray]:
    """The alive Gaussians as viser's ``add_gaussian_splats`` arguments (DC colour only):
    {"centers": float32 [N, 3], "covariances": float32 [N, 3, 3], "rgbs": float32 [N, 3] in
    [0, 1], "opacities": float32 [N, 1]}."""
    g = compact(g)
    return {"centers": np.asarray(g.means, np.float32),
            "covariances": np.asarray(g.covariances(), np.float32),
            "rgbs": np.clip(np.asarray(g.colors(), np.float32), 0.0, 1.0),
            "opacities": np.asarray(g.opacities(), np.float32)[:, None]}


def with_sh_degree(g: Gaussians, degree: int) -> Gaussians:
    """Same Gaussians with SH coefficients truncated or zero-padded to ``degree``."""
    k_new, k_old = shlib.num_coeffs(degree), g.sh.shape[1]
    if k_new <= k_old:
        sh = g.sh[:, :k_new]
    else:
        sh = jnp.concatenate([g.sh, jnp.zeros((g.capacity, k_new - k_old, 3), g.sh.dtype)], axis=1)
    return dataclasses.replace(g, sh=sh)
