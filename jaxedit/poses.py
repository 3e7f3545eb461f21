"""Small rigid corrections of cameras fitted to their images: held-out cameras refined against
a frozen scene (:func:`refine_poses`) or training cameras learned with it
(:class:`CameraCorrections`). A correction float [6] is a rotation vector (radians) about the
point at the scene's depth on the optical axis and a translation in units of that depth, so a
unit of either moves the image by about ``f`` pixels and one learning rate suits both.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from .camera import Camera
from .errors import DataError
from .gaussians import Gaussians
from .raster.project import check_sh_degree
from .raster.render import count_pairs, next_capacity, render_tiles, resolve_backend


@dataclasses.dataclass(frozen=True)
class RefineConfig:
    """Settings of :func:`refine_poses`.

    Attributes:
      steps: Adam steps (fixed: no stopping rule).
      lr: initial learning rate of both halves of ``delta``, cosine-decayed.
      final_lr_fraction: the learning rate at the last step, as a fraction of ``lr``.
      blur_px: blur sigma (pixels) at the first step, shrinking to 0 at half the steps; 0: off.
      loss: "mse" (what PSNR scores) or "l1".
      headroom: intersection buffer over the pairs counted at the starting poses.
    """

    steps: int = 100
    lr: float = 2e-3
    final_lr_fraction: float = 0.01
    blur_px: float = 0.0
    loss: str = "mse"
    headroom: float = 1.5

    def check(self) -> "RefineConfig":
        if self.steps < 1:
            raise DataError("steps", f"must be >= 1, got {self.steps}")
        if not (self.lr > 0 and 0 < self.final_lr_fraction <= 1):
            raise DataError("lr", f"need lr > 0 and 0 < final_lr_fraction <= 1, got "
                                  f"{self.lr}, {self.final_lr_fraction}")
        if self.blur_px < 0:
            raise DataError("blur_px", f"must be >= 0, got {self.blur_px}")
        if self.loss not in ("l1", "mse"):
            raise DataError("loss", f"must be 'l1' or 'mse', got {self.loss!r}")
        return self


def so3_exp(omega: jax.Array) -> jax.Array:
    """Rotation vectors float [..., 3] -> matrices [..., 3, 3] (Rodrigues, finite grads at 0)."""
    omega = jnp.asarray(omega)
    t2 = jnp.sum(omega * omega, -1)[..., None, None]
    small = t2 < 1e-8
    safe = jnp.where(small, 1.0, t2)
    t = jnp.sqrt(safe)
    a = jnp.where(small, 1.0 - t2 / 6.0, jnp.sin(t) / t)
    b = jnp.where(small, 0.5 - t2 / 24.0, (1.0 - jnp.cos(t)) / safe)
    x, y, z = omega[..., 0], omega[..., 1], omega[..., 2]
    zero = jnp.zeros_like(x)
    k = jnp.stack([jnp.stack([zero, -z, y], -1), jnp.stack([z, zero, -x], -1),
                   jnp.stack([-y, x, zero], -1)], -2)
    eye = jnp.eye(3, dtype=omega.dtype)
    return eye + a * k + b * (k @ k)


def apply_delta(cameras: Camera, delta: jax.Array, depth: jax.Array) -> Camera:
    """``cameras`` (one or a batch [B]) with ``world_to_camera`` = [exp(w) | depth u] @
    world_to_camera, ``delta`` float [6] or [B, 6] = (w rotation vector, u translation / depth),
    ``depth`` float [] or [B] the translation unit (scene units)."""
    w2c = jnp.asarray(cameras.world_to_camera)
    delta = jnp.asarray(delta, w2c.dtype)
    rot = so3_exp(delta[..., :3])
    depth = jnp.asarray(depth, w2c.dtype)[..., None]
    # Pivot at the scene's depth, not the camera centre: rotation then mostly changes
    # parallax and translation shifts the image, nearly independent for Adam.
    pivot = depth * jnp.array([0.0, 0.0, 1.0], w2c.dtype)
    trans = depth * delta[..., 3:] + pivot - jnp.einsum("...ij,...j->...i", rot, pivot,
                                                        precision=jax.lax.Precision.HIGHEST)
    new_r = jnp.matmul(rot, w2c[..., :3, :3], precision=jax.lax.Precision.HIGHEST)
    new_t = jnp.einsum("...ij,...j->...i", rot, w2c[..., :3, 3],
                       precision=jax.lax.Precision.HIGHEST) + trans
    top = jnp.concatenate([new_r, new_t[..., None]], -1)
    return dataclasses.replace(cameras, world_to_camera=jnp.concatenate([top, w2c[..., 3:, :]], -2))


def scene_depth(gaussians: Gaussians, cameras: Camera) -> jax.Array:
    """Median depth of the alive Gaussians in front of each camera [B]: float [B] (else 1.0)."""
    r = jnp.asarray(cameras.world_to_camera)[:, :3, :3]
    t = jnp.asarray(cameras.world_to_camera)[:, :3, 3]
    z = jnp.einsum("bj,cj->bc", r[:, 2], gaussians.means,
                   precision=jax.lax.Precision.HIGHEST) + t[:, 2:3]
    z = jnp.where(gaussians.alive[None] & (z > 0.0), z, jnp.nan)
    med = jnp.nanmedian(z, axis=1)
    return jnp.where(jnp.isfinite(med), med, 1.0)


def _blur(images: jax.Array, sigma: jax.Array, radius: int) -> jax.Array:
    """Gaussian blur of float [B, H, W, 3] by traced ``sigma`` pixels (0: none), static radius."""
    x = jnp.arange(-radius, radius + 1, dtype=images.dtype)
    kern = jnp.exp(-0.5 * (x / jnp.maximum(sigma, 1e-3)) ** 2)
    kern = kern / kern.sum()
    pad = [(0, 0), (radius, radius), (radius, radius), (0, 0)]
    # Edge padding: a zero border would pull every view's edges towards black.
    p = jnp.pad(images, pad, mode="edge")
    h, w = images.shape[1], images.shape[2]
    rows = sum(kern[i] * p[:, i:i + h, :, :] for i in range(2 * radius + 1))
    return sum(kern[i] * rows[:, :, i:i + w, :] for i in range(2 * radius + 1))


@functools.partial(jax.jit, static_argnames=("capacity", "steps", "sh_degree", "backend", "loss",
                                             "radius"))
def _refine(gaussians, cameras, images, depth, background, lr, final_fraction, blur_px, *,
            capacity, steps, sh_degree, backend, loss, radius):
    """Adam on delta [B, 6]; returns (delta, per-view loss [steps, B], overflow [B])."""
    schedule = optax.cosine_decay_schedule(lr, steps, alpha=final_fraction)
    opt = optax.adam(schedule)
    gaussians = jax.lax.stop_gradient(gaussians)

    def loss_fn(delta, sigma):
        cams = apply_delta(cameras, delta, depth)
        out = render_tiles(gaussians, cams, capacity=capacity, background=background,
                             sh_degree=sh_degree, backend=backend)
        rgb, target = out.rgb, images
        if radius:
            rgb, target = _blur(rgb, sigma, radius), _blur(target, sigma, radius)
        diff = rgb - target
        per_view = jnp.mean(jnp.abs(diff) if loss == "l1" else diff * diff, axis=(1, 2, 3))
        # Views are independent and Adam elementwise: B separate refinements.
        return per_view.sum(), (per_view, out.overflow)

    def step(carry, i):
        delta, state, overflow = carry
        sigma = blur_px * jnp.maximum(0.0, 1.0 - 2.0 * i / steps)
        (_, (per_view, over)), grad = jax.value_and_grad(loss_fn, has_aux=True)(delta, sigma)
        updates, state = opt.update(grad, state)
        return (optax.apply_updates(delta, updates), state, overflow | over), per_view

    delta0 = jnp.zeros((len(cameras), 6), images.dtype)
    carry = (delta0, opt.init(delta0), jnp.zeros((len(cameras),), bool))
    (delta, _, overflow), losses = jax.lax.scan(step, carry, jnp.arange(steps, dtype=images.dtype))
    return delta, losses, overflow


def refine_poses(gaussians: Gaussians, cameras: Camera, images, *,
                 config: RefineConfig = RefineConfig(),
                 background=None, sh_degree: int | None = None,
                 backend: str = "auto") -> tuple[Camera, dict]:
    """Refine each camera's pose so that the frozen scene renders its image.

    Args:
      gaussians: the trained scene (capacity C); not changed.
      cameras: a batch [B] of starting cameras; images: float [B, H, W, 3] in [0, 1].
      config: :class:`RefineConfig`; background: float [3], as the scene was trained with.
      sh_degree: active SH degree (default all); backend: as :func:`jaxedit.render`'s.
    Returns:
      (cameras [B] refined, info) with ``delta`` float64 [B, 6], ``rotation_deg`` [B],
      ``translation`` [B] (scene units), ``depth`` [B] and ``loss`` float64 [steps, B].
    """
    config = config.check()
    if not cameras.batch_shape or len(cameras.batch_shape) != 1:
        raise DataError("cameras", "refine_poses needs a batch of cameras [B]")
    images = jnp.asarray(images, gaussians.means.dtype)
    want = (len(cameras), cameras.height, cameras.width, 3)
    if images.shape != want:
        raise DataError("images", f"expected shape {list(want)} for these cameras, got "
                                  f"{list(images.shape)}")
    backend = resolve_backend(backend)
    sh_degree = check_sh_degree(gaussians, sh_degree)
    bg = jnp.zeros(3, images.dtype) if background is None else jnp.asarray(background, images.dtype)
    cameras = dataclasses.replace(cameras, world_to_camera=jnp.asarray(cameras.world_to_camera,
                                                                       images.dtype))
    depth = scene_depth(gaussians, cameras)
    # The corrections are small, so the pairs counted at the start with headroom hold;
    # a view whose buffer overflowed anyway is refined again with a larger one.
    capacity = next_capacity(max(1, count_pairs(gaussians, cameras, backend=backend))
                               * config.headroom)
    radius = int(np.ceil(3.0 * config.blur_px))
    while True:
        delta, losses, overflow = _refine(
            gaussians, cameras, images, depth, bg, config.lr, config.final_lr_fraction,
            config.blur_px, capacity=capacity, steps=config.steps, sh_degree=sh_degree,
            backend=backend, loss=config.loss, radius=radius)
        if not bool(jnp.any(overflow)):
            break
        capacity = next_capacity(2 * capacity)
    refined = apply_delta(cameras, delta, depth)
    delta = np.asarray(delta, np.float64)
    depth = np.asarray(depth, np.float64)
    info = {"delta": delta, "rotation_deg": np.degrees(np.linalg.norm(delta[:, :3], axis=1)),
            "translation": np.linalg.norm(delta[:, 3:], axis=1) * depth, "depth": depth,
            "loss": np.asarray(losses, np.float64)}
    return refined, info


def _row_adam() -> optax.GradientTransformation:
    """The Adam direction of one camera's correction (the learning rate is applied outside)."""
    return optax.scale_by_adam()


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class CameraCorrections:
    """Per-view pose corrections trained with the scene (Splatfacto's camera optimizer) by
    sparse Adam: a row's moments advance only when its view is trained.

    Attributes:
      delta: float [V, 6], the corrections (V = 0 when camera optimisation is off).
      depth: float [V], each view's translation unit and pivot, fixed at init.
      adam: ``optax.scale_by_adam`` state with a leading [V] on every leaf.
    """

    delta: jax.Array
    depth: jax.Array
    adam: Any

    @property
    def num_views(self) -> int:
        return int(self.delta.shape[0])


