"""Which outcome an edit shows: one of the K outcomes, the unedited input, a mix, or other.

The old measure (nearest outcome target by PSNR, "mixed" when the outcomes' average is
nearer) cannot be trusted: an *unedited* input is already nearest some outcome, and nearer
their average than any single one whenever the outcomes recolour different parts of the
view (issue 51: 52 % of unedited splash views counted as "mixed"). This one measures every
edit against the unedited input, the baseline every outcome starts from.

For a view with input ``u``, outcome targets ``t_1 .. t_K`` and an edited image ``x`` (all
[H, W, 3] in [0, 1], flattened):

- the edit's change ``d = x - u``, each outcome's change ``D_k = t_k - u``;
- weights ``w >= 0`` minimising ``|d - sum_k w_k D_k|`` (non-negative least squares): how
  far the edit went along each outcome (``w_k = 1``: all the way to ``t_k``);
- ``progress = sum_k w_k``, ``purity = max_k w_k / progress``, and ``residual`` = RMS of
  the part of ``d`` no outcome explains, over the RMS of a typical outcome change
  (``sqrt(mean_k mean(D_k^2))``).

The class, in this order:

1. ``"other"``: ``residual > OTHER_RESIDUAL`` (the edit changed the view, in a way no blend
   of outcomes explains, by more than a typical outcome changes it: a colour cast, a lost
   structure). The VAE round trip alone, the floor of any latent-diffusion edit, leaves
   0.2-0.8 of it on the bundled editor's held-out views (probed on 32 view-instruction
   pairs), so an edit the VAE alone made is never "other";
2. ``"unedited"``: ``progress < EDITED_PROGRESS`` (it went less than half-way towards the
   outcomes: the input, or the input with the VAE's noise);
3. outcome ``k`` (an int): ``purity >= PURE_SHARE`` (outcome k carries at least two thirds
   of the change: twice the rest together);
4. ``"mixed"``: the rest (a blend, e.g. half one outcome and half another: purity 1/2).

So the unedited input is ``"unedited"`` (d = 0), a pure target ``t_k`` is ``k`` (w = e_k),
and a 50/50 blend of two targets is ``"mixed"`` (w = 1/2, 1/2), whatever the targets.

:func:`summarise` gives the figures over a set of draws: ``unedited_fraction`` over all of
them, and over the *edited* ones only (every class but unedited) ``single_outcome_fraction``
(one outcome), ``outcome_frequencies`` [K], ``mixed_fraction`` and ``other_fraction``.
Given which view each draw edits, it adds ``intervals``: 95 % percentile intervals of the
one-outcome share and of each outcome's frequency from a bootstrap that resamples *views*
(a view's draws start from the same image and lean alike, so they are not independent draws;
resampling draws would make the intervals too narrow). With a few dozen views the interval
of a frequency spans about +-10 points: it says whether a figure near a goal's edge is a miss
or sampling noise.

Pooled shares can still be fooled: a model that always gives view A outcome 0 and view B
outcome 1 has balanced frequencies and one outcome in every draw, yet it picks by the view,
not by the noise. :func:`view_spread` tells the two apart: over the views with at least two
draws on an outcome, the share whose draws land on more than one outcome, beside the share
expected if every draw picked independently with the pooled frequencies (0 for a choice by
view, whatever the pooled shares).
"""

from __future__ import annotations

from collections import Counter
from typing import Sequence

import numpy as np
from scipy.optimize import nnls

from jaxedit.metrics import percentile_interval

UNEDITED, MIXED, OTHER = "unedited", "mixed", "other"
#: Below this total weight along the outcomes (a fraction of one outcome's change) the
#: view is unedited.
EDITED_PROGRESS = 0.5
#: The dominant outcome's share of the total weight from which the view shows one outcome.
PURE_SHARE = 2.0 / 3.0
#: Above this unexplained change (RMS, over a typical outcome change's RMS) the view is
#: "other".
OTHER_RESIDUAL = 1.0

#: Resamples of the views' bootstrap, and its interval's level.
BOOTSTRAP, LEVEL = 10_000, 0.95

__all__ = ["BOOTSTRAP", "EDITED_PROGRESS", "LEVEL", "MIXED", "OTHER", "OTHER_RESIDUAL",
           "PURE_SHARE", "UNEDITED", "classify", "classify_many", "summarise", "view_spread"]


def classify(image, original, targets, *, other_gate: bool = True) -> dict:
    """The class of one edited view (module docstring): ``image``, ``original`` [H, W, 3],
    ``targets`` [K, H, W, 3]. Returns {"label": k (int) | "unedited" | "mixed" | "other",
    "weights": [K], "progress", "purity", "residual"}. ``other_gate`` False skips rule 1
    (where an edit leans, however much else it changed)."""
    u = np.asarray(original, np.float64).reshape(-1)
    d = np.asarray(image, np.float64).reshape(-1) - u
    t = np.asarray(targets, np.float64)
    D = t.reshape(t.shape[0], -1) - u  # [K, P]
    scale = np.sqrt(np.mean(D ** 2, axis=1))  # RMS of each outcome's change
    if not np.all(scale > 1e-6):
        raise ValueError("an outcome target equals the input on this view: the view cannot "
                         "tell that outcome from no edit")
    w, _ = nnls(D.T, d)
    residual = float(np.sqrt(np.mean((d - w @ D) ** 2)) / np.sqrt(np.mean(scale ** 2)))
    progress = float(w.sum())
    purity = float(w.max() / progress) if progress > 0 else 1.0
    if other_gate and residual > OTHER_RESIDUAL:
        label = OTHER
    elif progress < EDITED_PROGRESS:
        label = UNEDITED
    elif purity >= PURE_SHARE:
        label = int(np.argmax(w))
    else:
        label = MIXED
    return {"label": label, "weights": [float(x) for x in w], "progress": progress,
            "purity": purity, "residual": residual}


