"""The dense oracle the tests hold the tile splatter to: per pixel, front to back (INRIA):

    power = -0.5 (a dx^2 + c dy^2) - b dx dy          (skip if power > 0)
    alpha = min(0.99, o exp(power))                   (skip if alpha < 1/255)
    if T (1 - alpha) < 1e-4: stop, this Gaussian is NOT blended
    C += c alpha T;  T *= 1 - alpha
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from ..camera import Camera
from ..gaussians import Gaussians
from . import project as P
from .types import RenderOutput

#: Work per lax.map step of the oracle (pixels x Gaussians), to bound memory.
_BLOCK_ELEMENTS = 1 << 22


def pixel_alpha(means2d, conics, opacities, px, py):
    """alpha float [...] at pixel centres ``px``, ``py`` [...] (broadcastable), 0 where skipped,
    of means2d [..., 2], conics [..., 3], opacities [...]."""
    dx = means2d[..., 0] - px
    dy = means2d[..., 1] - py
    power = -0.5 * (conics[..., 0] * dx * dx + conics[..., 2] * dy * dy) - conics[..., 1] * dx * dy
    alpha = jnp.minimum(P.ALPHA_MAX, opacities * jnp.exp(jnp.minimum(power, 0.0)))
    return jnp.where((power > 0) | (alpha < P.ALPHA_MIN), 0.0, alpha)


def finish(features, transmittance, background, dtype):
    """(rgb [H, W, 3], alpha [H, W], depth [H, W]) from features float [H, W, 4] = sum_i w_i
    (r, g, b, z), final transmittance [H, W] and background [3] or None (black)."""
    rgb = features[..., :3]
    if background is not None:
        rgb = rgb + transmittance[..., None] * jnp.asarray(background, dtype)
    alpha = jnp.clip(1.0 - transmittance, 0.0, 1.0)
    has = alpha > 1e-12
    depth = jnp.where(has, features[..., 3] / jnp.where(has, alpha, 1.0), 0.0)
    return rgb, alpha, depth


def _composite_dense(proj: P.Projected, width: int, height: int):
    """features float [H, W, 4] and final transmittance float [H, W], densely."""
    dtype = proj.means2d.dtype
    order = jnp.argsort(jnp.where(proj.visible, proj.depths, jnp.inf), stable=True)
    m2, con, op = proj.means2d[order], proj.conics[order], proj.opacities[order]
    feats = jnp.concatenate([proj.colors, proj.depths[:, None]], -1)[order]  # [C, 4]
    n_pix = width * height
    cap = max(proj.means2d.shape[0], 1)
    block = max(1, min(n_pix, _BLOCK_ELEMENTS // cap))
    n_blocks = -(-n_pix // block)
    idx = jnp.arange(n_blocks * block)
    pxs = (idx % width).astype(dtype) + 0.5
    pys = (idx // width).astype(dtype) + 0.5

    def one_block(xy):
        px, py = xy  # [block]
        alpha = pixel_alpha(m2[None], con[None], op[None], px[:, None], py[:, None])  # [block, C]
        t_after = jnp.cumprod(1.0 - alpha, axis=-1)
        t_before = jnp.concatenate([jnp.ones_like(t_after[:, :1]), t_after[:, :-1]], -1)
        blended = t_after >= P.T_MIN  # a prefix: T only decreases
        w = jnp.where(blended, alpha * t_before, 0.0)
        t_final = jnp.prod(jnp.where(blended, 1.0 - alpha, 1.0), -1)
        return P.matmul_exact(w, feats), t_final  # not TF32 on a GPU: this is the oracle

    f, t = jax.lax.map(one_block, (pxs.reshape(n_blocks, block), pys.reshape(n_blocks, block)))
    f = f.reshape(-1, 4)[:n_pix].reshape(height, width, 4)
    t = t.reshape(-1)[:n_pix].reshape(height, width)
    return f, t


@functools.partial(jax.jit, static_argnames=("sh_degree",))
def _render_one(gaussians, camera, background, sh_degree, near, far, means2d_delta):
    proj = P.project(gaussians, camera, sh_degree=sh_degree, near=near, far=far,
                     means2d_delta=means2d_delta)
    feats, trans = _composite_dense(proj, camera.width, camera.height)
    rgb, alpha, depth = finish(feats, trans, background, gaussians.means.dtype)
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, means2d=proj.means2d,
                        radii=proj.radii, visible=proj.visible,
                        num_intersections=jnp.zeros((), jnp.int32),
                        overflow=jnp.zeros((), bool))


def render_reference(gaussians: Gaussians, camera: Camera, *, background=None,
                     sh_degree: int | None = None, near: float = 0.01, far: float = 1e10,
                     means2d_delta: jax.Array | None = None) -> RenderOutput:
    """Dense oracle render; same signature and output as :func:`jaxedit.raster.render`."""
    sh_degree = P.check_sh_degree(gaussians, sh_degree)
    bg = None if background is None else jnp.asarray(background, gaussians.means.dtype)
    fn = functools.partial(_render_one, sh_degree=sh_degree)
    if camera.batch_shape:
        d_axis = None if means2d_delta is None else 0
        return jax.vmap(lambda cam, d: fn(gaussians, cam, bg, near=near, far=far, means2d_delta=d),
                        in_axes=(0, d_axis))(camera, means2d_delta)
    return fn(gaussians, camera, bg, near=near, far=far, means2d_delta=means2d_delta)


@jax.jit
def _weights_one(gaussians, camera, values, near, far):
    proj = P.project(gaussians, camera, sh_degree=0, near=near, far=far)
    order = jnp.argsort(jnp.where(proj.visible, proj.depths, jnp.inf), stable=True)
    m2, con, op = proj.means2d[order], proj.conics[order], proj.opacities[order]
    width, height = camera.width, camera.height
    vals = values.reshape(width * height, -1)
    alpha = pixel_alpha(m2[None], con[None], op[None],
                        (jnp.arange(width * height) % width).astype(m2.dtype)[:, None] + 0.5,
                        (jnp.arange(width * height) // width).astype(m2.dtype)[:, None] + 0.5)
    t_after = jnp.cumprod(1.0 - alpha, axis=-1)  # [P, C]
    t_before = jnp.concatenate([jnp.ones_like(t_after[:, :1]), t_after[:, :-1]], -1)
    w = jnp.where(t_after >= P.T_MIN, alpha * t_before, 0.0)
    sums = P.matmul_exact(w.T, vals)  # [C, F], depth order
    return jnp.zeros_like(sums).at[order].set(sums)


def accumulate_weights_reference(gaussians: Gaussians, camera: Camera, values, *,
                                 near: float = 0.01, far: float = 1e10) -> jax.Array:
    """Dense oracle of :func:`jaxedit.raster.render.accumulate_weights` (same signature)."""
    values = jnp.asarray(values, gaussians.means.dtype)
    if camera.batch_shape:
        return sum(_weights_one(gaussians, camera[i], values[i], near, far)
                   for i in range(camera.batch_shape[0]))
    return _weights_one(gaussians, camera, values, near, far)
