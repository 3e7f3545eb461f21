"""Real spherical harmonics up to degree 3, in INRIA 3DGS's sign convention: the colour seen
along ``d`` (camera centre to mean) is ``max(sum_k sh[k] Y_k(d) + 0.5, 0)``."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
      -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
      0.3731763325901154, -0.4570457994644658, 1.445305721320277,
      -0.5900435899266435)


def num_coeffs(degree: int) -> int:
    """Number of SH coefficients per channel for ``degree`` (0..3)."""
    return (degree + 1) ** 2


def degree_from_coeffs(n: int) -> int:
    """Inverse of :func:`num_coeffs`; raises ValueError for a non-square count."""
    d = int(round(np.sqrt(n))) - 1
    if (d + 1) ** 2 != n or not 0 <= d <= 3:
        raise ValueError(f"{n} SH coefficients is not (d+1)^2 for a degree d in 0..3")
    return d


def basis(degree: int, dirs: jnp.ndarray) -> jnp.ndarray:
    """SH basis values float [..., (degree+1)^2] of unit directions [..., 3] (static
    ``degree`` in 0..3)."""
    x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    out = [jnp.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [C2[0] * xy, C2[1] * yz, C2[2] * (2 * zz - xx - yy),
                C2[3] * xz, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [C3[0] * y * (3 * xx - yy),
                C3[1] * xy * z,
                C3[2] * y * (4 * zz - xx - yy),
                C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
                C3[4] * x * (4 * zz - xx - yy),
                C3[5] * z * (xx - yy),
                C3[6] * x * (xx - 3 * yy)]
    return jnp.stack(out, axis=-1)


def evaluate(sh: jnp.ndarray, dirs: jnp.ndarray, degree: int | None = None) -> jnp.ndarray:
    """Colour float [..., 3] (>= 0) of ``sh`` float [..., K, 3] (K = (D+1)^2, DC first) seen
    along ``dirs`` float [..., 3] (any length), at static ``degree`` <= D (default D)."""
    full = degree_from_coeffs(sh.shape[-2])
    degree = full if degree is None else min(degree, full)
    norm = jnp.sqrt(jnp.sum(dirs * dirs, axis=-1, keepdims=True))
    unit = dirs / jnp.maximum(norm, 1e-12)
    b = basis(degree, unit)  # [..., k]
    k = num_coeffs(degree)
    # HIGHEST: no TF32 on GPUs.
    rgb = jnp.einsum("...k,...kc->...c", b, sh[..., :k, :],
                     precision=jax.lax.Precision.HIGHEST) + 0.5
    return jnp.maximum(rgb, 0.0)


def rgb_to_dc(rgb):
    """DC coefficient whose colour is ``rgb`` (inverse of ``0.5 + C0 * dc``)."""
    return (rgb - 0.5) / C0


def dc_to_rgb(dc):
    return 0.5 + C0 * dc