def classify_many(images, originals, targets, *, other_gate: bool = True) -> list:
    """Labels of B views: images, originals [B, H, W, 3], targets [B, K, H, W, 3]."""
    return [classify(x, u, t, other_gate=other_gate)["label"]
            for x, u, t in zip(images, originals, targets)]


def summarise(labels: Sequence, k: int, groups: Sequence | None = None, *, seed: int = 0,
              resamples: int = BOOTSTRAP) -> dict:
    """The figures of a set of draws' labels (module docstring); K outcomes. Fractions over
    the edited draws are None when no draw was edited. ``groups`` (one per label: the view
    each draw edits) adds ``intervals`` from ``resamples`` bootstrap draws of the views,
    seeded by ``seed``."""
    counts = Counter(labels)
    n = len(labels)
    edited = n - counts[UNEDITED]

    def over_edited(c):
        return float(c) / edited if edited else None

    out = {"draws": n, "edited": edited,
           "unedited_fraction": float(counts[UNEDITED]) / n if n else None,
           "single_outcome_fraction": over_edited(sum(counts[i] for i in range(k))),
           "outcome_frequencies": [over_edited(counts[i]) for i in range(k)],
           "mixed_fraction": over_edited(counts[MIXED]),
           "other_fraction": over_edited(counts[OTHER])}
    if groups is not None:
        out["intervals"] = _view_bootstrap(labels, groups, k, seed, resamples)
    return out


def _is_outcome(label, k: int) -> bool:
    """Whether a label is one of the K outcomes (not unedited, mixed or other)."""
    return isinstance(label, (int, np.integer)) and 0 <= label < k


def _check_groups(labels: Sequence, groups: Sequence) -> None:
    if len(groups) != len(labels):
        raise ValueError(f"{len(groups)} groups for {len(labels)} labels")


def view_spread(labels: Sequence, groups: Sequence, k: int) -> dict:
    """Whether an outcome is the draw's or the view's (module docstring): ``labels`` and
    ``groups`` (the view each draw edits) as for :func:`summarise`. Over the views with at
    least two draws on one of the K outcomes: {"views": how many, "spread": the share whose
    outcome draws are not all one outcome, "expected": that share if each draw picked
    independently with the outcome frequencies pooled over those views}; both None without
    such a view."""
    _check_groups(labels, groups)
    per_view: dict = {}
    for g, label in zip(groups, labels):
        if _is_outcome(label, k):
            per_view.setdefault(g, []).append(int(label))
    chosen = [v for v in per_view.values() if len(v) >= 2]
    if not chosen:
        return {"views": 0, "spread": None, "expected": None}
    pooled = np.bincount(np.concatenate(chosen), minlength=k) / sum(map(len, chosen))
    # P(m independent draws not all one outcome) = 1 - sum_k p_k^m, averaged over the views.
    expected = np.mean([1.0 - np.sum(pooled ** len(v)) for v in chosen])
    spread = np.mean([len(set(v)) > 1 for v in chosen])
    return {"views": len(chosen), "spread": float(spread), "expected": float(expected)}


def _view_bootstrap(labels: Sequence, groups: Sequence, k: int, seed: int,
                    resamples: int) -> dict:
    """Percentile intervals of ``single_outcome_fraction`` and ``outcome_frequencies`` over
    ``resamples`` resamples of the views (``groups``, one per label) with replacement; a
    resample without an edited draw is left out. {"level", "resamples", "views",
    "single_outcome_fraction": [low, high], "outcome_frequencies": [[low, high]] * K}."""
    _check_groups(labels, groups)
    views, view_of = np.unique(np.asarray(groups), return_inverse=True)
    # Per view: its draws in each outcome (columns 0..K-1) and its edited draws (column K).
    per_view = np.zeros((len(views), k + 1))
    for v, label in zip(view_of, labels):
        if label != UNEDITED:
            per_view[v, k] += 1
            if _is_outcome(label, k):
                per_view[v, label] += 1
    pick = np.random.default_rng(seed).integers(0, len(views), (resamples, len(views)))
    sums = per_view[pick].sum(1)  # [R, K + 1]
    sums = sums[sums[:, k] > 0]
    if not len(sums):
        return {"level": LEVEL, "resamples": 0, "views": int(len(views)),
                "single_outcome_fraction": None, "outcome_frequencies": [None] * k}
    freqs = sums[:, :k] / sums[:, k:]
    return {"level": LEVEL, "resamples": int(len(sums)), "views": int(len(views)),
            "single_outcome_fraction": percentile_interval(freqs.sum(1), level=LEVEL),
            "outcome_frequencies": [percentile_interval(freqs[:, i], level=LEVEL)
                                    for i in range(k)]}
