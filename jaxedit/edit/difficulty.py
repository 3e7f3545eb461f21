"""Subtask difficulty d(r_a, r_b) of ProEdit (paper eq. 3), with memoised edits.

    d(r_a, r_b) = sum_{k in V} dist(T2D(v_k(s), e(r_a)), T2D(v_k(s), e(r_b)))

where v_k(s) are renders (or photos) of the ORIGINAL scene, T2D the 2D editor and e(r) the
interpolated embedding, so d is known before editing starts. ``dist`` is any
``(img_a float [H, W, 3], img_b float [H, W, 3]) -> float`` (LPIPS or MS-SSIM). The
:class:`DifficultyOracle` memoises the edit of every (ratio, view) pair.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import jax
import numpy as np
from skimage.metrics import structural_similarity

from ..errors import DataError
from ..editors.base import edit_views, editor_guidance, interpolate_embedding
from ..editors.keys import quantize_ratio, view_key

Distance = Callable[[np.ndarray, np.ndarray], float]


def _pool2(x: np.ndarray) -> np.ndarray:
    h, w = (x.shape[0] // 2) * 2, (x.shape[1] // 2) * 2
    x = x[:h, :w]
    return 0.25 * (x[0::2, 0::2] + x[1::2, 0::2] + x[0::2, 1::2] + x[1::2, 1::2])


def ms_ssim_distance(a, b, *, levels: int = 3, win_size: int = 7) -> float:
    """1 - SSIM averaged over an image pyramid of ``levels`` scales (2x2 mean pooling).

    Args:
      a, b: float [H, W, 3] (or [H, W]) in [0, 1], same shape.
      levels: pyramid depth; scales smaller than ``win_size`` pixels are skipped.
      win_size: odd side of SSIM's uniform window (scikit-image's default 7).

    Returns a float >= 0, 0 for identical images (a mean, not MS-SSIM's product, so a
    negative coarse-scale SSIM stays well defined).
    """
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    if a.shape != b.shape:
        raise DataError("distance", f"image shapes differ: {a.shape} vs {b.shape}")
    if min(a.shape[:2]) < win_size:
        raise DataError("distance", f"images of {a.shape[:2]} are smaller than the SSIM window "
                        f"{win_size}")
    channel_axis = -1 if a.ndim == 3 else None
    values = []
    for _ in range(levels):
        if min(a.shape[:2]) < win_size:
            break
        values.append(structural_similarity(a, b, data_range=1.0, win_size=win_size,
                                            channel_axis=channel_axis))
        a, b = _pool2(a), _pool2(b)
    return float(1.0 - np.mean(values))


def l1_distance(a, b) -> float:
    """Mean absolute difference of two images (a cheap, non-perceptual alternative)."""
    return float(np.mean(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))))


DISTANCES = ("auto", "lpips", "ms-ssim")


def lpips_weights_to_use(choice: str = "auto", lpips_weights=None):
    """Which LPIPS weights file the difficulty uses -> Path, or None for MS-SSIM.

    Args:
      choice: "auto" or "lpips" (``lpips_weights``, else the bundled AlexNet) or "ms-ssim".
      lpips_weights: a weights file written by ``convert-lpips`` (e.g. LPIPS-VGG).
    """
    from ..io.weights import bundled_lpips_weights

    if choice not in DISTANCES:
        raise DataError("distance", f"must be one of {', '.join(DISTANCES)}, got {choice!r}")
    if choice == "ms-ssim":
        if lpips_weights is not None:
            raise DataError("lpips_weights", "given with distance ms-ssim")
        return None
    if lpips_weights is not None:
        return Path(lpips_weights)  # an explicit file must exist: the loader says so if not
    return bundled_lpips_weights()


def default_distance(choice: str = "auto", lpips_weights=None) -> Distance:
    """The difficulty distance: LPIPS (the paper's), or MS-SSIM when asked for.

    Arguments as :func:`lpips_weights_to_use`. The result has a ``name`` or ``__name__``
    ("lpips-alex", "lpips-vgg", "ms_ssim_distance") that schedule.json records.
    """
    path = lpips_weights_to_use(choice, lpips_weights)
    if path is None:
        return ms_ssim_distance
    from ..lpips import lpips_distance

    return lpips_distance(path)


#: Difficulty views by default: every training view up to this many, else a seeded subset
#: of this size (an editor call per view and ratio).
DIFFICULTY_VIEWS = 16
#: fold_in purpose of the difficulty view subset's key.
_DIFFICULTY_VIEWS_KEY = 5


def difficulty_view_subset(num_views: int, count: int | None, key) -> tuple[int, ...]:
    """The fixed, seeded subset of ``count`` view indices (sorted) the difficulty is taken over.

    ``count`` None: all views up to :data:`DIFFICULTY_VIEWS`; a subset depends on ``key`` only.
    """
    if num_views <= 0:
        raise DataError("views", "need at least one original view")
    count = min(num_views, DIFFICULTY_VIEWS if count is None else int(count))
    if count >= num_views:
        return tuple(range(num_views))
    chosen = jax.random.choice(jax.random.fold_in(key, _DIFFICULTY_VIEWS_KEY), num_views,
                               (count,), replace=False)
    return tuple(sorted(int(v) for v in np.asarray(chosen)))


class DifficultyOracle:
    """d(r_a, r_b) of one instruction over a subset of original views, memoised.

    Args:
      editor: any :class:`jaxedit.editors.Editor`.
      originals: float [N, H, W, 3], renders (or photos) of the original scene, v_k(s).
      prompt: the instruction p; e(r) = interpolate_embedding(E(p), E(""), r).
      views: indices of the views V (default: :func:`difficulty_view_subset` of ``seed``).
      distance: ``(img_a, img_b) -> float``; default :func:`ms_ssim_distance`.
      timestep_range: the editor's SDEdit range (default (0.98, 0.98): a full-strength edit).
      guidance: the editor's (text, image) guidance scales (None: its own).
      seed: seeds the edits' fixed keys, so d(r, r) = 0 and answers repeat.
      common_noise: one key per view shared by all ratios (default), so d measures how the
        edit changes with r; False: a key per (view, ratio), adding the editor's seed noise.
      reduction: "mean" over views (default: eq. 3's sum / |V|) or "sum" (eq. 3 as printed).
      embeddings: (E(p), E("")) already encoded (None: the oracle encodes ``prompt``).

    Attributes:
      editor_calls: views edited so far (distinct (ratio, view) pairs).
      evaluations: number of distinct (r_a, r_b) pairs evaluated.
    """

    def __init__(self, editor, originals, prompt: str, *, views: Sequence[int] | None = None,
                 distance: Distance | None = None,
                 timestep_range: tuple[float, float] = (0.98, 0.98),
                 guidance: tuple[float, float] | None = None, seed: int = 0,
                 reduction: str = "mean", common_noise: bool = True, embeddings=None):
        originals = np.asarray(originals, np.float32)
        if originals.ndim != 4 or originals.shape[-1] != 3:
            raise DataError("originals",
                            f"expected float [N, H, W, 3], got shape {originals.shape}")
        if reduction not in ("sum", "mean"):
            raise DataError("reduction", f"must be 'sum' or 'mean', got {reduction!r}")
        self.editor = editor
        self.originals = originals
        self.prompt = prompt
        self.views = (difficulty_view_subset(len(originals), None, jax.random.key(int(seed)))
                      if views is None else tuple(int(v) for v in views))
        bad = [v for v in self.views if not 0 <= v < len(originals)]
        if bad or not self.views:
            raise DataError("views", f"indices must be in 0..{len(originals) - 1}, "
                            f"got {list(self.views)}")
        self.distance = ms_ssim_distance if distance is None else distance
        self.timestep_range = tuple(timestep_range)
        self.guidance = editor_guidance(editor, guidance)
        self.reduction = reduction
        self.common_noise = bool(common_noise)
        self._run_key = jax.random.key(int(seed))
        self._e_prompt, self._e_null = ((editor.encode(prompt), editor.encode(""))
                                        if embeddings is None else embeddings)
        self._images: dict[tuple[int, int], np.ndarray] = {}
        self._pairs: dict[tuple[int, int], float] = {}
        self.editor_calls = 0

    @property
    def evaluations(self) -> int:
        return len(self._pairs)

    def _edit(self, q: int, views) -> None:
        """Edit the ``views`` not yet edited at ratio ``q`` / 1e6 (in the editor's batches,
        :func:`jaxedit.editors.base.edit_views`) into the memo."""
        missing = [int(k) for k in dict.fromkeys(views) if (q, int(k)) not in self._images]
        if not missing:
            return
        r = q / 1e6
        emb = interpolate_embedding(self._e_prompt, self._e_null, r)
        keys = [view_key(self._run_key, k, 0.0 if self.common_noise else r, 0) for k in missing]
        photos = [self.originals[k] for k in missing]
        edited = edit_views(self.editor, photos, photos, emb, keys,
                            timestep_range=self.timestep_range, guidance=self.guidance)
        for k, image in zip(missing, edited):
            self._images[(q, k)] = np.asarray(image, np.float32)
        self.editor_calls += len(missing)

    def edited(self, ratio: float, view: int) -> np.ndarray:
        """T2D(v_k(s), e(r)) for view index ``view``, edited at most once (memoised)."""
        q = quantize_ratio(ratio)
        self._edit(q, [view])
        return self._images[(q, int(view))]

    def __call__(self, r_a: float, r_b: float) -> float:
        """d(r_a, r_b) >= 0, symmetric, d(r, r) = 0."""
        qa, qb = sorted((quantize_ratio(r_a), quantize_ratio(r_b)))
        if qa == qb:
            return 0.0
        hit = self._pairs.get((qa, qb))
        if hit is None:
            for q in (qa, qb):  # every view of a ratio in one go: the editor may batch them
                self._edit(q, self.views)
            ds = [float(self.distance(self.edited(qa / 1e6, k), self.edited(qb / 1e6, k)))
                  for k in self.views]
            hit = float(np.sum(ds) if self.reduction == "sum" else np.mean(ds))
            self._pairs[(qa, qb)] = hit
        return hit

    def edited_ratios(self) -> list[float]:
        """The ratios whose every view is edited already (d between them costs no editor call)."""
        counts: dict[int, int] = {}
        for q, k in self._images:
            if k in self.views:
                counts[q] = counts.get(q, 0) + 1
        return sorted(q / 1e6 for q, n in counts.items() if n >= len(set(self.views)))

    def fingerprint(self) -> str:
        """A digest of what the answers depend on (editor inputs, embeddings, keys, views,
        distance): two oracles of one fingerprint give the same d."""
        import hashlib

        h = hashlib.sha256()
        for part in (self.originals, np.asarray(self._e_prompt, np.float32),
                     np.asarray(self._e_null, np.float32),
                     np.asarray(jax.random.key_data(self._run_key))):
            h.update(np.ascontiguousarray(part).tobytes())
        h.update(repr((self.views, self.timestep_range, tuple(self.guidance), self.reduction,
                       self.common_noise, getattr(self.editor, "name", type(self.editor).__name__),
                       getattr(self.distance, "name", getattr(self.distance, "__name__", ""))
                       )).encode())
        return h.hexdigest()

    def memo(self) -> dict[str, np.ndarray]:
        """The edits (float16: half the bytes, well under a uint8 step) and distances computed
        so far, as arrays (:meth:`restore` reads them)."""
        keys = sorted(self._images)
        pairs = sorted(self._pairs)
        shape = (0,) + self.originals.shape[1:]
        return {"fingerprint": np.asarray(self.fingerprint()),
                "image_keys": np.asarray(keys, np.int64).reshape(-1, 2),
                "images": (np.stack([self._images[k] for k in keys]).astype(np.float16) if keys
                           else np.zeros(shape, np.float16)),
                "pair_keys": np.asarray(pairs, np.int64).reshape(-1, 2),
                "pairs": np.asarray([self._pairs[k] for k in pairs], np.float64)}

    def restore(self, memo) -> bool:
        """Take the edits and distances of another oracle's :meth:`memo` if it had this
        fingerprint (then no editor call repeats them); returns whether it did."""
        if str(np.asarray(memo["fingerprint"])) != self.fingerprint():
            return False
        for (q, k), image in zip(np.asarray(memo["image_keys"]), np.asarray(memo["images"])):
            self._images.setdefault((int(q), int(k)), np.asarray(image, np.float32))
        for (qa, qb), d in zip(np.asarray(memo["pair_keys"]), np.asarray(memo["pairs"])):
            self._pairs.setdefault((int(qa), int(qb)), float(d))
        return True

    def curve(self, ratios: Sequence[float]) -> list[tuple[float, float]]:
        """[(r, d(0, r))] for plotting the difficulty curve (schedule.json's difficulty_curve)."""
        return [(float(r), self(0.0, r)) for r in ratios]