def init_corrections(depth) -> CameraCorrections:
    """Zero corrections for ``len(depth)`` views (depth float [V], e.g. :func:`scene_depth`)."""
    depth = jnp.asarray(depth, jnp.float32).reshape(-1)
    delta = jnp.zeros((depth.shape[0], 6), jnp.float32)
    return CameraCorrections(delta=delta, depth=depth, adam=jax.vmap(_row_adam().init)(delta))


def update_correction(corr: CameraCorrections, view, grad, lr) -> CameraCorrections:
    """One sparse Adam step on row ``view`` (int32 []) with ``grad`` float [6]
    at ``lr`` (float []; 0 leaves the row and its moments unchanged)."""
    row_state = jax.tree_util.tree_map(lambda a: a[view], corr.adam)
    direction, new_state = _row_adam().update(grad, row_state)
    active = lr > 0
    row = jnp.where(active, corr.delta[view] - lr * direction, corr.delta[view])
    adam = jax.tree_util.tree_map(
        lambda a, new, old: a.at[view].set(jnp.where(active, new, old)),
        corr.adam, new_state, row_state)
    return dataclasses.replace(corr, delta=corr.delta.at[view].set(row), adam=adam)


def corrected_cameras(cameras: Camera, corr: CameraCorrections) -> Camera:
    """The training cameras [V] with their learned corrections applied."""
    if corr.num_views != len(cameras):
        raise DataError("cameras", f"{len(cameras)} cameras for {corr.num_views} learned "
                                   f"pose corrections")
    return apply_delta(cameras, corr.delta, corr.depth)


def correction_sizes(corr: CameraCorrections) -> dict:
    """Host summary of the corrections: ``rotation_deg`` and ``translation`` (scene units), [V]."""
    delta = np.asarray(corr.delta, np.float64)
    depth = np.asarray(corr.depth, np.float64)
    return {"rotation_deg": np.degrees(np.linalg.norm(delta[:, :3], axis=1)),
            "translation": np.linalg.norm(delta[:, 3:], axis=1) * depth}
