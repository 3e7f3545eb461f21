"""Data parallelism over a mesh of devices: views sharded, Gaussians and networks replicated.

:func:`views_step` is :func:`jaxedit.train.apply_step` for V views of one replicated
scene (no density control or camera optimisation): one SPMD program, the gradient
all-reduced by XLA. Across processes :func:`shard_local_views` and :func:`fetch`
handle per-process data.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ..losses import photometric_loss
from ..raster.render import render_tiles

#: Name of the mesh axis views are sharded along (the editor's too).
VIEWS = "views"


def views_mesh(devices=None) -> Mesh:
    """A one-axis mesh over ``devices`` (default: every device JAX sees)."""
    return Mesh(np.array(list(devices) if devices is not None else jax.devices()), (VIEWS,))


def replicate(tree, mesh: Mesh):
    """``tree`` with every array copied to every device of ``mesh``."""
    return jax.device_put(tree, NamedSharding(mesh, PartitionSpec()))


def shard_views(tree, mesh: Mesh):
    """``tree``'s arrays split along their first (view) axis over ``mesh``; that axis must be
    a multiple of the mesh size."""
    return jax.device_put(tree, NamedSharding(mesh, PartitionSpec(VIEWS)))


def shard_local_views(local, mesh: Mesh):
    """Global arrays of each process's own views: ``local``'s arrays [v, ...] (this
    process's v views, the same v on every process) become [v x processes, ...] split along
    the views over ``mesh``, each process's on its devices."""
    sharding = NamedSharding(mesh, PartitionSpec(VIEWS))
    return jax.tree_util.tree_map(
        lambda x: jax.make_array_from_process_local_data(sharding, np.asarray(x)), local)


def fetch(tree):
    """``tree``'s arrays as NumPy on this process, whole: an array sharded across processes
    is all-gathered (every process must call it then), any other is read where it is."""
    from jax.experimental import multihost_utils

    def one(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable and not x.is_fully_replicated:
            return np.asarray(multihost_utils.process_allgather(x, tiled=True))
        return np.asarray(x)

    return jax.tree_util.tree_map(one, tree)


def views_loss_and_grad(state, images: jax.Array, cameras, key: jax.Array):
    """(loss, render output, gradient w.r.t. the trainable Gaussians) of V views.

    Args:
      state: :class:`jaxedit.train.TrainState`.
      images: float [V, H, W, 3] targets; cameras: batched Camera [V].
      key: the step key (a random background's colour).
    """
    from ..train import active_sh_degree, background_color, sh_mask
    from ..train.state import params_of

    cfg, g = state.config, state.gaussians
    bg = background_color(cfg, jax.random.split(key)[0])
    mask = sh_mask(active_sh_degree(state.step, cfg), g.sh.shape[-2])
    target = jnp.asarray(images, g.means.dtype)

    def loss_fn(params):
        gg = dataclasses.replace(params, alive=g.alive, sh=params.sh * mask)
        out = render_tiles(gg, cameras, capacity=state.max_intersections, background=bg)
        return photometric_loss(out.rgb, target, cfg.lambda_dssim), out

    (loss, out), grads = jax.value_and_grad(loss_fn, has_aux=True)(params_of(g))
    return loss, out, grads


def views_step(state, images: jax.Array, cameras, key: jax.Array):
    """One optimiser step on the mean loss of V views: (state, {"loss", "overflow"});
    sharded inputs and a replicated state run it data parallel."""
    from ..train.state import params_of

    loss, out, grads = views_loss_and_grad(state, images, cameras, key)
    params = params_of(state.gaussians)
    updates, opt_state = state.optimizer.update(grads, state.opt_state, params,
                                                scene_extent=state.scene_extent)
    params = optax.apply_updates(params, updates)
    new = dataclasses.replace(state, gaussians=dataclasses.replace(
        params, alive=state.gaussians.alive), opt_state=opt_state, step=state.step + 1)
    overflow = jnp.any(out.overflow)
    new = jax.tree_util.tree_map(lambda old, nw: jnp.where(overflow, old, nw), state, new)
    return new, {"loss": loss, "overflow": overflow}


views_step_jit = jax.jit(views_step)
views_loss_and_grad_jit = jax.jit(views_loss_and_grad)
