"""3DGS training: a pure, jit-compiled train step, a resumable fit loop, checkpoints.

The pieces, from the inside out:

* :class:`TrainConfig` (with :class:`jaxedit.densify.DensifyConfig`): every hyper-parameter,
  Splatfacto defaults, JSON-serialisable (it is stored in checkpoints).
* :class:`TrainState`: the whole training state as one pytree -- Gaussians,
  optax state (one Adam per attribute through ``optax.partition``), densify
  statistics, the step count and the run's base PRNG key. The config, the scene
  extent and the intersection-buffer size are static fields: changing them
  recompiles, and they travel with the state into checkpoints.
* :func:`train_step` ``(state, batch, key) -> (state, metrics)``: render one
  view, 0.8 L1 + 0.2 D-SSIM, Adam, then density control. Pure and jitted.
  It never silently returns a bad step: when the tile splatter's intersection
  buffer overflowed, or density control needed more slots than the capacity
  has (while the hard cap allows more), it returns the *input* state unchanged
  with ``metrics["redo"]`` set; :func:`step_with_retry` (used by :func:`fit`)
  grows the buffer / capacity outside jit and redoes the step -- one recompile,
  logged, and the same result as if the room had been there from the start.
* :func:`train_chunk`: up to ``length`` steps in one compiled ``lax.scan``; the
  views are picked from the device-resident images on the device, and the
  metrics come back stacked, so there is no host round trip per step.
* :func:`fit`: the loop over chunks; between them the host logs, checkpoints,
  grows the buffer / capacity after a redo, and runs the divergence guard
  (:func:`divergence`: a non-finite loss or parameter, or an exploding loss,
  stops the run with a DataError naming the step). The view of step ``s`` and
  its PRNG key are pure functions of ``(base key, s)`` (a seeded permutation
  per epoch), so a run resumed from any checkpoint ends with bit-identical
  Gaussians, whatever the chunking.

Numerics: no float32 dot in the step runs at DEFAULT precision (on NVIDIA GPUs
that is TF32, a 10-bit mantissa, which made training diverge there, issue #18);
``tests/test_backbone.py`` checks it with :mod:`jaxedit.tf32`.

The ProEdit driver can swap the ``images`` array between :func:`fit` calls (the
edited dataset; :func:`put_image` updates one view of a device array in place),
stop early with ``should_stop(step, loss_history)``, or run its own loop around
:func:`select_batch` + :func:`step_with_retry`.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import math
import os
import time
from pathlib import Path
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from . import densify as dens
from . import gaussians as glib
from . import poses
from . import sh as shlib
from .camera import Camera
from .densify import DensifyConfig
from .errors import DataError
from .gaussians import Gaussians
from .io.files import atomic_path
from .losses import photometric_loss
from .poses import CameraCorrections
from .raster import render
from .raster.render import next_capacity, render_tiles

log = logging.getLogger(__name__)

BACKGROUNDS = ("random", "white", "black")
CHECKPOINT_VERSION = 1


# --------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Training hyper-parameters (defaults: nerfstudio Splatfacto / INRIA 3DGS).

    Attributes:
      iterations: optimiser steps of the run (one view per step).
      lr_means, lr_means_final: means learning rate, decayed exponentially from
        the first to the second over ``iterations`` steps, both multiplied by the
        scene extent (INRIA).
      lr_sh_dc, lr_sh_rest, lr_opacity, lr_scales, lr_quats: Adam learning rates.
      adam_eps: Adam epsilon (1e-15: tiny, as in 3DGS).
      lambda_dssim: loss = (1 - l) L1 + l (1 - SSIM).
      sh_degree: largest SH degree trained (<= the Gaussians'); one degree is
        switched on every ``sh_degree_interval`` steps, starting at 0.
      background: "random" (a uniform colour per step), "white" or "black";
        the colour behind the Gaussians in training renders.
      densify: :class:`DensifyConfig`.
      camera_opt: learn a 6-DoF pose correction per training view with the scene
        (Splatfacto's camera optimizer, gsplat's ``pose_opt``): for poses estimated
        by structure from motion, whose residual errors (~0.4 degree, 1-2 px) the
        Gaussians would otherwise blur over. See :class:`jaxedit.poses.CameraCorrections`.
      lr_camera, lr_camera_final: its learning rate (radians, and the translation in
        units of the view's scene depth, see :func:`jaxedit.poses.apply_delta`), decayed
        exponentially from the first to the second between ``camera_opt_from`` and
        ``iterations``.
      camera_opt_from: the step the corrections start to move: before it the scene is
        too blurred for its photometric gradient to say where a camera points.
    """

    iterations: int = 30_000
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    adam_eps: float = 1e-15
    lambda_dssim: float = 0.2
    sh_degree: int = 3
    sh_degree_interval: int = 1000
    background: str = "white"
    densify: DensifyConfig = DensifyConfig()
    camera_opt: bool = False
    lr_camera: float = 1e-3
    lr_camera_final: float = 1e-5
    camera_opt_from: int = 500

    def __post_init__(self):
        if self.background not in BACKGROUNDS:
            raise DataError("background", f"must be one of {BACKGROUNDS}, got {self.background!r}")
        if self.iterations < 0:
            raise DataError("iterations", f"must be >= 0, got {self.iterations}")
        if not 0 <= self.sh_degree <= 3:
            raise DataError("sh_degree", f"must be in 0..3, got {self.sh_degree}")
        if self.sh_degree_interval <= 0:
            raise DataError("sh_degree_interval", "must be positive")
        if not 0.0 <= self.lambda_dssim <= 1.0:
            raise DataError("lambda_dssim", f"must be in [0, 1], got {self.lambda_dssim}")
        if not (self.lr_camera > 0 and 0 < self.lr_camera_final <= self.lr_camera):
            raise DataError("lr_camera", f"need 0 < lr_camera_final <= lr_camera, got "
                                         f"{self.lr_camera_final}, {self.lr_camera}")
        if self.camera_opt_from < 0:
            raise DataError("camera_opt_from", f"must be >= 0, got {self.camera_opt_from}")
        if isinstance(self.densify, dict):
            object.__setattr__(self, "densify", _densify_from_dict(self.densify))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict, where: str = "config") -> "TrainConfig":
        _check_fields(cls, data, where, "train config")
        data = dict(data)
        if "densify" in data:
            data["densify"] = _densify_from_dict(data["densify"], f"{where}.densify")
        return cls(**data)


