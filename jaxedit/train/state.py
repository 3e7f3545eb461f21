"""The training state (:class:`TrainState`, one pytree), its optimiser and learning-rate
schedules, and a fresh state."""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from .. import densify as dens
from .. import poses
from .. import sh as shlib
from ..camera import Camera
from ..errors import DataError
from ..gaussians import Gaussians
from ..poses import CameraCorrections
from .config import TrainConfig

_LABELS = dict(means="means", log_scales="scales", quats="quats", opacity_logits="opacity", sh="sh")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TrainState:
    """Everything a run needs to continue.

    Attributes:
      gaussians: Gaussians, capacity C.
      opt_state: optax state of :attr:`optimizer` over the parameters (the Gaussians
        without ``alive``).
      densify_stats: :class:`jaxedit.densify.DensifyStats`.
      step: int32 [], optimiser steps done.
      densify_origin: int32 [], density control sees ``step - densify_origin`` (reset at
        each subtask start).
      key: uint32 [2], the run's base PRNG key data (views and per-step keys derive from it).
      cameras: :class:`jaxedit.poses.CameraCorrections` of the V training views
        (V = 0 unless ``config.camera_opt``).
      config: TrainConfig (static).
      scene_extent: float32 [], the world size (:func:`scene_extent`); traced, so scenes
        of the same shapes share compiled programs.
      max_intersections: int (static), the tile splatter's buffer size (0: not sized yet,
        :func:`size_buffer`).
      frozen: bool [C] or None: alive Gaussians a local edit keeps as they are (no update,
        densify or opacity reset); None: every Gaussian is trained.
    """

    gaussians: Gaussians
    opt_state: Any
    densify_stats: dens.DensifyStats
    step: jax.Array
    densify_origin: jax.Array
    key: jax.Array
    cameras: CameraCorrections
    config: TrainConfig = dataclasses.field(metadata=dict(static=True))
    scene_extent: jax.Array
    max_intersections: int = dataclasses.field(metadata=dict(static=True))
    frozen: Any = None

    @property
    def capacity(self) -> int:
        return self.gaussians.capacity

    @property
    def optimizer(self) -> optax.GradientTransformationExtraArgs:
        """The optimiser of ``config`` (:func:`optimizer`, built once per config); its
        ``update`` takes ``scene_extent=``."""
        return optimizer(self.config)

    @property
    def strategy(self):
        """The density strategy of ``config.densify`` (:func:`jaxedit.densify.strategy_for`,
        built once per config); its ``update`` takes ``scene_extent=``."""
        return dens.strategy_for(self.config.densify, iterations=self.config.iterations)


class Batch(NamedTuple):
    """One training view: image float [H, W, 3] in [0, 1], its (single) Camera, and its
    index among the training views (int32 []; needed only with ``config.camera_opt``).

    ``region``: float [H, W] or None, the pixels a local edit changes; the step then also
    reports ``region_loss`` there (training is unchanged).
    """

    image: jax.Array
    camera: Camera
    view: jax.Array | None = None
    region: jax.Array | None = None


def params_of(g: Gaussians) -> Gaussians:
    """The trainable part of the Gaussians (``alive`` removed: it is not differentiable)."""
    return dataclasses.replace(g, alive=None)


def lr_schedule(lr: float, lr_final: float, steps: int, *, begin: int = 0, scale=1.0):
    """optax schedule: ``lr * scale`` at step ``begin``, decayed exponentially to
    ``lr_final * scale`` over ``steps`` steps (the one decay of every learning rate here)."""
    return optax.exponential_decay(init_value=lr * scale, transition_steps=max(steps, 1),
                                   decay_rate=lr_final / lr, transition_begin=begin,
                                   end_value=lr_final * scale)


def means_lr(config: TrainConfig, scene_extent, step):
    """float [], the means' learning rate at 0-based ``step``: ``lr_means`` to
    ``lr_means_final`` over ``iterations``, times the scene extent (INRIA)."""
    return lr_schedule(config.lr_means, config.lr_means_final, config.iterations,
                       scale=scene_extent)(step)


def _scale_by_means_lr(config: TrainConfig) -> optax.GradientTransformationExtraArgs:
    """``optax.scale_by_learning_rate(means_lr)`` with the extent given to ``update``."""
    def init(params):
        return optax.ScaleByScheduleState(count=jnp.zeros([], jnp.int32))

    def update(updates, state, params=None, *, scene_extent, **extra):
        step_size = -1 * means_lr(config, scene_extent, state.count)
        updates = jax.tree_util.tree_map(lambda g: jnp.array(step_size, dtype=g.dtype) * g,
                                         updates)
        return updates, optax.ScaleByScheduleState(count=optax.safe_increment(state.count))

    return optax.GradientTransformationExtraArgs(init, update)


