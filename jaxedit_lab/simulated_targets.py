"""Target families of the simulated editor: the noise-free ground truth of every instruction.

:mod:`jaxedit_lab.simulated` describes the model; this module is its part that says what each
edit family *should* produce. ``_target_family(original, kind, points, mode)`` returns the map
s -> T^k(s) from a strength s in [0, 1] (s = 0: the original, s = 1: the full target) to the
target image of one instruction kind and one divergent mode k (0 .. MAX_MODES - 1; mode 0 is the
single target of the editor with ``modes=1``):

=========  ===================================================================================
kind       full target of modes 0, 1, 2
=========  ===================================================================================
colour     affine colour grade with a gentle S-curve (``_autumn``): orange-red, golden, crimson
material   smoothed shading through a metal ramp + sheen inside the foreground (``_bronze``):
           polished bronze, verdigris, dark antique bronze
style      soft posterisation + outlines (``_cartoon``): neutral, cool and rose palettes
texture    veins stamped as a function of colour, or of the world point seen by the pixel
           (``_marble``), at phase offsets 0, 1/3, 2/3 in white, blue-grey and pink marble
shape      radial bulge of the head around its centroid (``_bulge``), amplitude s BULGE_MAX:
           round, taller, wider
local      the warm, coloured pixels only (:func:`orange_weight`) get their channels permuted
           (``_recolour``): blue (red and blue swapped), violet, green; the rest is the original
=========  ===================================================================================

Every target is a function of the content (colour) of each pixel through smooth functions, of
the object's silhouette (:func:`foreground`, :func:`head_mask`) or of the surface point, never
of the pixel position in the frame, so it is consistent across views. The image helpers they
share with the editor's perturbation (``_sample``) live here too; ``blur`` is the library's
(:func:`jaxedit.editors.masks.blur`). Everything is pure
JAX, traced inside the editor's compiled edit.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxedit.editors.masks import blur


# --------------------------------------------------------------------------------------------
# Image helpers (JAX, pure)


def _luma(x):
    """Rec. 601 luma of float [..., 3] -> [...]."""
    return 0.299 * x[..., 0] + 0.587 * x[..., 1] + 0.114 * x[..., 2]


def _smoothstep(e0, e1, x):
    t = jnp.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _sample(img, rows, cols):
    """Bilinear lookup of float [H, W, C] at float [H, W] pixel coordinates (edge clamped)."""
    coords = jnp.stack([rows, cols])
    return jnp.stack([jax.scipy.ndimage.map_coordinates(img[..., c], list(coords), order=1,
                                                        mode="nearest")
                      for c in range(img.shape[-1])], axis=-1)


def foreground(original, *, low: float = 0.03, high: float = 0.10):
    """Soft foreground mask float [H, W] in [0, 1] of float [H, W, 3].

    The background colour is the per-channel median of the border pixels; a pixel is foreground
    as its largest channel difference to it goes from ``low`` to ``high``.
    """
    border = jnp.concatenate([original[0], original[-1], original[:, 0], original[:, -1]])
    bg = jnp.median(border, axis=0)
    dist = jnp.max(jnp.abs(original - bg), axis=-1)
    return _smoothstep(low, high, blur(dist, 0.7))


def _centroid_radius(mask):
    """Centroid (row, col) and radius sqrt(area / pi) of a soft mask [H, W] (pixels)."""
    h, w = mask.shape
    rows, cols = jnp.meshgrid(jnp.arange(h) + 0.5, jnp.arange(w) + 0.5, indexing="ij")
    area = jnp.sum(mask)
    ok = area > 4.0  # an empty foreground falls back to the image centre
    safe = jnp.maximum(area, 1e-6)
    cr = jnp.where(ok, jnp.sum(mask * rows) / safe, h / 2.0)
    cc = jnp.where(ok, jnp.sum(mask * cols) / safe, w / 2.0)
    rad = jnp.where(ok, jnp.sqrt(safe / jnp.pi), 0.25 * min(h, w))
    return cr, cc, rad


# --------------------------------------------------------------------------------------------
# Full targets (r = 1 or strength s), one per kind. original: float [H, W, 3] in [0, 1].

_AUTUMN = np.array([[0.55, 0.55, 0.00],
                    [0.15, 0.55, 0.10],
                    [0.05, 0.15, 0.35]], np.float32)
_BRONZE = np.array([[0.16, 0.09, 0.04], [0.70, 0.43, 0.18], [1.00, 0.88, 0.60]], np.float32)
_MARBLE_BASE = np.array([0.93, 0.92, 0.89], np.float32)

# The divergent modes (jaxedit_lab.simulated, section 4). Mode 0 of every kind is the single
# target of the editor with ``modes=1``; the others are equally plausible, individually
# 3D-consistent alternatives (each is a function of the content, the silhouette or the surface
# point, like mode 0).
MAX_MODES = 3
_MODE_GRADES = (_AUTUMN,  # orange-red foliage
                np.array([[0.50, 0.50, 0.05],  # golden: yellow highlights, dim blue
                          [0.35, 0.50, 0.10],
                          [0.05, 0.10, 0.20]], np.float32),
                np.array([[0.50, 0.45, 0.05],  # crimson: redder, bluish shadows
                          [0.10, 0.45, 0.05],
                          [0.10, 0.20, 0.45]], np.float32))
_MODE_PATINAS = (_BRONZE,  # polished bronze
                 np.array([[0.06, 0.14, 0.12], [0.27, 0.55, 0.46],  # verdigris (green patina)
                           [0.75, 0.95, 0.85]], np.float32),
                 np.array([[0.09, 0.05, 0.02], [0.42, 0.27, 0.10],  # dark antique bronze
                           [0.80, 0.62, 0.30]], np.float32))
_MODE_PALETTES = (None, (0.80, 0.95, 1.20), (1.15, 0.80, 1.05))  # neutral, cool, rose cartoon
_MODE_MARBLES = ((0.0, _MARBLE_BASE),  # (vein phase offset, base colour): white Carrara,
                 (1.0 / 3.0, np.array([0.80, 0.84, 0.92], np.float32)),  # blue-grey,
                 (2.0 / 3.0, np.array([0.95, 0.84, 0.80], np.float32)))  # pink
_MODE_ASPECTS = ((1.0, 1.0), (1.0, 0.35), (0.35, 1.0))  # bulge: round, taller, wider


def _autumn(original, grade=_AUTUMN):
    graded = original @ grade.T
    # a gentle S-curve on the grade adds the contrast of a warm "film look"
    return jnp.clip(graded + 0.15 * graded * (1 - graded) * (graded - 0.3), 0.0, 1.0)


def _bronze(original, mask, ramp_colours=_BRONZE):
    """Cast metal: smoothed shading through a metal ramp (dark, mid, light colours [3, 3]),
    specular sheen, inside the mask."""
    h, w, _ = original.shape
    # a statue has no skin or hair texture: keep the large-scale shading of the luminance and
    # drop most of its fine detail (a blur of a function of the content, so view-consistent up
    # to the blur's footprint)
    lum = _luma(original)
    smooth = blur(lum, max(h, w) / 40.0)
    lum = _smoothstep(0.0, 1.0, 0.8 * smooth + 0.2 * lum)[..., None]
    c = ramp_colours
    lo = c[0] + (c[1] - c[0]) * jnp.clip(2 * lum, 0, 1)
    hi = c[1] + (c[2] - c[1]) * jnp.clip(2 * lum - 1, 0, 1)
    ramp = jnp.where(lum < 0.5, lo, hi)
    sheen = 0.6 * lum ** 6  # metallic highlights on the brightest parts
    metal = jnp.clip(ramp + sheen, 0.0, 1.0)
    m = mask[..., None]
    return m * metal + (1 - m) * original


def _cartoon(original, levels: int = 4, width: float = 0.2, gains=None):
    mean = jnp.mean(original, axis=-1, keepdims=True)
    sat = mean + 1.3 * (original - mean)
    if gains is not None:  # the palette of a mode: per-channel gains before posterising
        sat = sat * jnp.asarray(gains, jnp.float32)
    sat = jnp.clip(sat, 0.0, 1.0)
    y = sat * (levels - 1)
    base = jnp.floor(y)
    # a soft staircase keeps the target a continuous function of the colour
    step = _smoothstep(0.5 - width, 0.5 + width, y - base)
    poster = jnp.clip((base + step) / (levels - 1), 0.0, 1.0)
    lum = blur(_luma(original), 0.8)
    gy = jnp.pad(lum[2:] - lum[:-2], ((1, 1), (0, 0)), mode="edge") * 0.5
    gx = jnp.pad(lum[:, 2:] - lum[:, :-2], ((0, 0), (1, 1)), mode="edge") * 0.5
    edge = _smoothstep(0.04, 0.12, jnp.sqrt(gx * gx + gy * gy))
    return poster * (1.0 - 0.85 * edge[..., None])


def _marble(original, mask, points=None, offset: float = 0.0, base=_MARBLE_BASE):
    lum = _luma(original)
    if points is None:
        # the vein phase is a smooth function of the surface colour, so it is stamped on the
        # same surface point in every view
        phase = 3.0 * lum + 2.0 * (original[..., 0] - original[..., 2]) + original[..., 1]
    else:
        p = points
        phase = 3.0 * (p[..., 0] + 0.6 * p[..., 1] + 0.3 * p[..., 2]) \
            + 0.8 * jnp.sin(4.0 * p[..., 1] + 2.0 * p[..., 2]) + 0.5 * jnp.sin(5.0 * p[..., 0])
    if offset:  # another mode: the same world-anchored pattern, veins in other places
        phase = phase + offset
    v = jnp.abs(jnp.sin(jnp.pi * phase))
    vein = (1.0 - v) ** 8  # thin dark lines where the phase crosses an integer
    base = jnp.asarray(base) * (0.78 + 0.22 * lum[..., None])
    vein = 0.55 * vein[..., None]
    marble = base * (1.0 - vein) + vein * jnp.array([0.35, 0.36, 0.40])
    m = mask[..., None]
    return m * marble + (1 - m) * original


def head_mask(mask, *, fraction: float = 0.6):
    """The upper ``fraction`` of a foreground mask's vertical extent (the head of an upright
    subject; image rows grow downwards), float [H, W]."""
    h = mask.shape[0]
    rows = jnp.arange(h) + 0.5
    present = jnp.sum(mask, axis=1) > 0.5
    top = jnp.min(jnp.where(present, rows, h))
    bottom = jnp.max(jnp.where(present, rows, 0.0))
    cut = top + fraction * jnp.maximum(bottom - top, 0.0)
    return mask * _smoothstep(cut + 1.0, cut - 1.0, rows)[:, None]


def _bulge(original, mask, amount, aspect=(1.0, 1.0)):
    """Magnify the head around its centroid: inverse warp x -> c + (x - c) f(|x - c| / R).

    ``aspect`` (rows, columns) scales the amount along each image axis: (1, 1) is the
    isotropic bulge; (1, 0.35) makes the head taller, (0.35, 1) wider."""
    h, w, _ = original.shape
    cr, cc, rad = _centroid_radius(head_mask(mask))
    rows, cols = jnp.meshgrid(jnp.arange(h) + 0.5, jnp.arange(w) + 0.5, indexing="ij")
    dr, dc = rows - cr, cols - cc
    rho2 = (dr * dr + dc * dc) / (rad * rad)
    # f < 1 near the centre samples closer to the centroid (magnification 1 / (1 - amount)),
    # f -> 1 far away; |amount| <= 0.5 keeps the radial map monotone (no folds)
    g = jnp.exp(-rho2 / (2 * 0.8 ** 2))
    if aspect == (1.0, 1.0):
        f = 1.0 - amount * g
        return _sample(original, cr + dr * f - 0.5, cc + dc * f - 0.5)
    fr, fc = 1.0 - aspect[0] * amount * g, 1.0 - aspect[1] * amount * g
    return _sample(original, cr + dr * fr - 0.5, cc + dc * fc - 0.5)


BULGE_MAX = 0.35

# The local instruction's modes: channel orders of the recoloured part (orange (0.87, 0.46,
# 0.32) becomes blue (0.32, 0.46, 0.87), violet (0.46, 0.32, 0.87) or green (0.32, 0.87, 0.46)).
_MODE_PERMUTATIONS = ((2, 1, 0), (1, 2, 0), (2, 0, 1))


def orange_weight(original):
    """How much a pixel belongs to the local instruction's part, float [H, W] in [0, 1].

    A function of the pixel's colour alone (so of the surface, in every view): coloured
    (chroma max - min from 0.12 to 0.24) and warm (red above blue by 0.02 to 0.08). Grey,
    white, black and cool pixels weigh exactly 0.
    """
    chroma = jnp.max(original, axis=-1) - jnp.min(original, axis=-1)
    warm = original[..., 0] - original[..., 2]
    return _smoothstep(0.12, 0.24, chroma) * _smoothstep(0.02, 0.08, warm)


def _recolour(original, order=_MODE_PERMUTATIONS[0]):
    """The local instruction's full target: the :func:`orange_weight` part of float
    [H, W, 3] with its channels in ``order``, the other pixels unchanged."""
    w = orange_weight(original)[..., None]
    return w * original[..., jnp.asarray(order)] + (1.0 - w) * original


def _target_family(original, kind: str, points=None, mode: int = 0):
    """s -> target of strength s (s = 0: the original, s = 1: the full target) for one kind
    and one divergent mode (0 .. MAX_MODES - 1; mode 0 is the editor's single target).

    What does not depend on s (the foreground mask, the full colour target) is computed once,
    so the edit's two strengths (nominal and jittered) share it.
    """
    if kind == "shape":
        mask = foreground(original)
        aspect = _MODE_ASPECTS[mode]
        return lambda s: _bulge(original, mask, s * BULGE_MAX, aspect)
    if kind == "colour":
        full = _autumn(original, _MODE_GRADES[mode])
    elif kind == "material":
        full = _bronze(original, foreground(original), _MODE_PATINAS[mode])
    elif kind == "style":
        full = _cartoon(original, gains=_MODE_PALETTES[mode])
    elif kind == "texture":
        offset, base = _MODE_MARBLES[mode]
        full = _marble(original, foreground(original), points, offset, base)
    elif kind == "local":
        full = _recolour(original, _MODE_PERMUTATIONS[mode])
    else:
        raise ValueError(kind)
    return lambda s: jnp.clip(original + s * (full - original), 0.0, 1.0)