def _densify_from_dict(data, where: str = "densify") -> DensifyConfig:
    if isinstance(data, DensifyConfig):
        return data
    _check_fields(DensifyConfig, data, where, "densify")
    return DensifyConfig(**data)


def _check_fields(cls, data, where: str, what: str) -> None:
    """DataError unless ``data`` is a dict whose keys are all fields of dataclass ``cls``."""
    if not isinstance(data, dict):
        raise DataError(where, f"{what} must be an object")
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise DataError(where, f"unknown {what} field(s) {', '.join(unknown)}")


# --------------------------------------------------------------------------------------
# State
# --------------------------------------------------------------------------------------

_LABELS = dict(means="means", log_scales="scales", quats="quats", opacity_logits="opacity", sh="sh")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TrainState:
    """Everything a run needs to continue.

    Attributes:
      gaussians: Gaussians, capacity C.
      opt_state: optax state of ``optimizer(config, extent)`` over the
        parameters (the Gaussians without ``alive``).
      densify_stats: :class:`jaxedit.densify.DensifyStats`.
      step: int32 [], optimiser steps done.
      densify_origin: int32 [], density control sees ``step - densify_origin``
        (the ProEdit driver sets it at each subtask start so that warm-up counts
        from there).
      key: uint32 [2], the run's base PRNG key data (views and per-step keys derive from it).
      cameras: :class:`jaxedit.poses.CameraCorrections` of the V training views
        (V = 0 unless ``config.camera_opt``).
      config: TrainConfig (static).
      scene_extent: float (static).
      max_intersections: int (static), the tile splatter's buffer size (0: not
        sized yet, see :func:`size_buffer`). Every step pays for the whole buffer
        (it is sorted), so it is measured rather than guessed.
    """

    gaussians: Gaussians
    opt_state: Any
    densify_stats: dens.DensifyStats
    step: jax.Array
    densify_origin: jax.Array
    key: jax.Array
    cameras: CameraCorrections
    config: TrainConfig = dataclasses.field(metadata=dict(static=True))
    scene_extent: float = dataclasses.field(metadata=dict(static=True))
    max_intersections: int = dataclasses.field(metadata=dict(static=True))

    @property
    def capacity(self) -> int:
        return self.gaussians.capacity


class Batch(NamedTuple):
    """One training view: image float [H, W, 3] in [0, 1], its (single) Camera, and its
    index among the training views (int32 []; needed only with ``config.camera_opt``)."""

    image: jax.Array
    camera: Camera
    view: jax.Array | None = None


def _params(g: Gaussians) -> Gaussians:
    """The trainable part of the Gaussians (``alive`` removed: it is not differentiable)."""
    return dataclasses.replace(g, alive=None)


def optimizer(config: TrainConfig, scene_extent: float) -> optax.GradientTransformation:
    """One Adam per attribute (``optax.partition``), Splatfacto learning rates.

    The SH array holds DC and higher-order coefficients together; Adam is
    elementwise, so one Adam followed by a per-coefficient learning rate
    (DC: ``lr_sh_dc``, rest: ``lr_sh_rest``) equals two separate Adams.
    """

    def adam(lr):
        return optax.chain(optax.scale_by_adam(eps=config.adam_eps),
                           optax.scale_by_learning_rate(lr))

    means_lr = optax.exponential_decay(
        init_value=config.lr_means * scene_extent, transition_steps=max(config.iterations, 1),
        decay_rate=config.lr_means_final / config.lr_means,
        end_value=config.lr_means_final * scene_extent)
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

    transforms = {"means": adam(means_lr), "scales": adam(config.lr_scales),
                  "quats": adam(config.lr_quats), "opacity": adam(config.lr_opacity),
                  "sh": sh_transform()}
    labels = Gaussians(alive=None, **_LABELS)
    return optax.partition(transforms, labels)


def scene_extent(cameras: Camera) -> float:
    """INRIA's ``cameras_extent``: 1.1 x the largest camera distance from the rig centre."""
    centers = np.asarray(cameras.center(), np.float64).reshape(-1, 3)
    radius = float(np.max(np.linalg.norm(centers - centers.mean(0), axis=-1))) if len(centers) else 0.0
    return 1.1 * radius if radius > 0 else 1.0


