"""The edit driver's checkpoint format: the whole driver state in one npz, atomically, bit-exact.

Leaves of the trainer state are stored under their pytree paths (typed PRNG keys
as raw key data), the training images and flags as arrays, and everything else
as one JSON record (``info``), so a resumed run continues with the same bits.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import DataError
from ..io.files import atomic_path, read_npz
from .buffer import Utilisation
from .driver import DensityTally, DriverState, LossTracker

CHECKPOINT_NAME = "checkpoint.npz"


def _flatten(tree) -> dict[str, np.ndarray]:
    leaves = jax.tree_util.tree_flatten_with_path(tree)[0]
    return {jax.tree_util.keystr(p): np.asarray(v) for p, v in leaves}


def _unflatten(template, arrays: dict[str, np.ndarray], where: str):
    paths, treedef = jax.tree_util.tree_flatten_with_path(template)
    leaves = []
    for p, ref in paths:
        k = jax.tree_util.keystr(p)
        if k not in arrays:
            raise DataError(where, f"checkpoint lacks {k} (saved by another version?)")
        a = arrays[k]
        if isinstance(ref, jax.Array) and jax.dtypes.issubdtype(ref.dtype, jax.dtypes.prng_key):
            a = jax.random.wrap_key_data(a)
        else:
            a = jnp.asarray(a)
        leaves.append(a)
    return jax.tree_util.tree_unflatten(treedef, leaves)


def _key_data(tree):
    """Replace typed PRNG keys by their raw data so they can be saved."""
    def fn(x):
        if isinstance(x, jax.Array) and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
            return jax.random.key_data(x)
        return x
    return jax.tree_util.tree_map(fn, tree)


def save_checkpoint(path: str | os.PathLike, st: DriverState, meta: dict) -> None:
    """Write the driver state to ``path`` (npz, atomic: a crash never leaves half a file)."""
    arrays = {f"train/{k}": v for k, v in _flatten(_key_data(st.train)).items()}
    arrays["images"] = np.asarray(jax.device_get(st.images))
    arrays["edited"] = np.asarray(st.edited)
    arrays["tracker_recent"] = np.asarray(st.tracker.recent)
    info = {"subtask": st.subtask, "step": st.step, "records": list(st.records),
            "seconds": st.seconds, "utilisation": st.utilisation.as_dict(),
            "complete_at": st.complete_at, "annealed_at": st.annealed_at,
            "density": st.density._asdict(),
            "tracker": [int(st.tracker.count), float(st.tracker.best),
                        int(st.tracker.since_best)],
            "max_intersections": getattr(st.train, "max_intersections", None), "meta": meta}
    arrays["info"] = np.frombuffer(json.dumps(info).encode(), np.uint8)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)


def load_checkpoint(path: str | os.PathLike, train_template) -> tuple[DriverState, dict]:
    """Read a checkpoint written by :func:`save_checkpoint` (state, meta).

    ``train_template`` is any trainer state of the same structure (shapes may
    differ: capacity grows during a run); its typed PRNG keys are restored.
    """
    path = Path(path)
    arrays = read_npz(path)
    try:
        info = json.loads(arrays.pop("info").tobytes().decode())
        if not isinstance(info, dict):
            raise ValueError("not a record")
    except (KeyError, ValueError):
        raise DataError(path, "not a jaxedit edit checkpoint (no info record)") from None
    train = _unflatten(train_template, {k[6:]: v for k, v in arrays.items()
                                        if k.startswith("train/")}, str(path))
    if info.get("max_intersections") is not None and hasattr(train, "max_intersections"):
        train = dataclasses.replace(train, max_intersections=int(info["max_intersections"]))
    count, best, since = info["tracker"]
    tracker = LossTracker(jnp.asarray(arrays["tracker_recent"], jnp.float32), jnp.int32(count),
                          jnp.float32(best), jnp.int32(since))
    st = DriverState(subtask=info["subtask"], step=info["step"], train=train,
                     images=jax.device_put(arrays["images"]), edited=arrays["edited"],
                     tracker=tracker, records=tuple(info["records"]), seconds=info["seconds"],
                     complete_at=int(info.get("complete_at", -1)),
                     annealed_at=int(info.get("annealed_at", -1)),
                     density=DensityTally(**info.get("density", {})),
                     utilisation=Utilisation(**info["utilisation"]))
    return st, info["meta"]
