"""What an edit may turn into (its outcomes) and how a result is scored against them.

An instruction has K valid outcomes (one for a deterministic edit). The ablation scores the
held-out renders of every run against the outcomes' noise-free targets at r = 1:

- :func:`outcome_scores`: ``psnr_best`` (PSNR to the best single outcome, mean over the
  held-out views), ``mode_mixing`` (0: one outcome, 1: an even blend,
  :func:`jaxedit.metrics.mode_scores`) and ``outcome_agreement``: each held-out render is
  classified to its nearest outcome target (PSNR), and the agreement is the fraction of views
  in the most common class (1: every view shows the same outcome; 1/K at worst);
- :func:`outcome_targets`: the targets of an editor's outcomes for views: the editor's own
  ``mode_targets`` where it has them (the simulated editor, test editors), else the bundled
  InstructPix2Pix's training outcomes (:mod:`jaxedit_lab.train_editor.edit_data`),
  made again for the views of a procedural scene: its image outcomes from the scene's renders with coverage, its
  local and geometry outcomes by rendering the edited scene.
- :class:`FixedTargets`: an "editor" that returns one outcome's target for every view, for
  the ceiling reference (a scene trained directly on one outcome's targets).
"""

from __future__ import annotations

import numpy as np

from jaxedit.errors import DataError
from jaxedit.metrics import mode_scores, psnr


def outcome_scores(renders, targets) -> dict:
    """Scores of renders [M, H, W, 3] against outcome targets [K, M, H, W, 3] (see the module
    docstring); also ``outcome_of_view`` (the nearest outcome of each view)."""
    renders, targets = np.asarray(renders, np.float32), np.asarray(targets, np.float32)
    scores = mode_scores(renders, targets)
    nearest = [int(np.argmax([float(psnr(renders[v], targets[k, v]))
                              for k in range(targets.shape[0])]))
               for v in range(renders.shape[0])]
    counts = np.bincount(nearest, minlength=targets.shape[0])
    return {"psnr_best": float(scores["psnr_best"]), "ssim_best": float(scores["ssim_best"]),
            "mode": int(scores["mode"]), "psnr_per_mode": [float(x) for x in scores["psnr_per_mode"]],
            "mode_mixing": float(scores["mode_mixing"]),
            "outcome_agreement": float(counts.max()) / len(nearest),
            "outcome_of_view": nearest}


def outcome_targets(editor, prompt: str, images, *, scene_name: str | None = None,
                    dataset=None, indices=None, scene_seed: int = 0) -> np.ndarray:
    """float32 [K, N, H, W, 3]: every outcome of ``prompt`` for ``images`` [N, H, W, 3].

    ``editor.mode_targets(original, 1.0, prompt)`` where the editor has it; otherwise the
    bundled editor's outcomes (:mod:`jaxedit_lab.train_editor.edit_data`) for the views
    ``indices`` of ``dataset``, a procedural built-in scene ``scene_name`` made with ``scene_seed``.
    """
    if hasattr(editor, "mode_targets"):
        return np.stack([editor.mode_targets(o, 1.0, prompt) for o in images],
                        axis=1).astype(np.float32)
    from jaxedit_lab.train_editor import edit_data
    from jaxedit.scenes import get_scene, library, render_scene

    ins = edit_data.instruction(prompt)
    if scene_name is None or dataset is None or scene_name in library.DATASETS:
        raise DataError("scenes", f"the outcomes of {prompt!r} are made again from a procedural "
                                  f"scene's renders; {scene_name!r} is not one")
    if not ins.applies_to(scene_name):
        raise DataError("prompts", f"{prompt!r} does not apply to the {scene_name} scene "
                                   f"(only {', '.join(ins.scenes)})")
    scene = get_scene(scene_name, scene_seed)
    cameras = dataset.cameras
    rgba = render_scene(scene, cameras, alpha=True)  # every view: the luma bands of the scene
    idx = np.asarray(indices)
    if ins.kind in ("local", "geometry"):
        edited = render_scene(edit_data._edited_scene(scene, prompt), cameras[idx])
        return np.asarray(edited, np.float32)[None]
    bands = edit_data.luma_bands(rgba)
    return np.stack([edit_data.apply_image_outcome(prompt, name, rgba[idx, ..., :3],
                                                   rgba[idx, ..., 3], bands)
                     for name in ins.outcomes]).astype(np.float32)


class FixedTargets:
    """An editor whose every edit is outcome ``k``'s target of the view (found by its original
    photo): trains a scene directly on one outcome (the ceiling reference)."""

    def __init__(self, editor, originals, targets):
        self.editor = editor
        self._originals = np.asarray(originals, np.float32)
        self._targets = np.asarray(targets, np.float32)

    def encode(self, prompt: str):
        return self.editor.encode(prompt)

    def edit(self, image, original, embedding, key, **kwargs):
        o = np.asarray(original, np.float32)
        if o.shape != self._originals.shape[1:]:
            raise ValueError(f"FixedTargets: an original of shape {o.shape}, the views are "
                             f"{self._originals.shape[1:]}")
        # the training view whose photo it is (the nearest: callers may hand over a copy)
        view = int(np.argmin(np.mean((self._originals - o) ** 2, axis=(1, 2, 3))))
        return self._targets[view]
