"""The Editor protocol every 2D instruction editor implements.

An editor turns a text instruction into an embedding (``encode``) and edits one
view given an embedding (``edit``). The framework, not the editor, forms the
ProEdit subtask embedding e(r) = r E(p) + (1 - r) E("") with
:func:`interpolate_embedding`; ``encode("")`` is the null embedding E("").

Images are float32 arrays [H, W, 3] in [0, 1] (NumPy or JAX). ``image`` is the
current render of a view, ``original`` the original photo of that view (IP2P
conditions on it). ``timestep_range`` is (t_min, t_max) as fractions of the
diffusion schedule in [0, 1] (the paper: 0.45-0.85, annealed by the driver);
``guidance`` is (text_scale, image_scale), None for the editor's own (its ``guidance``
attribute: what its weights folder recommends, InstructPix2Pix's 7.5, 1.5 by default;
:func:`editor_guidance`).

An editor that can edit several views in one call (the JAX InstructPix2Pix) also has
``edit_many(images, originals, embeddings, keys, ...)`` and ``batch``, its most views per
call; :func:`edit_views` uses it wherever several views are due at once, and makes
``calls_side_by_side`` of its calls at once when the editor has that attribute.

Local edits (issue 35) ask an editor where an instruction acts: ``relevance(image,
original, embedding, key, ...)`` -> float32 [H, W] mask in [0, 1]; :func:`relevance`
calls it (the JAX InstructPix2Pix has it as a method: one batched UNet call).
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
        """Embedding E(prompt): an array (the simulated editor's is small, IP2P's is [77, 768])."""
        ...

    def edit(self, image, original, embedding, key: jax.Array, *,
             timestep_range: tuple[float, float] = (0.02, 0.98),
             guidance: tuple[float, float] | None = None) -> np.ndarray | jax.Array:
        """Edited image float32 [H, W, 3] in [0, 1], deterministic given ``key`` (NumPy, or a
        JAX array on the editor's device: the JAX editor's result stays on the device)."""
        ...


def editor_guidance(editor, guidance: tuple[float, float] | None = None) -> tuple[float, float]:
    """``guidance`` as (text, image) floats, or where None the editor's own: its ``guidance``
    attribute (the bundled editor's folder recommends 2, 1.5: :func:`jaxedit.editors.bundled.
    recommended_guidance`), else InstructPix2Pix's 7.5, 1.5."""
    if guidance is None:
        guidance = getattr(editor, "guidance", IP2P_GUIDANCE)
    return check_guidance(guidance)


def relevance(editor, image, original, embedding, key: jax.Array, *,
              timestep_range: tuple[float, float] = (0.02, 0.98),
              guidance: tuple[float, float] | None = None):
    """Where ``embedding`` changes the view, float32 [H, W] in [0, 1] (1: relevant).

    ``editor.relevance`` (the JAX InstructPix2Pix's is
    :meth:`jaxedit.editors.jax_ip2p.JaxIP2PEditor.relevance`). An editor without one is a
    DataError (``--local auto`` needs it; ``--region`` / ``--masks`` do not).
    """
    fn = getattr(editor, "relevance", None)
    if fn is None:
        raise DataError("--local", f"editor {getattr(editor, 'name', type(editor).__name__)!r} "
                                   "gives no relevance map: use --local off with --region or "
                                   "--masks")
    return fn(image, original, embedding, key, timestep_range=timestep_range,
              guidance=editor_guidance(editor, guidance))


def warm_up(editor, height: int, width: int, key: jax.Array, *, views: int = 1,
            guidance: tuple[float, float] | None = None) -> None:
    """Edit ``views`` grey views of ``height`` x ``width`` once and drop the result, so that
    the editor's program for that call (:func:`edit_views`' batch of ``views``, these
    guidance scales) is compiled, and written to the persistent compilation cache, before a
    run needs it. The demo calls it on a thread while the reconstruction trains: on a GPU
    an SD 1.5-size editor program compiles for about 45 s. The run's own edits are not
    changed (an editor is a pure function of its inputs and keys)."""
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
    """Edit views [B] with their keys [B]: ``editor.edit_many`` in chunks of
    ``editor.batch`` where the editor has it, else one ``edit`` per view.

    ``images``, ``originals``: [B, H, W, 3] (or sequences of [H, W, 3]); ``embedding``
    one [...] for all views; ``keys``: B typed keys. Returns B edited views (each as
    ``edit`` returns it), in order. One view per call gives ``edit``'s own result,
    so an editor without ``edit_many``, or with ``batch`` 1, edits exactly as before.
    An editor whose ``calls_side_by_side`` is above 1 has that many calls made at once, on
    threads (the same calls, so the same results).
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
