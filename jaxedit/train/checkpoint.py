"""Trainer checkpoints: a :class:`TrainState` in one ``.npz`` (:mod:`jaxedit.io.checkpoint`),
the static fields and template shapes in its meta record, the leaves bit for bit.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp

from .. import gaussians as glib
from .. import poses
from ..errors import DataError
from ..io.checkpoint import FORMAT_VERSION, read_pytree, restore, save_pytree
from .config import TrainConfig
from .state import TrainState, init_state

KIND = "train"
#: The scene extent was a static field, kept only in the meta record, before it was traced:
#: files of that layout lack its leaf, and the template built from their meta holds it.
PRE_TRACED_EXTENT = (".scene_extent",)
#: The version of the file layout (that of every jaxedit checkpoint).
CHECKPOINT_VERSION = FORMAT_VERSION


def save_checkpoint(path, state: TrainState, *, extra: dict | None = None) -> Path:
    """Write ``state`` to ``path`` (.npz) atomically: every leaf plus the static fields.

    ``extra`` (JSON-serialisable) is stored alongside and returned by
    :func:`load_checkpoint_with_extra`.
    """
    meta = dict(config=state.config.to_dict(), scene_extent=float(state.scene_extent),
                max_intersections=state.max_intersections, capacity=state.capacity,
                sh_degree=state.gaussians.sh_degree, step=int(state.step),
                num_views=state.cameras.num_views, extra=extra or {})
    return save_pytree(path, state, kind=KIND, meta=meta)


def _template(meta: dict, where) -> TrainState:
    """A TrainState of the stored structure and static fields (its arrays are placeholders)."""
    try:
        config = TrainConfig.from_dict(meta["config"], f"{where}:config")
        capacity, sh_degree = int(meta["capacity"]), int(meta["sh_degree"])
        extent, buffer = float(meta["scene_extent"]), int(meta["max_intersections"])
        views = int(meta.get("num_views", 0))
    except (KeyError, TypeError, ValueError) as e:
        raise DataError(where, f"checkpoint metadata lacks or garbles {e}") from None
    template = init_state(glib.empty(capacity, sh_degree),
                          dataclasses.replace(config, camera_opt=False), extent,
                          key=jax.random.key(0), max_intersections=buffer)
    return dataclasses.replace(template, config=config, cameras=poses.init_corrections(
        jnp.ones((views,), jnp.float32)))


def load_checkpoint_with_extra(path) -> tuple[TrainState, dict]:
    """(TrainState, extra) from a checkpoint written by :func:`save_checkpoint`."""
    arrays, meta = read_pytree(path, kind=KIND)
    state = restore(_template(meta, path), arrays, path, template_fills=PRE_TRACED_EXTENT)
    return state, meta.get("extra", {})


def load_checkpoint(path) -> TrainState:
    """The TrainState stored at ``path``."""
    return load_checkpoint_with_extra(path)[0]
