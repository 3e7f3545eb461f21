"""The editor's identity on a scene: does e(0) give back the views it is shown (else r_0
moves the scene before the instruction begins)?"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from ..errors import DataError, check_ranges, ranged
from .outputs import bundled_lpips, image_scores


@dataclasses.dataclass(frozen=True)
class IdentityFloor:
    """What an editor's identity on the scene must clear before an edit trains.

    Attributes:
      min_psnr: lowest identity PSNR (dB) of e(0)'s edits against the renders.
      max_lpips: highest identity LPIPS (AlexNet) of those edits against the renders.
      accept_low: go on (with a warning) when the identity is under the floor.
      refine_min_psnr: r_0 snapshot's PSNR (dB) vs the input's renders under which the log warns.
    """

    min_psnr: float = ranged(18.0, low=0.0)
    max_lpips: float = ranged(0.35, low=0.0)
    accept_low: bool = False
    refine_min_psnr: float = ranged(28.0, low=0.0)

    def __post_init__(self):
        check_ranges(self)


class LowIdentityError(DataError):
    """The editor does not reproduce the scene's views at e(0). ``figures``:
    :func:`measure_identity`'s record; ``record``: its file (None: not written)."""

    def __init__(self, where, problem: str, figures: dict):
        super().__init__(where, problem)
        self.figures = figures
        self.record = None


def measure_identity(oracle, photos: np.ndarray | None = None, *,
                     lpips: Callable | None = None) -> dict:
    """Score e(0)'s edits of the difficulty views (the oracle's own, reused by d(0, r))
    against the render, or the photo where that is nearer.

    Args:
      oracle: a :class:`jaxedit.edit.difficulty.DifficultyOracle` of the input's renders.
      photos: float [N, H, W, 3], the training views' photos (None: renders only).
      lpips: ``(a, b) -> float`` (None: the bundled LPIPS-AlexNet).
    Returns:
      {"psnr", "lpips" (means of each view's better score), "psnr_per_view",
      "lpips_per_view", "psnr_vs_renders", "lpips_vs_renders", "psnr_vs_photos",
      "lpips_vs_photos" (None without ``photos``), "views", "timestep", "editor_calls"}.
    """
    lpips = bundled_lpips() if lpips is None else lpips
    views = [int(k) for k in oracle.views]
    calls = oracle.editor_calls
    edited = [oracle.edited(0.0, k) for k in views]
    calls = oracle.editor_calls - calls

    def scores(refs):
        return ([image_scores(e[None], np.asarray(refs[k])[None])["psnr"]
                 for e, k in zip(edited, views)],
                [float(lpips(e, refs[k])) for e, k in zip(edited, views)])

    psnr_r, lp_r = scores(oracle.originals)
    psnr_o, lp_o = scores(photos) if photos is not None else (psnr_r, lp_r)
    psnr = [max(a, b) for a, b in zip(psnr_r, psnr_o)]
    lp = [min(a, b) for a, b in zip(lp_r, lp_o)]
    return {"psnr": float(np.mean(psnr)), "lpips": float(np.mean(lp)),
            "psnr_per_view": psnr, "lpips_per_view": lp,
            "psnr_vs_renders": float(np.mean(psnr_r)), "lpips_vs_renders": float(np.mean(lp_r)),
            "psnr_vs_photos": None if photos is None else float(np.mean(psnr_o)),
            "lpips_vs_photos": None if photos is None else float(np.mean(lp_o)),
            "views": views, "timestep": float(oracle.timestep_range[1]), "editor_calls": calls}


def identity_problem(figures: dict, floor: IdentityFloor) -> str | None:
    """What is wrong with ``figures`` (:func:`measure_identity`) under ``floor``, naming
    the figure and the floor (None: it clears the floor)."""
    problems = []
    if figures["psnr"] < floor.min_psnr:
        problems.append(f"PSNR {figures['psnr']:.1f} dB < floor {floor.min_psnr:g} dB")
    if figures["lpips"] > floor.max_lpips:
        problems.append(f"LPIPS {figures['lpips']:.3f} > ceiling {floor.max_lpips:g}")
    return "; ".join(problems) or None


def identity_line(figures: dict) -> str:
    """The log's line of the check."""
    return (f"editor identity on this scene: PSNR {figures['psnr']:.1f} dB, LPIPS "
            f"{figures['lpips']:.3f} (e(0) at t = {figures['timestep']:.2f}, "
            f"{len(figures['views'])} difficulty views)")
