"""The Editor protocol every 2D instruction editor implements.

Images are float32 [H, W, 3] in [0, 1] (``image`` the render, ``original`` the photo);
``timestep_range`` is (t_min, t_max) as schedule fractions; ``guidance`` (text, image), None
for the editor's own. Optional: ``edit_many`` with ``batch``, ``calls_side_by_side``,
``relevance``.
"""

from __future__ import annotations

import concurrent.futures
from typing import Any, Protocol, runtime_checkable

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import DataError
from .diffusion import IP2P_GUIDANCE, check_guidance
from .masks import relevance_mask  # noqa: F401 - part of the protocol's API


@runtime_checkable
class Editor(Protocol):
    name: str

    def encode(self, prompt: str) -> Any:
        """Embedding E(prompt), an array (IP2P's is [77, 768])."""
        ...

    def edit(self, image, original, embedding, key: jax.Array, *,
             timestep_range: tuple[float, float] = (0.02, 0.98),
             guidance: tuple[float, float] | None = None) -> np.ndarray | jax.Array:
        """Edited image float32 [H, W, 3] in [0, 1] (NumPy or JAX), deterministic given ``key``."""
        ...


def editor_guidance(editor, guidance: tuple[float, float] | None = None) -> tuple[float, float]:
    """``guidance``, else the editor's ``guidance`` attribute, else IP2P's, as (text, image)."""
    if guidance is None:
        guidance = getattr(editor, "guidance", IP2P_GUIDANCE)
    return check_guidance(guidance)


def relevance(editor, image, original, embedding, key: jax.Array, *,
              timestep_range: tuple[float, float] = (0.02, 0.98),
              guidance: tuple[float, float] | None = None):
    """``editor.relevance``: float32 [H, W] in [0, 1] (1: relevant); DataError without one."""
    fn = getattr(editor, "relevance", None)
    if fn is None:
        raise DataError("--local", f"editor {getattr(editor, 'name', type(editor).__name__)!r} "
                                   "gives no relevance map: use --local off with --region or "
                                   "--masks")
    return fn(image, original, embedding, key, timestep_range=timestep_range,
              guidance=editor_guidance(editor, guidance))


def warm_up(editor, height: int, width: int, key: jax.Array, *, views: int = 1,
            guidance: tuple[float, float] | None = None) -> None:
    """Edit ``views`` grey ``height`` x ``width`` views once, so the program is compiled."""
    grey = jnp.full((views, height, width, 3), 0.5, jnp.float32)
    out = edit_views(editor, grey, grey, editor.encode(""), jax.random.split(key, views),
                     guidance=guidance)
    jax.block_until_ready([jnp.asarray(x) for x in out])


def interpolate_embedding(e_prompt, e_null, ratio: float):
    """e(r) = r E(p) + (1 - r) E(null), elementwise on arrays of one shape."""
    if tuple(e_prompt.shape) != tuple(e_null.shape):
        raise ValueError(f"embedding shapes differ: {tuple(e_prompt.shape)} vs {tuple(e_null.shape)}")
    return ratio * e_prompt + (1.0 - ratio) * e_null


def edit_views(editor, images, originals, embedding, keys, *,
               timestep_range: tuple[float, float] = (0.02, 0.98),
               guidance: tuple[float, float] | None = None) -> list:
    """Edit views [B] with keys [B] by ``edit_many`` in chunks of ``editor.batch`` (else
    ``edit``), ``calls_side_by_side`` calls at once; results do not depend on the batching.

    ``images``, ``originals``: [B, H, W, 3] (or sequences of [H, W, 3]); ``embedding``: one
    for all views. Returns B views (as ``edit`` returns them), in order.
    """
    count = len(images)
    guidance = editor_guidance(editor, guidance)
    batch = int(getattr(editor, "batch", 1)) if hasattr(editor, "edit_many") else 1
    batch = 1 if batch <= 1 or count == 1 else batch

    def call(lo: int) -> list:
        if batch == 1:
            return [editor.edit(images[lo], originals[lo], embedding, keys[lo],
                                timestep_range=timestep_range, guidance=guidance)]
        hi = min(lo + batch, count)
        edited = editor.edit_many(jnp.stack([jnp.asarray(x) for x in images[lo:hi]]),
                                  jnp.stack([jnp.asarray(x) for x in originals[lo:hi]]),
                                  embedding, jnp.stack(list(keys[lo:hi])),
                                  timestep_range=timestep_range, guidance=guidance)
        return [edited[i] for i in range(hi - lo)]

    starts = range(0, count, batch)
    at_once = min(int(getattr(editor, "calls_side_by_side", 1)), len(starts))
    if at_once <= 1:
        parts = [call(lo) for lo in starts]
    else:
        with concurrent.futures.ThreadPoolExecutor(at_once,
                                                   thread_name_prefix="jaxedit-edit") as pool:
            parts = list(pool.map(call, starts))
    return [view for part in parts for view in part]