def _key_data(key) -> jax.Array:
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
    tx = optimizer(config, scene_extent)
    strategy = dens.adaptive(config.densify, scene_extent=scene_extent,
                             iterations=config.iterations)
    if max_intersections is None:
        max_intersections = 0
    if config.camera_opt:
        if cameras is None or not cameras.batch_shape:
            raise DataError("cameras", "camera optimisation needs the batch of training cameras")
        depth = poses.scene_depth(gaussians, jax.tree_util.tree_map(jnp.asarray, cameras))
    else:
        depth = jnp.zeros((0,), jnp.float32)
    return TrainState(gaussians=gaussians, opt_state=tx.init(_params(gaussians)),
                      densify_stats=strategy.init(gaussians), step=jnp.zeros((), jnp.int32),
                      densify_origin=jnp.zeros((), jnp.int32), key=_key_data(key),
                      cameras=poses.init_corrections(depth), config=config,
                      scene_extent=float(scene_extent),
                      max_intersections=int(max_intersections))


# --------------------------------------------------------------------------------------
# The step
# --------------------------------------------------------------------------------------

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


def _train_step(state: TrainState, batch: Batch, key) -> tuple[TrainState, dict]:
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

    params = _params(g)
    delta = jnp.zeros((g.capacity, 2), g.means.dtype)
    pose = corr.delta[view] if learn_pose else jnp.zeros((6,), g.means.dtype)
    (loss, out), (grads, grad2d, grad_pose) = jax.value_and_grad(
        loss_fn, argnums=(0, 1, 2), has_aux=True)(params, delta, pose)
    if learn_pose:
        corr = poses.update_correction(corr, view, grad_pose, _camera_lr(cfg, state.step))
    tx = optimizer(cfg, state.scene_extent)
    updates, opt_state = tx.update(grads, state.opt_state, params)
    params = optax.apply_updates(params, updates)
    g1 = dataclasses.replace(params, alive=g.alive)

    step = state.step + 1
    strategy = dens.adaptive(cfg.densify, scene_extent=state.scene_extent,
                             iterations=cfg.iterations)
    aux = dens.render_aux(grad2d, out, batch.camera.width, batch.camera.height)
    g2, opt_state, stats, info = strategy.update(g1, opt_state, state.densify_stats, aux,
                                                 step - state.densify_origin, k_dens)
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
                   lr_means=_means_lr(cfg, state.scene_extent, state.step),
                   densify=info._asdict())
    return new, metrics


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


def _camera_lr(cfg: TrainConfig, step):
    """float [], the pose corrections' learning rate at 0-based ``step`` (0 before
    ``camera_opt_from``)."""
    span = max(cfg.iterations - cfg.camera_opt_from, 1)
    frac = jnp.clip((jnp.asarray(step, jnp.float32) - cfg.camera_opt_from) / span, 0.0, 1.0)
    lr = cfg.lr_camera * (cfg.lr_camera_final / cfg.lr_camera) ** frac
    return jnp.where(step >= cfg.camera_opt_from, lr, 0.0)


def _means_lr(cfg: TrainConfig, extent: float, step):
    rate = cfg.lr_means_final / cfg.lr_means
    frac = jnp.minimum(jnp.asarray(step, jnp.float32) / max(cfg.iterations, 1), 1.0)
    return cfg.lr_means * extent * rate ** frac


train_step = jax.jit(_train_step)
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
  with :func:`grow_for_redo` and call again (or use :func:`step_with_retry`).
