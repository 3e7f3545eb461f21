"""How an edit made at the editor's model size becomes the target of a larger view.

Enlarging the edit of a shrunk view blurs every target, and so the scene.
:class:`DetailTargets` adds the edit's change at the editor's scale to the view::

    target = image + up(edit(down(image)) - down(image))

(antialiased bilinear resizes), so unchanged areas keep the view's own detail, but the
editor's own identity error (what e(0) changes) reaches every target. :class:`DeltaTargets`
pairs the edit with e(0)'s edit of the same view and noise (as Delta Denoising Score pairs
its two scores), so only the instruction's change is added::

    target = image + up(edit_e(r)(down(image)) - edit_e(0)(down(image)))

At e(0) the target is the view itself. Views at or under the editor's size are edited as
the editor edits them.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..errors import DataError

#: How a larger view's target is made: "delta" (:class:`DeltaTargets`), "detail"
#: (:class:`DetailTargets`) or "stretch" (the editor's own result, its edit enlarged).
TARGETS = ("delta", "detail", "stretch")
#: Editor images per edited view of each composition at e(r), r > 0 (at e(0), "delta" needs
#: none: its change is zero).
EDITS_PER_VIEW = {"delta": 2, "detail": 1, "stretch": 1}


def compose_target(images, small, edited_small):
    """``images + up(edited_small - small)``, clamped to [0, 1].

    Args:
      images: float [B, H, W, 3], the views at their own size.
      small: float [B, h, w, 3], the views at the editor's size (``down(images)``).
      edited_small: float [B, h, w, 3], the editor's edits of ``small``.
    Returns float32 [B, H, W, 3].
    """
    from .jax_ip2p import resize_images

    change = jnp.asarray(edited_small, jnp.float32) - jnp.asarray(small, jnp.float32)
    return jnp.clip(jnp.asarray(images, jnp.float32) + resize_images(change, images.shape[1:3]),
                    0.0, 1.0)


class DetailTargets:
    """``editor`` whose edits of views larger than its model size keep the views' detail
    (:func:`compose_target`); everything else is the editor's own. ``editor`` must have
    ``model_hw(height, width)``, the size it edits a view at."""

    def __init__(self, editor):
        if not hasattr(editor, "model_hw"):
            raise DataError("targets", f"editor {getattr(editor, 'name', editor)!r} does not "
                                       "say its model size; use stretched targets")
        self.editor = editor

    def __getattr__(self, name):
        return getattr(self.editor, name)

    def __repr__(self):
        return f"DetailTargets({self.editor!r})"

    def _smaller(self, height: int, width: int) -> tuple[int, int] | None:
        """The editor's size of a view of ``height`` x ``width`` when the view is larger
        (None: edited as it is)."""
        h, w = self.editor.model_hw(height, width)
        return (h, w) if h < height or w < width else None

    def edit_many(self, images, originals, embeddings, keys, **kwargs):
        """:meth:`edit_many` of the editor, composed as :func:`compose_target` for views
        larger than its size; float32 [B, H, W, 3]."""
        from .jax_ip2p import resize_images

        images = jnp.asarray(images, jnp.float32)
        hw = self._smaller(*images.shape[1:3])
        if hw is None:
            return self.editor.edit_many(images, originals, embeddings, keys, **kwargs)
        small = resize_images(images, hw)
        edited = self.editor.edit_many(small, resize_images(jnp.asarray(originals, jnp.float32),
                                                            hw), embeddings, keys, **kwargs)
        return compose_target(images, small, edited)

    def edit(self, image, original, embedding, key, **kwargs):
        """:meth:`edit` of one view [H, W, 3], composed as :meth:`edit_many`."""
        image = jnp.asarray(image, jnp.float32)
        if self._smaller(*image.shape[:2]) is None:
            return self.editor.edit(image, original, embedding, key, **kwargs)
        import jax

        if not jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
            key = jax.random.wrap_key_data(jnp.asarray(key, jnp.uint32))
        return self.edit_many(image[None], jnp.asarray(original, jnp.float32)[None], embedding,
                              key.reshape(1), **kwargs)[0]


class DeltaTargets(DetailTargets):
    """``editor`` whose edits of views larger than its model size add only the instruction's
    change: ``image + up(edit_e(down) - edit_null(down))``, both edits of one view made with
    its key in one ``edit_many`` call of 2B views (:func:`compose_target`); at e(0) the view
    itself, with no editor call. The pairs of half the editor's ``batch`` views go in one
    call (one view's pair where that is under 2), so a call edits no more images than the
    editor's own (its ``batch`` is the editor's: views at its size are edited as
    before). :attr:`measuring` is the single-edit
    :class:`DetailTargets` of the editor: its identity check and difficulty oracle edit with
    it, so they measure the editor, not the pairing."""

    def __init__(self, editor):
        super().__init__(editor)
        self.measuring = DetailTargets(editor)
        self._e_null = None

    def __repr__(self):
        return f"DeltaTargets({self.editor!r})"

    @property
    def e_null(self) -> np.ndarray:
        """E(""), the editor's embedding of the empty instruction (encoded once)."""
        if self._e_null is None:
            self._e_null = np.asarray(self.editor.encode(""), np.float32)
        return self._e_null

    def edit_many(self, images, originals, embeddings, keys, **kwargs):
        """Paired edits composed as above for views larger than the editor's size (else the
        editor's edit); ``embeddings`` [77, D] or [B, 77, D]; float32 [B, H, W, 3]."""
        from .jax_ip2p import resize_images

        images = jnp.asarray(images, jnp.float32)
        hw = self._smaller(*images.shape[1:3])
        if hw is None:
            return self.editor.edit_many(images, originals, embeddings, keys, **kwargs)
        b, null = images.shape[0], self.e_null
        emb = jnp.broadcast_to(jnp.asarray(embeddings, jnp.float32), (b, *null.shape))
        if bool(jnp.all(emb == null)):  # e(0): the change is zero
            return jnp.clip(images, 0.0, 1.0)
        small = resize_images(images, hw)
        orig = resize_images(jnp.asarray(originals, jnp.float32), hw)
        nulls = jnp.broadcast_to(null, emb.shape)
        pair = lambda x, y: jnp.concatenate([x, y])  # noqa: E731
        per = max(1, int(getattr(self.editor, "batch", 1)) // 2)
        parts = []
        for lo in range(0, b, per):
            at = slice(lo, min(lo + per, b))
            edited = self.editor.edit_many(pair(small[at], small[at]), pair(orig[at], orig[at]),
                                           pair(emb[at], nulls[at]), pair(keys[at], keys[at]),
                                           **kwargs)
            n = at.stop - lo
            parts.append(compose_target(images[at], edited[n:], edited[:n]))
        return parts[0] if len(parts) == 1 else jnp.concatenate(parts)


def measuring_editor(editor):
    """The editor an identity check and a difficulty oracle edit with: a
    :class:`DeltaTargets`' single-edit :attr:`~DeltaTargets.measuring`, else ``editor``."""
    return getattr(editor, "measuring", editor) if isinstance(editor, DeltaTargets) else editor


def with_targets(editor, targets: str):
    """``editor`` making larger views' targets as ``targets`` says (one of :data:`TARGETS`):
    "delta" / "detail" wrap an editor that has a model size in :class:`DeltaTargets` /
    :class:`DetailTargets` (others, e.g. the simulated editor, edit at the view's size and
    are returned as they are)."""
    if targets not in TARGETS:
        raise DataError("targets", f"must be one of {', '.join(TARGETS)}, got {targets!r}")
    if targets == "stretch" or not hasattr(editor, "model_hw"):
        return editor
    return DeltaTargets(editor) if targets == "delta" else DetailTargets(editor)
