"""What an edit reads and never changes: its views (:class:`EditData`) and its run's
context (:class:`EditContext`), built by constructors so ``dataclasses.replace`` redoes nothing.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import DataError
from .hooks import NO_HOOKS, EditHooks
from .outputs import Renderer
from .plan import ProEditConfig
from .trainer import SubtaskTrainer


@dataclasses.dataclass(frozen=True)
class EditData:
    """Views of the scene being edited (build with :meth:`create` or :meth:`from_dataset`).

    Attributes:
      train_images: float32 [N, H, W, 3], the original photos of the training views (an
        array, or :class:`jaxedit.io.views.FloatViews` of 8-bit photos kept as uint8).
      train_cameras: batched Camera [N], on the device.
      test_images: float32 [M, H, W, 3], held-out originals (never trained on; likewise).
      test_cameras: batched Camera [M].
    """

    train_images: np.ndarray
    train_cameras: Any
    test_images: np.ndarray
    test_cameras: Any

    @staticmethod
    def create(train_images: np.ndarray, train_cameras, test_images: np.ndarray,
               test_cameras) -> "EditData":
        """The views, checked, with the cameras put on the device once."""
        if train_images.ndim != 4 or train_images.shape[-1] != 3:
            raise DataError("train_images", f"need float [N, H, W, 3], got {train_images.shape}")
        if len(train_cameras) != len(train_images):
            raise DataError("train_cameras", f"{len(train_cameras)} cameras for "
                                             f"{len(train_images)} images")
        if len(test_cameras) != len(test_images):
            raise DataError("test_cameras", f"{len(test_cameras)} cameras for "
                                            f"{len(test_images)} images")
        return EditData(train_images, jax.device_put(train_cameras), test_images,
                        jax.device_put(test_cameras))

    @staticmethod
    def from_dataset(dataset) -> "EditData":
        """From a :func:`jaxedit.io.load_nerfstudio` dataset (train/test split), its views
        kept as loaded (uint8) and read as float32."""
        from ..io.views import FloatViews

        pixels = np.asarray(dataset.pixels)
        train = np.asarray(dataset.train_indices)
        test = np.asarray(dataset.test_indices)
        if len(test) == 0:  # no held-out split: score on the training views, say so
            test = train
        return EditData.create(FloatViews(pixels[train]), dataset.cameras[train],
                               FloatViews(pixels[test]), dataset.cameras[test])


def encode_prompt(editor, prompt: str) -> tuple[np.ndarray, np.ndarray]:
    """(E(p), E("")): the editor's embeddings of ``prompt`` and of "", NumPy, the editor's
    shape ([77, D] for InstructPix2Pix). The one place a run encodes its prompt."""
    return np.asarray(editor.encode(prompt)), np.asarray(editor.encode(""))


@dataclasses.dataclass(frozen=True)
class EditContext:
    """Everything a run reads but never changes (build with :meth:`create`).

    Attributes:
      editor: an :class:`jaxedit.editors.Editor`.
      prompt: the instruction p.
      data: the views (:class:`EditData`).
      config: :class:`ProEditConfig`, as given (resolved per subtask by
        :func:`jaxedit.edit.plan.subtask_limits`).
      trainer: :class:`SubtaskTrainer`.
      renderer: :class:`Renderer` of the editor's inputs and the snapshots.
      key: the run key (``jax.random.key(seed)``).
      e_prompt: E(p), the editor's embedding of the prompt (NumPy).
      e_null: E("") (NumPy); a subtask at ratio r edits with e(r) = r E(p) + (1 - r) E("").
      editor_device: the editor's device (:func:`jaxedit.edit.buffer.pick_devices`).
      masks: float [N, H, W] on the device, a local edit's training masks, or None.
      hooks: a study's changes (:class:`jaxedit.edit.hooks.EditHooks`; none by default).
    """

    editor: Any
    prompt: str
    data: EditData
    config: ProEditConfig
    trainer: SubtaskTrainer
    renderer: Renderer
    key: jax.Array
    e_prompt: np.ndarray
    e_null: np.ndarray
    editor_device: Any = None
    masks: Any = None
    hooks: EditHooks = NO_HOOKS

    @staticmethod
    def create(editor, prompt: str, data: EditData, config: ProEditConfig,
               trainer: SubtaskTrainer, renderer: Renderer, key: jax.Array, editor_device=None,
               masks=None, embeddings: tuple[np.ndarray, np.ndarray] | None = None,
               hooks: EditHooks = NO_HOOKS) -> "EditContext":
        """The context of a run; ``embeddings``: (E(p), E("")) of :func:`encode_prompt`
        when already encoded (None: encoded here)."""
        e_prompt, e_null = encode_prompt(editor, prompt) if embeddings is None else embeddings
        return EditContext(editor, prompt, data, config, trainer, renderer, key,
                           e_prompt=e_prompt, e_null=e_null,
                           editor_device=editor_device,
                           masks=None if masks is None else jnp.asarray(masks, jnp.float32),
                           hooks=hooks)
