"""The 2D instruction editors, one package beside the networks (``jaxedit.models``).

The ProEdit method (``jaxedit.edit``) sees an editor only through the protocol of
:mod:`.base`: encode a prompt, edit views at a timestep range, and (for local edits) say
where an instruction acts.

- :mod:`.base`: the :class:`Editor` protocol, e(r) interpolation, batched :func:`edit_views`,
  :func:`warm_up` (an editor's program compiled ahead of the run), :func:`relevance` and
  :func:`relevance_mask`.
- :mod:`.jax_ip2p`: InstructPix2Pix in JAX (no torch); :mod:`.ip2p`: its torch + diffusers
  reference (the JAX one also gives the relevance map of "Watch Your Steps");
  :mod:`.diffusion`: the arithmetic both share; :mod:`.keys`: per-view edit seeding.
- :mod:`.bundled`: the small InstructPix2Pix that ships with jaxedit, a diffusers folder
  inside the package, which ``--editor ip2p`` loads when no ``--ip2p-weights`` is given
  (with the guidance its folder recommends, :func:`recommended_guidance`).

The simulated editor (the offline test instrument whose targets are known exactly), the
outcome measure and the bundled editor's training are the lab's (:mod:`jaxedit_lab`), above
this library.

The two InstructPix2Pix editors are imported on demand (torch is optional; the JAX one
loads equinox networks).
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