@functools.lru_cache(maxsize=64)
def optimizer(config: TrainConfig) -> optax.GradientTransformationExtraArgs:
    """One Adam per attribute (``optax.partition``), Splatfacto learning rates; built once
    per config; ``update(grads, opt_state, params, scene_extent=...)``.

    The SH array holds DC and higher-order coefficients together; Adam is
    elementwise, so one Adam followed by a per-coefficient learning rate
    (DC: ``lr_sh_dc``, rest: ``lr_sh_rest``) equals two separate Adams.
    """

    def adam(lr):
        return optax.chain(optax.scale_by_adam(eps=config.adam_eps),
                           optax.scale_by_learning_rate(lr))

    k = shlib.num_coeffs(3)
    sh_lr = np.full((k, 1), config.lr_sh_rest, np.float32)
    sh_lr[0] = config.lr_sh_dc

    def sh_transform():
        def init(params):
            return optax.EmptyState()

        def update(updates, state, params=None):
            def scale(u):
                return u * -jnp.asarray(sh_lr[:u.shape[-2]], u.dtype)
            return jax.tree_util.tree_map(scale, updates), state

        return optax.chain(optax.scale_by_adam(eps=config.adam_eps),
                           optax.GradientTransformation(init, update))

    transforms = {"means": optax.chain(optax.scale_by_adam(eps=config.adam_eps),
                                       _scale_by_means_lr(config)),
                  "scales": adam(config.lr_scales),
                  "quats": adam(config.lr_quats), "opacity": adam(config.lr_opacity),
                  "sh": sh_transform()}
    labels = Gaussians(alive=None, **_LABELS)
    return optax.partition(transforms, labels)


def scene_extent(cameras: Camera) -> float:
    """INRIA's ``cameras_extent``: 1.1 x the largest camera distance from the rig centre."""
    centers = np.asarray(cameras.center(), np.float64).reshape(-1, 3)
    radius = float(np.max(np.linalg.norm(centers - centers.mean(0), axis=-1))) if len(centers) else 0.0
    return 1.1 * radius if radius > 0 else 1.0


def key_data(key) -> jax.Array:
    key = jnp.asarray(key) if not isinstance(key, jax.Array) else key
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        return jax.random.key_data(key)
    if key.shape != (2,) or key.dtype != jnp.uint32:
        raise DataError("key", f"expected a PRNG key, got {key.dtype} {tuple(key.shape)}")
    return key


def init_state(gaussians: Gaussians, config: TrainConfig, scene_extent: float, *,
               key=None, max_intersections: int | None = None,
               cameras: Camera | None = None) -> TrainState:
    """A fresh TrainState.

    Args:
      gaussians: initial Gaussians (e.g. :func:`jaxedit.gaussians.from_points`).
      config: TrainConfig.
      scene_extent: world size (see :func:`scene_extent`).
      key: the run's base PRNG key (default ``jax.random.key(0)``).
      max_intersections: tile buffer size. Default 0: not sized yet;
        :func:`fit` and :func:`step_with_retry` size it from the training views
        (:func:`size_buffer`) before the first step, then grow it on overflow.
      cameras: the training cameras [V] in the order :func:`fit` will get them;
        required with ``config.camera_opt`` (their corrections start at zero, their
        depth units from ``gaussians``), ignored otherwise.
    """
    if config.sh_degree > gaussians.sh_degree:
        raise DataError("sh_degree", f"config trains degree {config.sh_degree} but the "
                                     f"Gaussians hold degree {gaussians.sh_degree}")
    if not np.isfinite(scene_extent) or scene_extent <= 0:
        raise DataError("scene_extent", f"must be a positive number, got {scene_extent}")
    key = jax.random.key(0) if key is None else key
    tx = optimizer(config)
    strategy = dens.strategy_for(config.densify, iterations=config.iterations)
    if max_intersections is None:
        max_intersections = 0
    if config.camera_opt:
        if cameras is None or not cameras.batch_shape:
            raise DataError("cameras", "camera optimisation needs the batch of training cameras")
        depth = poses.scene_depth(gaussians, jax.tree_util.tree_map(jnp.asarray, cameras))
    else:
        depth = jnp.zeros((0,), jnp.float32)
    return TrainState(gaussians=gaussians, opt_state=tx.init(params_of(gaussians)),
                      densify_stats=strategy.init(gaussians), step=jnp.zeros((), jnp.int32),
                      densify_origin=jnp.zeros((), jnp.int32), key=key_data(key),
                      cameras=poses.init_corrections(depth), config=config,
                      scene_extent=jnp.asarray(scene_extent, jnp.float32),
                      max_intersections=int(max_intersections))
