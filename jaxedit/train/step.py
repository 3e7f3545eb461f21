"""One optimisation step: render a view, 0.8 L1 + 0.2 D-SSIM, Adam, density control.

:func:`apply_step` is the pure step (to trace inside a caller's jit or scan);
:func:`train_step` is it jitted. A step never returns a half-applied state: on a
tile-buffer overflow or too few slots it returns its *input* state with
``metrics["redo"]`` set (:mod:`jaxedit.train.room`). No float32 dot runs at DEFAULT
precision, which is TF32 on NVIDIA GPUs and makes training diverge.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import optax

from .. import densify as dens
from .. import poses
from ..errors import DataError
from ..gaussians import Gaussians
from ..losses import photometric_loss
from ..raster.render import render_tiles
from .config import TrainConfig
from .state import Batch, TrainState, lr_schedule, means_lr, params_of

def active_sh_degree(step, config: TrainConfig) -> jax.Array:
    """int32 [], SH degree in use at 0-based ``step``: one more every ``sh_degree_interval``."""
    return jnp.minimum(jnp.asarray(step, jnp.int32) // config.sh_degree_interval,
                       config.sh_degree)


def sh_mask(degree, num_coeffs: int) -> jax.Array:
    """float [K, 1]: 1 for the coefficients of degrees <= ``degree``, else 0.

    Masking (instead of a lower static degree) keeps one compiled step for the
    whole run; masked coefficients get zero gradient, so Adam leaves them at 0.
    """
    k = jnp.arange(num_coeffs)
    return (k < (jnp.asarray(degree) + 1) ** 2).astype(jnp.float32)[:, None]


def background_color(config: TrainConfig, key) -> jax.Array:
    """float [3], the background of a training render."""
    if config.background == "random":
        return jax.random.uniform(key, (3,))
    return jnp.full((3,), 1.0 if config.background == "white" else 0.0)


def psnr_from_mse(mse):
    return -10.0 * jnp.log10(jnp.maximum(mse, 1e-12))


def apply_step(state: TrainState, batch: Batch, key) -> tuple[TrainState, dict]:
    """One optimisation step on one view, pure and not jitted (see :data:`train_step`)."""
    cfg = state.config
    g = state.gaussians
    k_bg, k_dens = jax.random.split(key)
    bg = background_color(cfg, k_bg)
    mask = sh_mask(active_sh_degree(state.step, cfg), g.sh.shape[-2])
    target = jnp.asarray(batch.image, g.means.dtype)
    corr = state.cameras
    # A static branch: without camera optimisation the step has no pose terms at all.
    learn_pose = corr.num_views > 0
    if learn_pose and batch.view is None:
        raise DataError("batch", "camera optimisation needs the view index of every batch")
    view = batch.view if learn_pose else None

    def loss_fn(params, delta, pose):
        gg = dataclasses.replace(params, alive=g.alive, sh=params.sh * mask)
        cam = batch.camera
        if learn_pose:
            cam = poses.apply_delta(cam, pose, corr.depth[view])
        out = render_tiles(gg, cam, capacity=state.max_intersections, background=bg,
                           means2d_delta=delta)
        return photometric_loss(out.rgb, target, cfg.lambda_dssim), out

    params = params_of(g)
    frozen = state.frozen  # None: a static branch, the step is as before local edits
    delta = jnp.zeros((g.capacity, 2), g.means.dtype)
    pose = corr.delta[view] if learn_pose else jnp.zeros((6,), g.means.dtype)
    (loss, out), (grads, grad2d, grad_pose) = jax.value_and_grad(
        loss_fn, argnums=(0, 1, 2), has_aux=True)(params, delta, pose)
    if learn_pose:
        corr = poses.update_correction(corr, view, grad_pose, camera_lr(cfg, state.step))
    if frozen is not None:
        grads = keep_rows(frozen, jax.tree_util.tree_map(jnp.zeros_like, grads), grads)
    updates, opt_state = state.optimizer.update(grads, state.opt_state, params,
                                                scene_extent=state.scene_extent)
    if frozen is not None:  # bit-identical: Adam's moments alone would still move them
        params = keep_rows(frozen, params, optax.apply_updates(params, updates))
    else:
        params = optax.apply_updates(params, updates)
    g1 = dataclasses.replace(params, alive=g.alive)

    step = state.step + 1
    aux = dens.render_aux(grad2d, out, batch.camera.width, batch.camera.height)
    g2, opt_state, stats, info = state.strategy.update(
        g1, opt_state, state.densify_stats, aux, step - state.densify_origin, k_dens,
        frozen=frozen, scene_extent=state.scene_extent)
    new = dataclasses.replace(state, gaussians=g2, opt_state=opt_state, densify_stats=stats,
                              step=step, cameras=corr)
    redo = out.overflow | info.capacity_limited
    # A step that must be redone leaves the state untouched (never half-applied).
    new = jax.tree_util.tree_map(lambda old, nw: jnp.where(redo, old, nw), state, new)
    mse = jnp.mean((out.rgb - target) ** 2)
    metrics = dict(loss=loss, psnr=psnr_from_mse(mse), num_gaussians=info.alive,
                   finite=_finite_fields(g2, loss),
                   overflow=out.overflow, num_intersections=out.num_intersections,
                   capacity_limited=info.capacity_limited, redo=redo,
                   sh_degree=active_sh_degree(state.step, cfg),
                   lr_means=means_lr(cfg, state.scene_extent, state.step),
                   densify=info._asdict())
    if batch.region is not None:  # a static branch: only a local edit's chunk passes one
        metrics["region_loss"] = photometric_loss(out.rgb, target, cfg.lambda_dssim,
                                                  weight=batch.region)
    return new, metrics


def keep_rows(rows, old, new):
    """``new`` with the slots of ``rows`` (bool [C]) taken from ``old``, leaf by leaf
    (pytrees of [C, ...] arrays, e.g. Gaussians or their gradients)."""
    def pick(a, b):
        return jnp.where(rows.reshape(rows.shape + (1,) * (a.ndim - 1)), a, b)

    return jax.tree_util.tree_map(pick, old, new)


#: Fields checked by the divergence guard, in the order its message names them.
GUARDED = ("loss", "means", "log_scales", "quats", "opacity_logits", "sh")


def _finite_fields(g: Gaussians, loss) -> dict:
    """bool [] per :data:`GUARDED` quantity: the loss, and each parameter over the alive slots."""
    out = {"loss": jnp.isfinite(loss)}
    for name in GUARDED[1:]:
        a = getattr(g, name)
        ok = jnp.isfinite(a).reshape(a.shape[0], -1).all(-1)
        out[name] = jnp.all(ok | ~g.alive)
    return out


def camera_lr(cfg: TrainConfig, step):
    """float [], the pose corrections' learning rate at 0-based ``step``: ``lr_camera`` to
    ``lr_camera_final`` from ``camera_opt_from`` to ``iterations`` (0 before)."""
    lr = lr_schedule(cfg.lr_camera, cfg.lr_camera_final, cfg.iterations - cfg.camera_opt_from,
                     begin=cfg.camera_opt_from)(step)
    return jnp.where(step >= cfg.camera_opt_from, lr, 0.0)


train_step = jax.jit(apply_step)
train_step.__doc__ = """One optimisation step on one view (pure, jitted).

Args:
  state: TrainState.
  batch: Batch(image float [H, W, 3], camera: a single Camera).
  key: PRNG key of this step (random background, split children).
Returns:
  (state, metrics): metrics is a dict of scalars -- loss, psnr (of this view),
  num_gaussians, overflow, num_intersections, capacity_limited, redo, sh_degree,
  lr_means, and ``densify`` (the :class:`jaxedit.densify.DensifyInfo` fields).
  When ``metrics["redo"]`` is True the returned state IS the input state: grow
  with :func:`jaxedit.train.grow_for_redo` and call again (or use
  :func:`jaxedit.train.step_with_retry`).
"""
