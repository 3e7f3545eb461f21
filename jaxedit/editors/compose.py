"""How an edit made at the editor's model size becomes the target of a larger view.

Enlarging the edit of a shrunk view blurs every target, and so the scene.
:class:`DetailTargets` adds the edit's change at the editor's scale to the view::

    target = image + up(edit(down(image)) - down(image))

(antialiased bilinear resizes), so unchanged areas keep the view's own detail, but the
editor's own identity error (what e(0) changes) reaches every target. :class:`DeltaTargets`
pairs the edit with e(0)'s edit of the same view and noise (as Delta Denoising Score pairs
its two scores), so only the instruction's change is added::

    target = image + up(edit_e(r)(down(image)) - edit_e(0)(down(image)))

At e(0) the target is the view itself, but the pairing has no fixed point where e(0)'s edit
of an edited view pulls it back. Anchored pairs (``reference="photo"``) take e(0)'s
identity error on the view's photo instead, the source branch of Delta Denoising Score::

    target = image + up(edit_e(r)(down(image)) - down(image) - edit_e(0)(down(photo)) + down(photo))

A hybrid (``DetailTargets(editor, keep_null=True)``) gives the view itself at e(0) and the
detail composition at r > 0. Views at or under the editor's size are edited as the editor
edits them.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..errors import DataError

#: How a larger view's target is made: "delta" / "anchored" (:class:`DeltaTargets` paired
#: with the render's / the photo's e(0) edit), "hybrid" (the render at e(0), else detail),
#: "detail" (:class:`DetailTargets`) or "stretch" (the editor's own result, enlarged).
TARGETS = ("delta", "anchored", "hybrid", "detail", "stretch")
#: Editor images per edited view of each composition at e(r), r > 0 (at e(0), "delta" and
#: "hybrid" need none: the target is the view).
EDITS_PER_VIEW = {"delta": 2, "anchored": 2, "hybrid": 1, "detail": 1, "stretch": 1}


def _per_view(editor, embeddings, b: int) -> tuple[jnp.ndarray, np.ndarray]:
    """(``b`` views' embeddings [B, D...] from [D...] or [B, D...], E("") [D...])."""
    null = np.asarray(editor.encode(""), np.float32)
    return jnp.broadcast_to(jnp.asarray(embeddings, jnp.float32), (b, *null.shape)), null


def _all_null(editor, embeddings, b: int) -> bool:
    """Whether every one of ``b`` views' ``embeddings`` ([D...] or [B, D...]) is E("")."""
    emb, null = _per_view(editor, embeddings, b)
    return bool(jnp.all(emb == null))


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
    ``model_hw(height, width)``, the size it edits a view at. ``keep_null``: a larger
    view edited with E("") is its own target (no editor call)."""

    def __init__(self, editor, keep_null: bool = False):
        if not hasattr(editor, "model_hw"):
            raise DataError("targets", f"editor {getattr(editor, 'name', editor)!r} does not "
                                       "say its model size; use stretched targets")
        self.editor = editor
        self.keep_null = bool(keep_null)

    @property
    def measuring(self):
        """The single-edit composition an identity check and a difficulty oracle edit with."""
        return DetailTargets(self.editor) if self.keep_null else self

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
        if self.keep_null and _all_null(self.editor, embeddings, images.shape[0]):
            return jnp.clip(images, 0.0, 1.0)
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
    change, e(r)'s edit of the shrunk view less e(0)'s edit made with the same key in the
    same ``edit_many`` call (:func:`compose_target`): e(0)'s edit of the view itself
    (``reference="render"``; at e(0) the view, with no editor call) or of its photo, less
    the photo (``"photo"``). The pairs of half the editor's ``batch`` views go in one call
    (one view's pair where that is under 2), so a call edits no more images than the
    editor's own (its ``batch`` is the editor's: views at its size are edited as before).
    :attr:`measuring` is the single-edit :class:`DetailTargets`: the identity check and the
    difficulty oracle edit with it, so they measure the editor, not the pairing."""

    def __init__(self, editor, reference: str = "render"):
        super().__init__(editor)
        if reference not in ("render", "photo"):
            raise DataError("reference", f"must be 'render' or 'photo', got {reference!r}")
        self.reference = reference

    def __repr__(self):
        return f"DeltaTargets({self.editor!r}, reference={self.reference!r})"

    @property
    def measuring(self):
        return DetailTargets(self.editor)

    def edit_many(self, images, originals, embeddings, keys, **kwargs):
        """Paired edits composed as above for views larger than the editor's size (else the
        editor's edit); ``embeddings`` [77, D] or [B, 77, D]; float32 [B, H, W, 3]."""
        from .jax_ip2p import resize_images

        images = jnp.asarray(images, jnp.float32)
        hw = self._smaller(*images.shape[1:3])
        if hw is None:
            return self.editor.edit_many(images, originals, embeddings, keys, **kwargs)
        b = images.shape[0]
        emb, null = _per_view(self.editor, embeddings, b)
        if self.reference == "render" and bool(jnp.all(emb == null)):
            return jnp.clip(images, 0.0, 1.0)  # e(0): the change is zero
        small = resize_images(images, hw)
        orig = resize_images(jnp.asarray(originals, jnp.float32), hw)
        ref = small if self.reference == "render" else orig
        nulls = jnp.broadcast_to(null, emb.shape)
        pair = lambda x, y: jnp.concatenate([x, y])  # noqa: E731
        per = max(1, int(getattr(self.editor, "batch", 1)) // 2)
        parts = []
        for lo in range(0, b, per):
            at = slice(lo, min(lo + per, b))
            edited = self.editor.edit_many(pair(small[at], ref[at]), pair(orig[at], orig[at]),
                                           pair(emb[at], nulls[at]), pair(keys[at], keys[at]),
                                           **kwargs)
            n = at.stop - lo
            # the change from small + (e(0)'s edit of ref - ref): e(0)'s identity error
            base = edited[n:] if self.reference == "render" else small[at] + edited[n:] - ref[at]
            parts.append(compose_target(images[at], base, edited[:n]))
        return parts[0] if len(parts) == 1 else jnp.concatenate(parts)


def measuring_editor(editor):
    """The editor an identity check and a difficulty oracle edit with: a composition's
    single-edit :attr:`~DetailTargets.measuring`, else ``editor``."""
    return editor.measuring if isinstance(editor, DetailTargets) else editor


def with_targets(editor, targets: str):
    """``editor`` making larger views' targets as ``targets`` says (one of :data:`TARGETS`):
    every one but "stretch" wraps an editor that has a model size (others, e.g. the
    simulated editor, edit at the view's size and are returned as they are)."""
    if targets not in TARGETS:
        raise DataError("targets", f"must be one of {', '.join(TARGETS)}, got {targets!r}")
    if targets == "stretch" or not hasattr(editor, "model_hw"):
        return editor
    if targets in ("delta", "anchored"):
        return DeltaTargets(editor, "render" if targets == "delta" else "photo")
    return DetailTargets(editor, keep_null=targets == "hybrid")
