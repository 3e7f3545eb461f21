"""The Editor protocol every 2D instruction editor implements.

An editor turns a text instruction into an embedding (``encode``) and edits one
view given an embedding (``edit``). The framework, not the editor, forms the
ProEdit subtask embedding e(r) = r E(p) + (1 - r) E("") with
:func:`interpolate_embedding`; ``encode("")`` is the null embedding E("").

Images are float32 arrays [H, W, 3] in [0, 1] (NumPy or JAX). ``image`` is the
current render of a view, ``original`` the original photo of that view (IP2P
conditions on it). ``timestep_range`` is (t_min, t_max) as fractions of the
diffusion schedule in [0, 1] (the paper: 0.45-0.85, annealed by the driver);
``guidance`` is (text_scale, image_scale).
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import jax
import numpy as np


@runtime_checkable
class Editor(Protocol):
    name: str

    def encode(self, prompt: str) -> Any:
        """Embedding E(prompt): an array (the simulated editor's is small, IP2P's is [77, 768])."""
        ...

    def edit(self, image, original, embedding, key: jax.Array, *,
             timestep_range: tuple[float, float] = (0.02, 0.98),
             guidance: tuple[float, float] = (7.5, 1.5)) -> np.ndarray | jax.Array:
        """Edited image float32 [H, W, 3] in [0, 1], deterministic given ``key`` (NumPy, or a
        JAX array on the editor's device: the JAX editor's result stays on the device)."""
        ...


def interpolate_embedding(e_prompt, e_null, ratio: float):
    """e(r) = r E(p) + (1 - r) E(null), elementwise on arrays of one shape."""
    if tuple(e_prompt.shape) != tuple(e_null.shape):
        raise ValueError(f"embedding shapes differ: {tuple(e_prompt.shape)} vs {tuple(e_null.shape)}")
    return ratio * e_prompt + (1.0 - ratio) * e_null