"""


@functools.partial(jax.jit, static_argnames=("tile",))
def _count_views(gaussians: Gaussians, cameras: Camera, tile: int):
    from .raster import binning, project

    def one(cam):
        proj = project.project(gaussians, cam, sh_degree=0)
        return binning.count_intersections(proj, cam.width, cam.height, tile)

    return jax.lax.map(one, cameras)


def measure_intersections(gaussians: Gaussians, cameras: Camera) -> int:
    """Most tile intersections any of ``cameras`` (a batch, or one camera) needs, counted at
    the tile size of the compositor the training step renders with (``backend="auto"``)."""
    from .raster.render import resolve_backend, tile_size

    if not cameras.batch_shape:
        cameras = jax.tree_util.tree_map(lambda a: jnp.asarray(a)[None], cameras)
    tile = tile_size(resolve_backend("auto"))
    return int(jnp.max(_count_views(gaussians, cameras, tile=tile)))


def size_buffer(state: TrainState, cameras: Camera, *, headroom: float = 1.5) -> TrainState:
    """``state`` with a tile buffer of ``headroom`` x what the views need now (outside jit).

    Training grows the scene, hence the headroom; when it is not enough the step
    overflows and is redone with a larger buffer (:func:`grow_for_redo`).
    """
    needed = measure_intersections(state.gaussians, cameras)
    cap = next_capacity(max(int(needed * headroom), 1))
    log.info("train: intersection buffer %d (views need up to %d)", cap, needed)
    return dataclasses.replace(state, max_intersections=cap)


def grow_for_redo(state: TrainState, metrics: dict) -> TrainState:
    """After a step that asked for a redo: a larger intersection buffer and/or capacity.

    Outside jit. The buffer at least doubles (and holds what the frame needed);
    the capacity doubles until it holds what density control needed, clamped to
    the hard cap. Logged (each costs one recompile).
    """
    if bool(metrics["overflow"]):
        needed = int(np.max(np.asarray(metrics["num_intersections"])))
        # Training grows the scene, so leave room (each size is one more compile).
        new = max(2 * state.max_intersections, next_capacity(int(needed * 1.5)))
        log.info("train: intersection buffer %d -> %d (a view needed %d)",
                 state.max_intersections, new, needed)
        state = dataclasses.replace(state, max_intersections=new)
    if bool(metrics["capacity_limited"]):
        needed = int(metrics["densify"]["slots_needed"])
        cap = state.config.densify.max_gaussians
        # Room for the next maintenance steps too: each growth is one more compile.
        new_cap = dens.grown_capacity(state.capacity, GROWTH_ROOM * needed, cap)
        if new_cap <= state.capacity:
            raise RuntimeError(f"capacity {state.capacity} cannot grow to hold {needed}")
        log.info("train: capacity %d -> %d Gaussians (density control needed %d, cap %d)",
                 state.capacity, new_cap, needed, cap)
        g, opt_state, stats = dens.grow_state(state.gaussians, state.opt_state,
                                               state.densify_stats, new_cap)
        state = dataclasses.replace(state, gaussians=g, opt_state=opt_state, densify_stats=stats)
    return state


#: On a capacity redo, the capacity grows to hold this many times the slots the step needed.
GROWTH_ROOM = 2

#: The capacity :func:`fit` gives a fresh run that will densify on a GPU, as a multiple
#: of its alive Gaussians (within ``max_gaussians``): see :func:`plan_room`.
ROOM = 4.0


def default_room(platform: str | None = None) -> float | None:
    """:func:`fit`'s ``room`` on ``platform`` (default: JAX's default backend).

    A dead slot still costs its share of every step's per-Gaussian passes
    (projection, Adam, the statistics): on a GPU nothing measurable, on a CPU
    about 1 ms per 1000 slots and step at 64 px (benchmarks/train_loop.py), more
    than the compiles it saves over a run. So: :data:`ROOM` on a GPU, on-demand
    growth (None) elsewhere.
    """
    return ROOM if (platform or jax.default_backend()) == "gpu" else None


def planned_capacity(state: TrainState, room: float | None) -> int:
    """The capacity :func:`plan_room` gives ``state`` (never less than it has)."""
    d = state.config.densify
    stop_at = d.stop_at if d.stop_at is not None else state.config.iterations // 2
    if room is None or room <= 1 or not d.enabled or int(state.step) >= stop_at:
        return state.capacity
    want = int(math.ceil(room * int(state.gaussians.num_alive()) / 1024.0)) * 1024
    return max(state.capacity, min(want, int(d.max_gaussians)))


def plan_room(state: TrainState, room: float | None = ROOM) -> TrainState:
    """``state`` with the room a densifying run will need, allocated before its first step.

    Density control runs inside the compiled chunk and only flips ``alive`` bits,
    but when it needs more slots than the capacity has, the chunk ends, the host
    grows the capacity and the chunk recompiles (seconds on a CPU, more with the
    GPU's kernels): the host stop that made end-to-end training several times
    slower than its steady state. Giving a fresh run ``room`` x its alive
    Gaussians up front makes those stops rare; the unused slots are dead and cost
    little per step. Outside jit. The capacity is part of the state (and of its
    checkpoints), so :func:`fit` plans only at step 0 and a resumed run keeps
    the capacity it had: resume stays bit-exact.
    """
    new_cap = planned_capacity(state, room)
    if new_cap <= state.capacity:
        return state
    log.info("train: capacity %d -> %d Gaussians (room planned for density control)",
             state.capacity, new_cap)
    g, opt_state, stats = dens.grow_state(state.gaussians, state.opt_state,
                                           state.densify_stats, new_cap)
    return dataclasses.replace(state, gaussians=g, opt_state=opt_state, densify_stats=stats)


def step_with_retry(state: TrainState, batch: Batch, key, *, max_retries: int = 8):
    """:func:`train_step`, growing buffer/capacity and redoing until the step is complete.

    Returns:
      (state, metrics) with ``metrics`` pulled to the host (NumPy scalars).
    """
    if state.max_intersections <= 0:
        state = size_buffer(state, batch.camera)
    for _ in range(max_retries + 1):
        new, metrics = train_step(state, batch, key)
        metrics = jax.device_get(metrics)
        if not bool(metrics["redo"]):
            return new, metrics
        state = grow_for_redo(state, metrics)
    raise RuntimeError(f"train step still incomplete after {max_retries} retries")


# --------------------------------------------------------------------------------------
# Data order
# --------------------------------------------------------------------------------------

def _stream_keys(base_data):
    base = jax.random.wrap_key_data(base_data)
    return jax.random.fold_in(base, 0), jax.random.fold_in(base, 1)


def _view_and_key(base_key_data, step, num_views: int):
    k_views, k_steps = _stream_keys(base_key_data)
    epoch, i = step // num_views, step % num_views
    view = jax.random.permutation(jax.random.fold_in(k_views, epoch), num_views)[i]
    return view.astype(jnp.int32), jax.random.fold_in(k_steps, step)


view_and_key = jax.jit(_view_and_key, static_argnums=2)
view_and_key.__doc__ = """(view index int32 [], step key) of 0-based ``step`` among ``num_views`` (static).

A pure function of (base key data uint32 [2], step): the views follow a fresh
seeded permutation every epoch of ``num_views`` steps.
"""


@jax.jit
def _select(images, cameras, base_key_data, step):
    view, key = _view_and_key(base_key_data, step, images.shape[0])
    return Batch(image=images[view], camera=cameras[view], view=view), key


def select_batch(images, cameras: Camera, base_key_data, step) -> tuple[Batch, jax.Array]:
    """(Batch of 0-based ``step``, its key) from images [N, H, W, 3] and cameras [N].

    The view is the ``step % N``-th entry of a seeded permutation of epoch ``step // N``.
    """
    return _select(jnp.asarray(images), cameras, jnp.asarray(base_key_data),
                   jnp.asarray(step, jnp.int32))


# --------------------------------------------------------------------------------------
# Chunks of steps on the device
# --------------------------------------------------------------------------------------

#: Steps per compiled chunk in :func:`fit` (the host acts only between chunks).
CHUNK = 16


def scan_steps(step, carry, n_active, *, length: int, after=None):
    """Up to ``length`` steps of ``step`` in one ``lax.scan``, ending early on a redo or a stop.

    Step ``i`` runs when ``i < n_active`` and no earlier step of the chunk asked
    for a redo or a stop; the others are skipped (``lax.cond``) with blank
    metrics, so one compiled chunk serves every count. A step that asks for a
    redo must leave its carry as it was (see :func:`train_step`), so the
    returned carry is the one after the completed steps.

    Args:
      step: ``(carry, i) -> (carry, metrics)``, ``i`` int32 [] the index in the
        chunk; ``metrics`` is a dict of arrays holding a bool ``redo``.
      carry: the pytree the steps advance.
      n_active: int32 [], steps wanted (<= ``length``).
      length: static scan length.
      after: optional ``(carry, metrics, i) -> (metrics, stop)``, evaluated after
        every index: extends the metrics and says whether the chunk ends after
        this step (e.g. a loss plateau); its stop counts only for a step that ran.
    Returns:
      (carry, metrics): the metrics stacked over the chunk ([length] each) plus
      ``ran`` (bool [length]: the step was attempted); a completed step has
      ``ran & ~redo``.
    """
    blank = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype),
                                   jax.eval_shape(step, carry, jnp.zeros((), jnp.int32))[1])

    def body(state, i):
        inner, stopped = state
        run = (i < n_active) & ~stopped
        inner, metrics = jax.lax.cond(run, step, lambda c, _: (c, blank), inner, i)
        stop = metrics["redo"]
        if after is not None:
            metrics, extra_stop = after(inner, metrics, i)
            stop = stop | extra_stop
        return (inner, stopped | (run & stop)), dict(metrics, ran=run)

    (carry, _), metrics = jax.lax.scan(body, (carry, jnp.zeros((), bool)),
                                       jnp.arange(length, dtype=jnp.int32))
    return carry, metrics


def _train_chunk(state: TrainState, images, cameras: Camera, n_active, *, length: int):
    """Up to ``length`` train steps in one ``lax.scan`` (:func:`scan_steps`), views and keys
    chosen on the device.

    Args:
      state: TrainState.
      images: float [N, H, W, 3] training images (on the device).
      cameras: Camera batch [N].
      n_active: int32 [], steps wanted (<= ``length``).
      length: static scan length.
    Returns:
      (state, metrics): :func:`train_step`'s metrics stacked over the chunk
      ([length] each) plus ``ran``; a completed step has ``ran & ~redo``.
    """
    num_views = images.shape[0]

    def one(st, _):
        view, key = _view_and_key(st.key, st.step, num_views)
        return _train_step(st, Batch(image=images[view], camera=cameras[view], view=view), key)

    return scan_steps(one, state, n_active, length=length)


train_chunk = jax.jit(_train_chunk, static_argnames=("length",))


def put_image(images: jax.Array, index, image) -> jax.Array:
    """``images`` [N, H, W, 3] with view ``index`` replaced by ``image`` [H, W, 3], in place.

    The buffer is donated, so an edited view lands in the device-resident
    training set without copying the other views (where the platform supports
    donation; elsewhere it is a copy, with the same result).
    """
    return _put_image(images, jnp.asarray(index, jnp.int32), jnp.asarray(image, images.dtype))


@functools.partial(jax.jit, donate_argnums=0)
def _put_image(images, index, image):
    return images.at[index].set(image)


#: Steps averaged by the divergence guard's loss rule.
GUARD_WINDOW = 16


def divergence(step0: int, metrics: dict, *, history=None, max_loss: float | None = 0.75,
               window: int = GUARD_WINDOW) -> str | None:
    """Why the steps of a chunk diverged, or None (host side, on fetched metrics).

    Args:
      step0: the step count before the chunk.
      metrics: per-step metrics of the chunk's completed steps (NumPy, [n]).
      history: the run's losses so far, this chunk's included (default: the chunk's).
      max_loss: the loss averaged over the last ``window`` steps may not exceed
        this. A photometric loss is at most ~1.2 (L1 <= 1, 1 - SSIM <= 2); an
        untrained scene sits near 0.3-0.4 and an opacity reset returns there, a
        render unrelated to its target (the GPU failure of issue #18) at ~1.
      window: steps averaged by the loss rule.
    Returns:
      a one-line reason naming the first bad step and quantity.
    """
    finite = metrics["finite"]
    for i in range(len(metrics["loss"])):
        for name in GUARDED:
            if not bool(finite[name][i]):
                what = "the loss" if name == "loss" else f"parameter {name}"
                return f"step {step0 + i + 1}: training diverged: {what} is not finite"
    n = len(metrics["loss"])
    losses = np.asarray(metrics["loss"] if history is None else history, np.float64)
    if max_loss is not None and n:
        recent = losses[-window:]
        if len(recent) >= min(window, 4) and recent.mean() > max_loss:
            return (f"step {step0 + n}: training diverged: the loss averaged "
                    f"{recent.mean():.3g} over {len(recent)} steps (more than {max_loss})")
    return None


# --------------------------------------------------------------------------------------
# Checkpoints
# --------------------------------------------------------------------------------------

def _leaf_paths(state: TrainState) -> list[str]:
    return [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_flatten_with_path(state)[0]]


def save_checkpoint(path, state: TrainState, *, extra: dict | None = None) -> Path:
    """Write ``state`` to ``path`` (.npz) atomically: every leaf plus the static fields.

    ``extra`` (JSON-serialisable) is stored alongside and returned by
    :func:`load_checkpoint_with_extra`.
    """
    path = Path(path)
    leaves = jax.tree_util.tree_leaves(jax.device_get(state))
    meta = dict(version=CHECKPOINT_VERSION, config=state.config.to_dict(),
                scene_extent=state.scene_extent, max_intersections=state.max_intersections,
                capacity=state.capacity, sh_degree=state.gaussians.sh_degree,
                step=int(state.step), num_views=state.cameras.num_views,
                paths=_leaf_paths(state), extra=extra or {})
    arrays = {f"leaf_{i:04d}": np.asarray(a) for i, a in enumerate(leaves)}
    arrays["meta"] = np.asarray(json.dumps(meta))
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
    return path


def load_checkpoint_with_extra(path) -> tuple[TrainState, dict]:
    """(TrainState, extra) from a checkpoint written by :func:`save_checkpoint`."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError) as e:
        raise DataError(path, f"cannot read checkpoint ({e})") from None
    if "meta" not in arrays:
        raise DataError(path, "not a jaxedit checkpoint (no meta record)")
    try:
        meta = json.loads(str(arrays["meta"]))
    except json.JSONDecodeError as e:
        raise DataError(path, f"corrupt checkpoint metadata ({e})") from None
    if meta.get("version") != CHECKPOINT_VERSION:
        raise DataError(path, f"checkpoint version {meta.get('version')} is not "
                              f"{CHECKPOINT_VERSION}")
    config = TrainConfig.from_dict(meta["config"], f"{path}:config")
    template = init_state(glib.empty(int(meta["capacity"]), int(meta["sh_degree"])),
                          dataclasses.replace(config, camera_opt=False),
                          float(meta["scene_extent"]), key=jax.random.key(0),
                          max_intersections=int(meta["max_intersections"]))
    template = dataclasses.replace(template, config=config, cameras=poses.init_corrections(
        jnp.ones((int(meta.get("num_views", 0)),), jnp.float32)))
    leaves, treedef = jax.tree_util.tree_flatten(template)
    if _leaf_paths(template) != meta["paths"]:
        raise DataError(path, "checkpoint layout does not match this jaxedit version's TrainState")
    loaded = []
    for i, ref in enumerate(leaves):
        a = arrays.get(f"leaf_{i:04d}")
        if a is None or a.shape != ref.shape or a.dtype != ref.dtype:
            raise DataError(path, f"checkpoint leaf {meta['paths'][i]} is missing or has the "
                                  f"wrong shape/dtype")
        loaded.append(jnp.asarray(a))
    return jax.tree_util.tree_unflatten(treedef, loaded), meta.get("extra", {})


def load_checkpoint(path) -> TrainState:
    """The TrainState stored at ``path``."""
    return load_checkpoint_with_extra(path)[0]


def checkpoint_name(step: int) -> str:
    return f"ckpt_{int(step):08d}.npz"


def latest_checkpoint(directory) -> Path | None:
    """The checkpoint of the highest step in ``directory`` (None if there is none)."""
    directory = Path(directory)
    if not directory.is_dir():
        return None
    found = sorted(directory.glob("ckpt_*.npz"))
    return found[-1] if found else None


def _prune_checkpoints(directory: Path, keep: int) -> None:
    for old in sorted(directory.glob("ckpt_*.npz"))[:-keep]:
        try:
            old.unlink()
        except FileNotFoundError:
            pass


# --------------------------------------------------------------------------------------
# Progress events (the library never draws: callers render them, see experiments/progress.py)
# --------------------------------------------------------------------------------------

class TrainProgress(NamedTuple):
    """One progress event of :func:`fit`, sent after every chunk of steps.

    Attributes:
      desc: the run's label (``fit(desc=...)``).
      step: steps done so far; total: the step the run ends at.
      loss, psnr: the last step's training loss and PSNR; gaussians: alive Gaussians.
    """

    desc: str
    step: int
    total: int
    loss: float
    psnr: float
    gaussians: int


# --------------------------------------------------------------------------------------
# The loop
# --------------------------------------------------------------------------------------

def _jsonable(metrics: dict) -> dict:
    out = {}
    for k, v in metrics.items():
        if isinstance(v, dict):
            out[k] = _jsonable(v)
        else:
            a = np.asarray(v)
            out[k] = a.item() if a.ndim == 0 else a.tolist()
    return out


def fit(state: TrainState, images, cameras: Camera, *, key=None, iterations: int | None = None,
        log_path=None, log_every: int = 10, checkpoint_dir=None, checkpoint_every: int | None = None,
        keep_checkpoints: int = 2, progress: Callable[[TrainProgress], None] | None = None,
        callback: Callable | None = None,
        should_stop: Callable[[int, list], bool] | None = None, desc: str = "train",
        chunk: int = CHUNK, max_loss: float | None = 0.75,
        room: float | None | str = "auto") -> TrainState:
    """Train until ``state.step == iterations`` (default ``state.config.iterations``).

    The images live on the device and the steps run in compiled chunks of up to
    ``chunk`` (:func:`train_chunk`); the host acts only between chunks (logs,
    progress, checkpoints, the divergence guard, growing the buffer or capacity),
    reading the chunk's metrics back at once. Chunking does not change the
    result: the view and key of step s depend only on (key, s).

    Args:
      state: TrainState (fresh from :func:`init_state` or from :func:`load_checkpoint`).
      images: float [N, H, W, 3] training images in [0, 1] (NumPy or JAX); the
        caller may pass a different array of the same shape to each call.
      cameras: Camera batch [N] matching ``images``.
      key: base PRNG key; default: the one in ``state`` (set by :func:`init_state`).
        The view and key of step s depend only on (key, s).
      iterations: stop at this step count (default: the config's).
      log_path: JSONL file receiving a metrics line every ``log_every`` steps and
        at every density-control step (appended to, so a resumed run continues it).
      checkpoint_dir: write ``ckpt_<step>.npz`` there every ``checkpoint_every``
        steps and at the end (atomic; the newest ``keep_checkpoints`` are kept).
        Chunks end on those steps.
      progress: ``progress(TrainProgress)`` after every chunk (and once at the start),
        e.g. to draw a bar; None: silent. The library itself never prints.
      callback: ``callback(state, metrics)`` after every chunk: the state at its
        end and the metrics of its completed steps (NumPy arrays [n]).
      should_stop: ``should_stop(step, loss_history) -> bool`` checked before
        every chunk; True ends the loop early (a final checkpoint is still written).
      chunk: steps per compiled chunk (1: the host sees every step).
      max_loss: divergence guard threshold (see :func:`divergence`; None: only
        non-finite values stop the run).
      room: a fresh run (step 0) that will densify starts with ``room`` x its alive
        Gaussians of capacity (:func:`plan_room`; None: as given, grown on demand;
        "auto": :func:`default_room`). The capacity changes only the speed and the
        last bits of the floats (reductions over differently sized arrays).
    Returns:
      the final TrainState.
    Raises:
      DataError: the run diverged (a non-finite loss or parameter, or an exploding
        loss); the message names the step and the quantity. Nothing of the bad
        chunk is checkpointed, so the newest checkpoint is the last good state.
    """
    if key is not None:
        state = dataclasses.replace(state, key=_key_data(key))
    total = state.config.iterations if iterations is None else int(iterations)
    if chunk < 1:
        raise DataError("chunk", f"must be >= 1, got {chunk}")
    images = jnp.asarray(images, state.gaussians.means.dtype)
    if images.ndim != 4 or images.shape[-1] != 3:
        raise DataError("images", f"expected float [N, H, W, 3], got {tuple(images.shape)}")
    if len(cameras) != images.shape[0]:
        raise DataError("cameras", f"{len(cameras)} cameras for {images.shape[0]} images")
    if (cameras.width, cameras.height) != (images.shape[2], images.shape[1]):
        raise DataError("cameras", f"cameras are {cameras.width}x{cameras.height} but images are "
                                   f"{images.shape[2]}x{images.shape[1]}")
    if images.shape[0] == 0:
        raise DataError("images", "no training views")
    if state.config.camera_opt and state.cameras.num_views != images.shape[0]:
        raise DataError("cameras", f"{images.shape[0]} training views but the state learns "
                                   f"pose corrections for {state.cameras.num_views}")
    cameras = jax.tree_util.tree_map(jnp.asarray, cameras)
    if int(state.step) == 0:
        state = plan_room(state, default_room() if room == "auto" else room)
    if state.max_intersections <= 0:
        state = size_buffer(state, cameras)
    ckpt_dir = None if checkpoint_dir is None else Path(checkpoint_dir)
    log_file = None
    if log_path is not None:
        Path(log_path).parent.mkdir(parents=True, exist_ok=True)
        log_file = open(log_path, "a")
    step = int(jax.device_get(state.step))
    if progress is not None:
        progress(TrainProgress(desc, step, total, float("nan"), float("nan"),
                               int(state.gaussians.num_alive())))
    history: list[float] = []
    t0 = time.monotonic()
    steps_done = 0

    def launch(st, at):
        """Dispatch the chunk that starts at step ``at`` (asynchronous: nothing is read)."""
        n = min(chunk, total - at)
        if ckpt_dir is not None and checkpoint_every:
            n = min(n, checkpoint_every - at % checkpoint_every)
        new, metrics = train_chunk(st, images, cameras, jax.device_put(np.int32(n)),
                                   length=chunk)
        return new, metrics, n

    try:
        ahead = None
        if step < total and not (should_stop is not None and should_stop(step, history)):
            ahead = launch(state, step)
        while ahead is not None:
            new, metrics, n = ahead
            # The next chunk goes to the device before this one is read, so the device
            # never waits for the host's logging and checks. It assumes this chunk
            # completes; when it does not (a redo, a stop, divergence) it is dropped.
            ahead = launch(new, step + n) if step + n < total else None
            metrics = jax.device_get(metrics)
            completed = metrics["ran"] & ~metrics["redo"]
            k = int(np.sum(completed))
            steps = jax.tree_util.tree_map(lambda a: a[:k], metrics)
            recent = history[-GUARD_WINDOW:] + [float(x) for x in steps["loss"]]
            reason = divergence(step, steps, history=recent, max_loss=max_loss,
                                window=GUARD_WINDOW)
            if reason is not None:
                raise DataError(desc, reason)
            state = new
            for i in range(k):
                history.append(float(steps["loss"][i]))
                done = step + i + 1
                if log_file is not None and (done % log_every == 0 or done == total
                                             or bool(steps["densify"]["refined"][i])):
                    record = dict(step=done, elapsed_s=time.monotonic() - t0,
                                  capacity=state.capacity,
                                  max_intersections=state.max_intersections,
                                  **_jsonable(jax.tree_util.tree_map(lambda a: a[i], steps)))
                    log_file.write(json.dumps(record) + "\n")
            if log_file is not None:
                log_file.flush()
            step += k
            steps_done += k
            if k < n:  # a step asked for more room: grow, then redo it in a new chunk
                state = grow_for_redo(state, jax.tree_util.tree_map(lambda a: a[k], metrics))
                ahead = None
            if k:
                if progress is not None:
                    progress(TrainProgress(desc, step, total, float(steps["loss"][-1]),
                                           float(steps["psnr"][-1]),
                                           int(steps["num_gaussians"][-1])))
                if callback is not None:
                    callback(state, steps)
                if ckpt_dir is not None and checkpoint_every and step % checkpoint_every == 0:
                    save_checkpoint(ckpt_dir / checkpoint_name(step), state)
                    _prune_checkpoints(ckpt_dir, keep_checkpoints)
            if should_stop is not None and step < total and should_stop(step, history):
                break
            if ahead is None and step < total:
                ahead = launch(state, step)
    finally:
        if log_file is not None:
            log_file.close()
    if ckpt_dir is not None and steps_done:
        save_checkpoint(ckpt_dir / checkpoint_name(step), state)
        _prune_checkpoints(ckpt_dir, keep_checkpoints)
    return state


def resume(checkpoint) -> TrainState:
    """The state of ``checkpoint``: a file, or a directory (its newest ``ckpt_*.npz``)."""
    path = Path(checkpoint)
    if path.is_dir():
        found = latest_checkpoint(path)
        if found is None:
            raise DataError(path, "no ckpt_*.npz checkpoint in this directory")
        path = found
    elif not path.exists():
        raise DataError(path, "no such checkpoint file or directory")
    return load_checkpoint(path)


# --------------------------------------------------------------------------------------
# Evaluation
# --------------------------------------------------------------------------------------

def render_views(gaussians: Gaussians, cameras: Camera, *, background=(1.0, 1.0, 1.0),
                 sh_degree: int | None = None) -> np.ndarray:
    """float32 [N, H, W, 3] renders of a camera batch (outside jit, one view at a time)."""
    out = []
    bg = jnp.asarray(background, jnp.float32)
    for i in range(len(cameras)):
        r = render(gaussians, cameras[i], background=bg, sh_degree=sh_degree)
        out.append(np.asarray(jnp.clip(r.rgb, 0.0, 1.0)))
    return np.stack(out) if out else np.zeros((0, cameras.height, cameras.width, 3), np.float32)


def evaluate(gaussians: Gaussians, images, cameras: Camera, *, background=(1.0, 1.0, 1.0),
             sh_degree: int | None = None) -> dict:
    """Held-out quality: mean PSNR and SSIM (scikit-image) over the views, plus per view.

    Returns:
      dict(psnr, ssim, psnr_per_view, ssim_per_view, renders float32 [N, H, W, 3]).
    """
    from .metrics import psnr, ssim_skimage

    renders = render_views(gaussians, cameras, background=background, sh_degree=sh_degree)
    images = np.asarray(images, np.float32)
    p = [float(psnr(r, t)) for r, t in zip(renders, images)]
    s = [float(ssim_skimage(r, t)) for r, t in zip(renders, images)]
    return dict(psnr=float(np.mean(p)) if p else math.nan,
                ssim=float(np.mean(s)) if s else math.nan,
                psnr_per_view=p, ssim_per_view=s, renders=renders)
