"""An edit run's checkpoint: its whole :class:`EditState` in one npz, atomically, bit-exact.

The format is :mod:`jaxedit.io.checkpoint`'s (versioned, fsync, atomic rename; the
trainer's checkpoints use it too): the trainer state's leaves under their pytree
paths (typed PRNG keys as raw key data), the training images, the edit flags and
the loss tracker as arrays, and everything else as the file's JSON meta record,
so a resumed run continues with the same bits.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from ..io.checkpoint import read_pytree, restore, save_pytree
from .buffer import Utilisation
from .state import DensityTally, EditState, LossTracker

KIND = "edit"


def save_checkpoint(path: str | os.PathLike, st: EditState, meta: dict) -> None:
    """Write the edit state to ``path`` (npz, atomic: a crash never leaves half a file)."""
    tree = {"train": st.train, "images": st.images, "edited": np.asarray(st.edited),
            "tracker_recent": st.tracker.recent}
    info = {"subtask": st.subtask, "step": st.step, "records": list(st.records),
            "seconds": st.seconds, "utilisation": st.utilisation.as_dict(),
            "complete_at": st.complete_at, "annealed_at": st.annealed_at,
            "density": st.density._asdict(),
            "tracker": [int(st.tracker.count), float(st.tracker.best),
                        int(st.tracker.since_best)],
            "max_intersections": getattr(st.train, "max_intersections", None), "meta": meta}
    save_pytree(path, tree, kind=KIND, meta=info)


def load_checkpoint(path: str | os.PathLike, train_template) -> tuple[EditState, dict]:
    """Read a checkpoint written by :func:`save_checkpoint` (state, meta).

    ``train_template`` is any trainer state of the same structure (shapes may
    differ: capacity grows during a run); its typed PRNG keys are restored.
    """
    path = Path(path)
    arrays, info = read_pytree(path, kind=KIND)
    template = {"train": train_template, "images": np.zeros((0,), np.float32),
                "edited": np.zeros((0,), bool), "tracker_recent": np.zeros((0,), np.float32)}
    # The capacity grows during a run: the stored shapes win over the template's.
    tree = restore(template, arrays, path, shapes=False)
    train = tree["train"]
    if info.get("max_intersections") is not None and hasattr(train, "max_intersections"):
        train = dataclasses.replace(train, max_intersections=int(info["max_intersections"]))
    count, best, since = info["tracker"]
    tracker = LossTracker(tree["tracker_recent"], jnp.int32(count),
                          jnp.float32(best), jnp.int32(since))
    st = EditState(subtask=info["subtask"], step=info["step"], train=train,
                     images=tree["images"], edited=np.asarray(tree["edited"]),
                     tracker=tracker, records=tuple(info["records"]), seconds=info["seconds"],
                     complete_at=int(info.get("complete_at", -1)),
                     annealed_at=int(info.get("annealed_at", -1)),
                     density=DensityTally(**info.get("density", {})),
                     utilisation=Utilisation(**info["utilisation"]))
    return st, info["meta"]
