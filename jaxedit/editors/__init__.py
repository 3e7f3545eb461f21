"""The 2D instruction editors. The method sees an editor only through :mod:`.base`'s
:class:`Editor` protocol.

- :mod:`.base`: the protocol, e(r) interpolation, :func:`edit_views`, :func:`warm_up`,
  :func:`relevance` and :func:`relevance_mask`.
- :mod:`.jax_ip2p`: InstructPix2Pix in JAX; :mod:`.ip2p`: its torch reference;
  :mod:`.diffusion`: their shared arithmetic; :mod:`.keys`: per-view seeding.
- :mod:`.bundled`: the small InstructPix2Pix shipped in the package.

The two InstructPix2Pix editors are imported on demand.
"""

from .base import (Editor, edit_views, editor_guidance, interpolate_embedding, relevance,
                   relevance_mask, warm_up)
from .bundled import (BUNDLED, DEFAULT_SIZE, bundled_editor, instructions, native_size,
                      recommended_guidance)
from .keys import view_key

__all__ = [
    "BUNDLED", "DEFAULT_SIZE", "Editor", "bundled_editor",
    "edit_views", "editor_guidance", "instructions", "interpolate_embedding", "native_size",
    "recommended_guidance", "relevance", "relevance_mask", "view_key", "warm_up",
]
