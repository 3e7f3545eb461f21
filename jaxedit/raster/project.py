"""EWA projection of 3D Gaussians to screen-space ellipses, with SH colour and culling, in
INRIA 3DGS / gsplat's conventions; the footprint is gsplat's opacity-aware extent, so the
tile splatter equals the dense oracle exactly."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .. import sh as shlib
from ..camera import Camera
from ..gaussians import Gaussians, quat_to_rotmat

#: 2D low-pass ("blur") added to every screen-space covariance, in pixels^2.
BLUR = 0.3
#: Per-pixel skip threshold on alpha.
ALPHA_MIN = 1.0 / 255.0
#: Alpha clamp.
ALPHA_MAX = 0.99
#: A pixel stops blending when its transmittance would drop below this.
T_MIN = 1e-4
#: Log-scales are clipped to this range so exp() never overflows (float32).
LOG_SCALE_RANGE = (-30.0, 20.0)
#: World coordinates beyond this magnitude are treated as invalid (culled).
MAX_COORD = 1e12
#: Relative safety margin on the footprint so rounding never drops a pixel.
FOOTPRINT_MARGIN = 1e-3


class Projected(NamedTuple):
    """Screen-space Gaussians for one camera (capacity ``C``).

    Culled Gaussians hold finite placeholders, ``opacities == 0``, ``visible == False``, zero
    gradients.

    Attributes:
      means2d: float [C, 2], projected centres in pixels.
      conics: float [C, 3], inverse 2D covariance (a, b, c): q = a dx^2 + 2 b dx dy + c dy^2.
      depths: float [C], camera-space z.
      opacities: float [C], sigmoid(logit); 0 where culled.
      colors: float [C, 3], SH colour seen from this camera, >= 0.
      extents: float [C, 2], half-widths in pixels of the footprint's bounding box.
      radii: int32 [C], ceil(max(extents)); 0 where culled.
      visible: bool [C].
    """

    means2d: jax.Array
    conics: jax.Array
    depths: jax.Array
    opacities: jax.Array
    colors: jax.Array
    extents: jax.Array
    radii: jax.Array
    visible: jax.Array


def matmul_exact(a: jax.Array, b: jax.Array) -> jax.Array:
    """``a @ b`` in full float32 (no TF32 on GPUs) on every platform: float [..., n, m]."""
    return jnp.matmul(a, b, precision=jax.lax.Precision.HIGHEST)


def _inputs_valid(g: Gaussians, near, far, cam: Camera):
    """bool [C]: alive, finite, in front of the near plane and before far (no gradient)."""
    finite = (jnp.all(jnp.isfinite(g.means), -1) & jnp.all(jnp.abs(g.means) < MAX_COORD, -1)
              & jnp.all(jnp.isfinite(g.log_scales), -1) & jnp.all(jnp.isfinite(g.quats), -1)
              & jnp.isfinite(g.opacity_logits)
              & jnp.all(jnp.isfinite(g.sh.reshape(g.sh.shape[0], -1)), -1))
    means = jnp.where(finite[:, None], g.means, 0.0)
    z = matmul_exact(means, cam.rotation[2]) + cam.translation[2]
    return jax.lax.stop_gradient(g.alive & finite & (z > near) & (z < far))


def project(gaussians: Gaussians, camera: Camera, *, sh_degree: int | None = None,
            near: float = 0.01, far: float = 1e10,
            means2d_delta: jax.Array | None = None) -> Projected:
    """Project Gaussians (capacity C) for one camera -> :class:`Projected`.

    ``sh_degree``: static active degree (default all); ``near``, ``far``: camera-space z kept;
    ``means2d_delta``: optional float [C, 2] added to the projected means.
    """
    g = gaussians
    dtype = g.means.dtype
    width, height = camera.width, camera.height
    valid = _inputs_valid(g, near, far, camera)
    vm = valid[:, None]

    # Double-where: culled Gaussians use safe placeholders, so no NaN values or gradients.
    means = jnp.where(vm, g.means, 0.0)
    log_scales = jnp.clip(jnp.where(vm, g.log_scales, 0.0), *LOG_SCALE_RANGE)
    quats = jnp.where(vm, g.quats, jnp.array([1.0, 0.0, 0.0, 0.0], dtype))

    rot_w2c, t_w2c = camera.rotation.astype(dtype), camera.translation.astype(dtype)
    pc = matmul_exact(means, rot_w2c.T) + t_w2c  # [C, 3] camera coordinates
    z = jnp.where(valid, pc[:, 2], 1.0)
    x, y = pc[:, 0], pc[:, 1]
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    inv_z = 1.0 / z
    means2d = jnp.stack([fx * x * inv_z + cx, fy * y * inv_z + cy], -1)
    if means2d_delta is not None:
        means2d = means2d + means2d_delta

    # Jacobian at the clamped direction (INRIA / gsplat): no huge far off-axis ellipses.
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lim_xp, lim_xn = (width - cx) / fx + 0.3 * tan_x, cx / fx + 0.3 * tan_x
    lim_yp, lim_yn = (height - cy) / fy + 0.3 * tan_y, cy / fy + 0.3 * tan_y
    tx = jnp.clip(x * inv_z, -lim_xn, lim_xp) * z
    ty = jnp.clip(y * inv_z, -lim_yn, lim_yp) * z
    zero = jnp.zeros_like(z)
    jac = jnp.stack([
        jnp.stack([fx * inv_z, zero, -fx * tx * inv_z * inv_z], -1),
        jnp.stack([zero, fy * inv_z, -fy * ty * inv_z * inv_z], -1),
    ], -2)  # [C, 2, 3]
    rot = quat_to_rotmat(quats)
    m = rot * jnp.exp(log_scales)[:, None, :]  # R S
    t = matmul_exact(matmul_exact(jac, rot_w2c), m)  # [C, 2, 3] = J W R S
    cov = matmul_exact(t, jnp.swapaxes(t, -1, -2))
    a = cov[:, 0, 0] + BLUR
    b = cov[:, 0, 1]
    c = cov[:, 1, 1] + BLUR
    det = a * c - b * b
    ok = valid & (det > 0) & jnp.isfinite(det) & jnp.isfinite(a) & jnp.isfinite(c)
    ok = jax.lax.stop_gradient(ok)
    det_s = jnp.where(ok, det, 1.0)
    a_s, b_s, c_s = jnp.where(ok, a, 1.0), jnp.where(ok, b, 0.0), jnp.where(ok, c, 1.0)
    conics = jnp.stack([c_s / det_s, -b_s / det_s, a_s / det_s], -1)

    opac = jax.nn.sigmoid(jnp.where(valid, g.opacity_logits, 0.0))
    # Footprint q <= k2 with k2 = 2 ln(255 o): beyond it alpha < 1/255 always.
    k2 = 2.0 * jnp.log(jnp.maximum(opac / ALPHA_MIN, 1e-30))
    ok = ok & jax.lax.stop_gradient(k2 > 0)
    # Bounding box of {d: d^T cov^-1 d <= k2}: half-widths k sqrt(cov_xx), k sqrt(cov_yy).
    k = jnp.sqrt(jnp.maximum(k2, 0.0)) * (1.0 + FOOTPRINT_MARGIN)
    ext = jax.lax.stop_gradient(jnp.stack([k * jnp.sqrt(a_s), k * jnp.sqrt(c_s)], -1) + 1e-3)
    mx, my = jax.lax.stop_gradient(means2d[:, 0]), jax.lax.stop_gradient(means2d[:, 1])
    # Pixel-centre range of the box; on screen iff it meets [0, W-1] x [0, H-1].
    on_screen = ((jnp.ceil(mx - ext[:, 0] - 0.5) <= width - 1) & (jnp.floor(mx + ext[:, 0] - 0.5) >= 0)
                 & (jnp.ceil(my - ext[:, 1] - 0.5) <= height - 1) & (jnp.floor(my + ext[:, 1] - 0.5) >= 0))
    visible = ok & on_screen & jnp.all(jnp.isfinite(means2d), -1) & jnp.all(jnp.isfinite(ext), -1)
    visible = jax.lax.stop_gradient(visible)

    centre = -matmul_exact(t_w2c, rot_w2c)  # -R^T t, exact (see matmul_exact)
    colors = shlib.evaluate(jnp.where(vm[:, :, None], g.sh, 0.0), means - centre, sh_degree)

    vis1 = visible[:, None]
    return Projected(
        means2d=jnp.where(vis1, means2d, 0.0),
        conics=jnp.where(vis1, conics, jnp.array([1.0, 0.0, 1.0], dtype)),
        depths=jnp.where(visible, z, 0.0),
        opacities=jnp.where(visible, opac, 0.0),
        colors=jnp.where(vis1, colors, 0.0),
        extents=jnp.where(vis1, ext, 0.0),
        radii=jnp.where(visible, jnp.ceil(jnp.max(jnp.where(vis1, ext, 0.0), -1)), 0).astype(jnp.int32),
        visible=visible,
    )


def check_sh_degree(gaussians: Gaussians, sh_degree: int | None) -> int:
    """The active SH degree to use; raises DataError when it exceeds the pytree's."""
    from ..errors import DataError

    full = gaussians.sh_degree
    if sh_degree is None:
        return full
    if not 0 <= int(sh_degree) <= full:
        raise DataError("sh_degree", f"{sh_degree} is not in 0..{full} (the Gaussians' SH degree)")
    return int(sh_degree)
