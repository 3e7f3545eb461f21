"""A simulated instruction editor: an offline, deterministic stand-in for a 2D diffusion editor.

:class:`SimulatedEditor` implements the :class:`jaxedit.edit.Editor` protocol without any
neural network. It is a *test and benchmark instrument*, built so that ProEdit's claims can be
checked against a known ground truth on a CPU; it is not InstructPix2Pix and does not pretend to
produce IP2P's images. What it reproduces is the behaviour ProEdit relies on:

1. **Instructions name 3D-consistent targets.** Every instruction maps the ORIGINAL view of a
   scene to a target image, ``target(original, r, instruction)``. The editor only sees images,
   so targets are image-space functions of the original pixels that stay consistent across views
   because they depend on the content (colour) of each pixel through smooth functions, or on the
   object's silhouette, not on the pixel position in the frame:

   ========================================  ==========  ===========================================
   instruction                               kind        full target (r = 1)
   ========================================  ==========  ===========================================
   ``make it look like autumn``              colour      affine warm colour grade of every pixel
   ``turn him into a bronze statue``         material    smoothed shading, bronze ramp, metal sheen
   ``make it look like a cartoon``           style       soft posterisation + outlines on edges
   ``give him a marble texture``             texture     veins stamped as a function of colour
                                                         (or of world position, see ``surfaces``)
   ``make his head bigger``                  shape       radial bulge around the head's centroid
   ========================================  ==========  ===========================================

   The foreground is the set of pixels whose colour differs from the background colour, taken as
   the per-channel median of the image border of the original (a soft mask). The bulge is centred
   on the centroid of the "head", the upper 60% of the foreground's vertical extent, with a
   radius sqrt(head area / pi); for an upright subject centred in the views (the built-in
   ``face`` scene, cameras with +z up) this is view-consistent.

2. **Subtasks.** The framework forms e(r) = r E(p) + (1 - r) E(""). ``encode`` returns
   E("") = Q e_0 and E(p_i) = Q (e_0 + e_{i+1}) with a fixed orthogonal Q, so the editor
   recovers the instruction and r from an embedding by projection (``decode``). The target's
   response to r is continuous and NON-linear: the effective strength is a normalised logistic
   s(r) = (sigma(k (r - m)) - sigma(-k m)) / (sigma(k (1 - m)) - sigma(-k m)) with a per-
   instruction midpoint m and steepness k (s(0) = 0, s(1) = 1). Colour/material/style/texture
   targets cross-fade original -> full target by s(r); the shape target warps with amplitude
   s(r) a_max (a partial warp, never a ghosted cross-fade).

3. **Feasible output space grows with the requested change.** One call of ``edit`` returns::

       out = keep(t) * image + (1 - keep(t)) * P(T_{s'}(original)) + noise

   where ``image`` is the current render, t ~ U(timestep_range) is the SDEdit noising level and
   keep(t) = cos(pi t / 2) = sqrt(alpha_bar(t)) of a cosine schedule is the fraction of the
   current render that survives (low t: output close to ``image``; t = 1: nothing survives). The
   perturbation P and the jittered strength s' are view-specific random draws (from ``key``)
   whose amplitude grows with the gap g = mean |image - T_r| between the current render and the
   r-partial target:

   - strength jitter: s' = s(r) (1 + jitter * g * z), z ~ N(0, 1) ("different degrees of colour
     change" of the paper's appendix A);
   - a smooth random displacement of the edited pattern, amplitude ``shift * g`` of the image size;
   - a low-frequency random colour field, amplitude ``colour * (g + local gap)``, where the local
     gap is the blurred per-pixel |image - T_r| (inconsistency concentrates where things change);
   - a small noise floor (``noise``) of smooth and per-pixel noise, scaled by (1 - keep), that
     is there even for a perfect render (the editor as a refiner, appendix B).

   Text guidance above 7.5 amplifies the perturbation, image guidance above 1.5 damps it
   (amplitude x (text / 7.5) x sqrt(1.5 / image)); the target itself does not depend on them.
   Hence a small step (render already close to T_r) gives nearly identical outputs across views
   and keys, a big jump gives inconsistent ones: exactly the FOS argument of the paper.

4. **Divergent modes** (``modes=K``, K = 2 or 3; default 1). A real editor's feasible output space
   holds *different* plausible outcomes, not one outcome plus zero-mean noise (paper sections 1
   and 3.2: one view gets a hat here, another there). With K > 1 every instruction has K
   discrete outcomes, each 3D-consistent on its own; mode 0 is the single target above:

   ===========  ================================================================================
   kind         modes 0, 1, 2 (full targets)
   ===========  ================================================================================
   colour       orange-red grade; golden grade; crimson grade
   material     polished bronze; verdigris (green patina); dark antique bronze
   style        neutral posterised palette; cool palette; rose palette (channel gains)
   texture      veins at phase offsets 0, 1/3, 2/3 (other places on the same surface) in white,
                blue-grey and pink marble
   shape        round bulge; taller head (vertical amount, 0.35 of it horizontally); wider head
   ===========  ================================================================================

   Each call draws one mode k per view (from ``key``, on its own ``fold_in`` stream, so the
   draws of section 3 keep their bits) and then edits exactly as in section 3 with T^k in
   place of T. The draw looks at how close the current render x already is to each mode's
   r-partial target T^k_r:

       d_k   = mean over pixels and channels of |x - T^k_r|
       tau   = tau_0 + kappa * min_j d_j
       p_k   = exp(-(d_k - min_j d_j) / tau) / sum_j exp(-(d_j - min_j d_j) / tau)

   with ``mode_floor`` tau_0 = 0.004 (the noise floor: differences below it are invisible) and
   ``mode_kappa`` kappa = 0.25. The temperature shrinks with the distance to the nearest mode,
   so the draw sharpens as the render approaches a mode: a render equal to T^k_r (d_k = 0,
   tau = tau_0) stays in mode k unless another mode is within a few tau_0, as SDEdit keeps what
   a lightly noised input already shows; a render far from every mode (d_min large) has
   tau >> the spread of the d_k and picks nearly uniformly. In between, kappa sets the
   feedback: a render twice as close to mode k as to mode j picks j about exp(-1 / kappa) =
   2% as often as k, and an even blend of K modes is unstable (the gain of the draw at the
   blend, about 1 / (K kappa), exceeds 1), so a scene trained on its own edits drifts to one
   mode. The modes are not equally likely from every start: from the original, the mode whose
   target is nearest to the original is favoured (e.g. polished bronze over verdigris on skin).
   ``modes=1`` skips the draw: bit for bit the editor before modes existed.

Everything random comes from the ``key`` argument; equal inputs and key give equal bits. Use
:func:`view_key` to derive per-view keys from (run key, view index, ratio, iteration).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import DataError

EMBED_DIM = 8
_RATIO_QUANTUM = 1_000_000  # ratios enter keys as round(r * 1e6)


# --------------------------------------------------------------------------------------------
# Seeding


def quantize_ratio(ratio: float) -> int:
    """The integer round(ratio * 1e6) used to seed and memoise per-ratio work."""
    r = float(ratio)
    if not math.isfinite(r) or r < 0.0 or r > 4000.0:
        raise DataError("ratio", f"must be a finite number in [0, 1], got {ratio!r}")
    return int(round(r * _RATIO_QUANTUM))


def view_key(run_key: jax.Array, view_index: int, ratio: float, iteration: int) -> jax.Array:
    """Key of one edit: fold_in of (view index, quantised ratio, iteration) into ``run_key``.

    The ratio is quantised to 1e-6 (``quantize_ratio``) so that ratios read back from JSON or
    recomputed in floating point give the same key.
    """
    if int(view_index) < 0 or int(iteration) < 0:
        raise DataError("view_key", f"view index and iteration must be >= 0, got "
                        f"{view_index}, {iteration}")
    k = jax.random.fold_in(run_key, int(view_index))
    k = jax.random.fold_in(k, quantize_ratio(ratio))
    return jax.random.fold_in(k, int(iteration))


# --------------------------------------------------------------------------------------------
# The vocabulary


@dataclasses.dataclass(frozen=True)
class Instruction:
    """One instruction of the vocabulary.

    Attributes:
      prompt: the text, matched after lower-casing and collapsing white space.
      kind: "colour", "material", "style", "texture" or "shape".
      midpoint, steepness: of the logistic strength curve s(r) (see the module docstring).
    """

    prompt: str
    kind: str
    midpoint: float
    steepness: float


VOCABULARY: tuple[Instruction, ...] = (
    Instruction("make it look like autumn", "colour", 0.5, 6.0),
    Instruction("turn him into a bronze statue", "material", 0.35, 9.0),
    Instruction("make it look like a cartoon", "style", 0.6, 8.0),
    Instruction("give him a marble texture", "texture", 0.45, 10.0),
    Instruction("make his head bigger", "shape", 0.5, 12.0),
)


def _normalise_prompt(prompt: str) -> str:
    return " ".join(str(prompt).lower().split()).rstrip(".!")


def strength(ratio, midpoint: float, steepness: float):
    """Normalised logistic s(r): s(0) = 0, s(1) = 1, continuous, increasing, non-linear.

    Works on floats and arrays (NumPy or JAX); values of r outside [0, 1] extrapolate.
    """
    xp = jnp if isinstance(ratio, jax.Array) else np
    sig = lambda x: 1.0 / (1.0 + xp.exp(-x))  # noqa: E731
    lo = sig(-steepness * midpoint)
    hi = sig(steepness * (1.0 - midpoint))
    return (sig(steepness * (ratio - midpoint)) - lo) / (hi - lo)


# --------------------------------------------------------------------------------------------
# Image helpers (JAX, pure)


def _luma(x):
    """Rec. 601 luma of float [..., 3] -> [...]."""
    return 0.299 * x[..., 0] + 0.587 * x[..., 1] + 0.114 * x[..., 2]


def _smoothstep(e0, e1, x):
    t = jnp.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _gaussian_kernel(sigma: float) -> jnp.ndarray:
    radius = max(1, int(math.ceil(3.0 * sigma)))
    x = np.arange(-radius, radius + 1, dtype=np.float32)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    return jnp.asarray(k / k.sum())


def _blur(x, sigma: float):
    """Separable Gaussian blur of float [H, W] or [H, W, C] with edge padding."""
    if sigma <= 0:
        return x
    k = _gaussian_kernel(sigma)
    r = (k.shape[0] - 1) // 2
    squeeze = x.ndim == 2
    if squeeze:
        x = x[..., None]

    def conv_axis(img, axis):
        pad = [(0, 0)] * img.ndim
        pad[axis] = (r, r)
        p = jnp.pad(img, pad, mode="edge")
        n = img.shape[axis]
        out = 0.0
        for i in range(k.shape[0]):
            out = out + k[i] * jax.lax.slice_in_dim(p, i, i + n, axis=axis)
        return out

    y = conv_axis(conv_axis(x, 0), 1)
    return y[..., 0] if squeeze else y


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
    return _smoothstep(low, high, _blur(dist, 0.7))


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


def _normals(u):
    """Standard normals from uniforms float [..., 2] in [0, 1) (Box-Muller) -> [...]."""
    return jnp.sqrt(-2.0 * jnp.log1p(-u[..., 0])) * jnp.cos(2 * jnp.pi * u[..., 1])


FIELD_WAVES = 4


def _random_field(u, h: int, w: int, *, cycles: float = 1.2):
    """Smooth random field float [H, W, C], roughly N(0, 1) per pixel, from uniforms [C, waves, 5].

    A sum of random plane waves per channel with about ``cycles`` periods across the image:
    low-frequency, like the colour casts and drifts of independent diffusion samples. (All the
    randomness of an edit is one uniform draw sliced up: one random-bits kernel to compile
    instead of one per draw, which dominated the compile time.)
    """
    waves = u.shape[1]
    radius = jnp.sqrt(-2.0 * jnp.log1p(-u[..., 0]))  # Box-Muller: both normals of one pair
    angle = 2 * jnp.pi * u[..., 1]
    freq = cycles * jnp.stack([radius * jnp.cos(angle), radius * jnp.sin(angle)], axis=-1)
    phase = 2 * jnp.pi * u[..., 2]
    amp = _normals(u[..., 3:5]) * math.sqrt(2.0 / waves)
    y = (jnp.arange(h) + 0.5) / max(h, w)
    x = (jnp.arange(w) + 0.5) / max(h, w)
    arg = 2 * jnp.pi * (freq[..., 0, None, None] * y[:, None]
                        + freq[..., 1, None, None] * x[None, :])
    field = jnp.sum(amp[..., None, None] * jnp.cos(arg + phase[..., None, None]), axis=1)
    return jnp.moveaxis(field, 0, -1)


# --------------------------------------------------------------------------------------------
# Full targets (r = 1 or strength s), one per kind. original: float [H, W, 3] in [0, 1].

_AUTUMN = np.array([[0.55, 0.55, 0.00],
                    [0.15, 0.55, 0.10],
                    [0.05, 0.15, 0.35]], np.float32)
_BRONZE = np.array([[0.16, 0.09, 0.04], [0.70, 0.43, 0.18], [1.00, 0.88, 0.60]], np.float32)
_MARBLE_BASE = np.array([0.93, 0.92, 0.89], np.float32)

# The divergent modes (see the module docstring, section 4). Mode 0 of every kind is the single
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
    smooth = _blur(lum, max(h, w) / 40.0)
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
    lum = _blur(_luma(original), 0.8)
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
    else:
        raise ValueError(kind)
    return lambda s: jnp.clip(original + s * (full - original), 0.0, 1.0)


def mode_probabilities(distances, *, kappa: float, floor: float):
    """p_k of the mode draw from the distances d_k of the render to each mode's r-target.

    p_k = softmax_k(-(d_k - d_min) / tau) with tau = floor + kappa * d_min (module docstring,
    section 4). float [K] -> float [K]; NumPy or JAX arrays.
    """
    xp = jnp if isinstance(distances, jax.Array) else np
    d = distances
    d_min = xp.min(d)
    logits = -(d - d_min) / (floor + kappa * d_min)
    w = xp.exp(logits - xp.max(logits))
    return w / xp.sum(w)


# --------------------------------------------------------------------------------------------
# The editor


@dataclasses.dataclass(frozen=True)
class _Params:
    noise: float
    colour: float
    shift: float
    jitter: float
    modes: int = 1
    mode_kappa: float = 0.25
    mode_floor: float = 0.004


_MODE_STREAM = 0x6D6F6465  # fold_in tag of the mode draw: the other draws keep their bits


def _mode_distances(image, original, s, points, kind: str, modes: int):
    """(partial targets float [K, H, W, 3], d_k = mean |image - T^k| float [K]) at strength s."""
    partial = jnp.stack([_target_family(original, kind, points, k)(s) for k in range(modes)])
    return partial, jnp.mean(jnp.abs(image[None] - partial), axis=(1, 2, 3))


@functools.partial(jax.jit, static_argnames=("kind", "params"))
def _edit_impl(image, original, s, key, t_range, gscale, points, *, kind, params: _Params):
    """(edited image float32 [H, W, 3], drawn mode int32 []); see the module docstring."""
    h, w, _ = image.shape
    nf = FIELD_WAVES * 5
    sizes = (1, 2, 2 * nf, 3 * nf, 3 * nf, h * w * 3 * 2)
    u = jax.random.uniform(key, (sum(sizes),), maxval=1.0 - 1e-7)
    u_t, u_jit, u_warp, u_col, u_sm, u_px = jnp.split(u, np.cumsum(sizes)[:-1])
    t = t_range[0] + (t_range[1] - t_range[0]) * u_t[0]
    keep = jnp.cos(0.5 * jnp.pi * jnp.clip(t, 0.0, 1.0))

    if params.modes == 1:  # the single-outcome editor, exactly as before modes existed
        mode = jnp.int32(0)
        family = _target_family(original, kind, points)
        target = family(s)
    else:
        partial, dist = _mode_distances(image, original, s, points, kind, params.modes)
        p = mode_probabilities(dist, kappa=params.mode_kappa, floor=params.mode_floor)
        mode = jax.random.categorical(jax.random.fold_in(key, _MODE_STREAM), jnp.log(p))
        families = [_target_family(original, kind, points, k) for k in range(params.modes)]
        family = lambda v: jax.lax.switch(mode, families, v)  # noqa: E731
        target = partial[mode]
    diff = jnp.abs(image - target)
    gap = jnp.mean(diff)
    local = _blur(jnp.mean(diff, axis=-1), max(h, w) / 16.0)

    # the edit of this view: a jittered strength, a displaced pattern, a colour cast
    s_view = s * (1.0 + params.jitter * gscale * gap * _normals(u_jit))
    edited = family(s_view)
    disp = _random_field(u_warp.reshape(2, FIELD_WAVES, 5), h, w, cycles=0.8)
    disp = disp * (params.shift * gscale * gap * max(h, w))
    rows, cols = jnp.meshgrid(jnp.arange(h, dtype=jnp.float32), jnp.arange(w, dtype=jnp.float32),
                              indexing="ij")
    edited = _sample(edited, rows + disp[..., 0], cols + disp[..., 1])
    cast = _random_field(u_col.reshape(3, FIELD_WAVES, 5), h, w)
    cast = cast * (params.colour * gscale * (gap + local))[..., None]
    edited = edited + cast

    floor = params.noise * (_random_field(u_sm.reshape(3, FIELD_WAVES, 5), h, w, cycles=2.0)
                            + _normals(u_px.reshape(h, w, 3, 2)))
    out = keep * image + (1.0 - keep) * (edited + floor)
    return jnp.clip(out, 0.0, 1.0).astype(jnp.float32), mode


@functools.partial(jax.jit, static_argnames=("kind", "params"))
def _probabilities_impl(image, original, s, points, *, kind, params: _Params):
    _, dist = _mode_distances(image, original, s, points, kind, params.modes)
    return mode_probabilities(dist, kappa=params.mode_kappa, floor=params.mode_floor)


@functools.partial(jax.jit, static_argnames=("kind", "mode"))
def _target_impl(original, s, points, *, kind, mode=0):
    return _target_family(original, kind, points, mode)(s).astype(jnp.float32)


def _as_image(x, where: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float32)
    if a.ndim != 3 or a.shape[-1] != 3 or a.shape[0] < 4 or a.shape[1] < 4:
        raise DataError(where, f"expected an image float [H, W, 3] with H, W >= 4, got shape "
                        f"{tuple(a.shape)}")
    if not np.all(np.isfinite(a)):
        raise DataError(where, "image has NaN or infinite values")
    return a


class SimulatedEditor:
    """Offline, deterministic (given the key) instruction editor with a known ground truth.

    See the module docstring for the model. Every argument has a default, so
    ``SimulatedEditor()`` works; ``.instructions`` lists the vocabulary.

    Args:
      noise: noise floor amplitude (smooth + per-pixel), present even when the render already
        equals the target.
      colour: amplitude of the low-frequency colour cast per unit of gap.
      shift: displacement of the edited pattern, as a fraction of the image size per unit gap.
      jitter: relative per-view jitter of the edit strength per unit gap.
      surfaces: optional per-view geometry for a truly 3D texture: a pair
        ``(originals float [N, H, W, 3], points float [N, H, W, 3])`` of original views and the
        world point seen by each pixel (e.g. from ``jaxedit.scenes.surface_points_and_ids``).
        When ``edit``/``target`` receive an ``original`` equal to one of these views (up to 8-bit
        rounding), the marble veins are a function of the world position instead of the colour.
        See :meth:`from_scene` for the built-in scenes.
      modes: number K of divergent outcomes per instruction, 1 .. MAX_MODES. 1 (default) is the
        single-outcome editor (bit for bit the editor before modes existed); K > 1 draws one of
        K modes per edit call (module docstring, section 4).
      mode_kappa: kappa of the draw's temperature tau = mode_floor + kappa * d_min.
      mode_floor: tau_0, the temperature of a render that already equals a mode's target.
    """

    name = "simulated"

    def __init__(self, *, noise: float = 0.004, colour: float = 0.12, shift: float = 0.05,
                 jitter: float = 1.0, surfaces: tuple | None = None, modes: int = 1,
                 mode_kappa: float = 0.25, mode_floor: float = 0.004):
        for field, v in (("noise", noise), ("colour", colour), ("shift", shift),
                         ("jitter", jitter), ("mode_kappa", mode_kappa)):
            if not (math.isfinite(v) and v >= 0):
                raise DataError(f"SimulatedEditor.{field}",
                                f"must be a finite number >= 0, got {v!r}")
        if not (math.isfinite(mode_floor) and mode_floor > 0):
            raise DataError("SimulatedEditor.mode_floor", f"must be a finite number > 0, got "
                            f"{mode_floor!r}")
        if isinstance(modes, bool) or not isinstance(modes, (int, np.integer)) \
                or not 1 <= modes <= MAX_MODES:
            raise DataError("SimulatedEditor.modes",
                            f"must be an integer in 1..{MAX_MODES}, got {modes!r}")
        self.params = _Params(float(noise), float(colour), float(shift), float(jitter),
                              int(modes), float(mode_kappa), float(mode_floor))
        q, _ = np.linalg.qr(np.random.default_rng(20241120).normal(size=(EMBED_DIM, EMBED_DIM)))
        self._basis = q.astype(np.float32)  # columns: null direction, then one per instruction
        self._surface_views = self._surface_points = None
        if surfaces is not None:
            originals, points = (np.asarray(a, np.float32) for a in surfaces)
            if originals.ndim != 4 or originals.shape[-1] != 3 or points.shape != originals.shape:
                raise DataError("surfaces", "expected (originals [N,H,W,3], points [N,H,W,3]), got "
                                f"{originals.shape} and {points.shape}")
            self._surface_views = originals
            # background pixels have no surface point (NaN from the ray caster): any finite
            # value does, the foreground mask keeps the texture off the background
            self._surface_points = np.nan_to_num(points)

    @classmethod
    def from_scene(cls, scene, cameras, images=None, **kwargs) -> SimulatedEditor:
        """An editor whose texture instruction is stamped on the 3D surface of a built-in scene.

        ``images`` (float [N, H, W, 3]) are the original views of ``cameras``; default: the ray
        caster's renders. Uses ``jaxedit.scenes.surface_points_and_ids``.
        """
        from .. import scenes

        if images is None:
            images = scenes.render_scene(scene, cameras)
        points, ids, _ = scenes.surface_points_and_ids(scene, cameras)
        points = np.where((np.asarray(ids) >= 0)[..., None], points, 0.0)
        return cls(surfaces=(images, points), **kwargs)

    # ---- vocabulary and embeddings ----------------------------------------------------------

    @property
    def instructions(self) -> tuple[str, ...]:
        return tuple(i.prompt for i in VOCABULARY)

    def _index(self, instruction) -> int:
        if isinstance(instruction, (int, np.integer)):
            if 0 <= int(instruction) < len(VOCABULARY):
                return int(instruction)
            raise DataError("instruction",
                            f"index {instruction} out of range 0..{len(VOCABULARY) - 1}")
        key = _normalise_prompt(instruction)
        for i, ins in enumerate(VOCABULARY):
            if ins.prompt == key:
                return i
        raise DataError("prompt", f"unknown instruction {instruction!r} for the simulated editor; "
                        f"known: {', '.join(repr(p) for p in self.instructions)}")

    def encode(self, prompt: str) -> np.ndarray:
        """E(prompt), float32 [8]. E("") is the null embedding; unknown prompts raise DataError."""
        z = np.zeros(EMBED_DIM, np.float32)
        z[0] = 1.0
        if _normalise_prompt(prompt) != "":
            z[1 + self._index(prompt)] = 1.0
        return self._basis @ z

    def decode(self, embedding) -> tuple[int | None, float]:
        """(instruction index, ratio r) of e(r) = r E(p) + (1 - r) E(""); (None, 0) for E("")."""
        e = np.asarray(embedding, np.float64).reshape(-1)
        if e.shape != (EMBED_DIM,) or not np.all(np.isfinite(e)):
            raise DataError("embedding", f"expected a finite float [{EMBED_DIM}] embedding of the "
                            f"simulated editor, got shape {np.shape(embedding)}")
        z = self._basis.T.astype(np.float64) @ e
        coords = z[1:1 + len(VOCABULARY)]
        residual = np.abs(np.concatenate([[z[0] - 1.0], z[1 + len(VOCABULARY):]])).max(initial=0.0)
        active = np.flatnonzero(np.abs(coords) > 1e-4)
        if residual > 1e-3 or len(active) > 1:
            raise DataError("embedding", "not an interpolation r E(p) + (1 - r) E('') of one "
                            "instruction of the simulated editor")
        if len(active) == 0:
            return None, 0.0
        i = int(active[0])
        r = float(coords[i])
        if r < -1e-4 or r > 1 + 1e-4:
            raise DataError("embedding", f"ratio {r:.4f} outside [0, 1]")
        return i, min(max(r, 0.0), 1.0)

    def strength(self, ratio: float, instruction) -> float:
        """s(r) of the instruction: the fraction of the full edit present in the r-target."""
        ins = VOCABULARY[self._index(instruction)]
        return float(strength(float(ratio), ins.midpoint, ins.steepness))

    # ---- images -----------------------------------------------------------------------------

    def _points(self, original: np.ndarray):
        """World points of a registered view equal to ``original`` up to 8-bit rounding, or None.

        Matching by content (mean absolute difference < 1/255) lets originals read back from
        PNG files find their geometry.
        """
        views = self._surface_views
        if views is None or views.shape[1:] != original.shape:
            return None
        err = np.mean(np.abs(views - original[None]), axis=(1, 2, 3))
        k = int(np.argmin(err))
        return jnp.asarray(self._surface_points[k]) if err[k] < 1.0 / 255 else None

    @property
    def modes(self) -> int:
        """K, the number of divergent outcomes of every instruction."""
        return self.params.modes

    def target(self, original, ratio: float, instruction, mode: int = 0) -> np.ndarray:
        """The noise-free r-partial target T^k_r(original) of mode k, float32 [H, W, 3] in [0, 1].

        ``instruction`` is a prompt of the vocabulary or its index; r = 0 gives ``original``.
        ``mode`` k in 0 .. modes - 1 (mode 0: the target of the single-outcome editor).
        """
        original = _as_image(original, "original")
        i = self._index(instruction)
        if isinstance(mode, bool) or not isinstance(mode, (int, np.integer)) \
                or not 0 <= mode < self.modes:
            raise DataError("mode", f"must be an integer in 0..{self.modes - 1}, got {mode!r}")
        ins = VOCABULARY[i]
        s = strength(float(ratio), ins.midpoint, ins.steepness)
        return np.asarray(_target_impl(jnp.asarray(original), jnp.float32(s),
                                       self._points(original), kind=ins.kind, mode=int(mode)))

    def mode_targets(self, original, ratio: float, instruction) -> np.ndarray:
        """The targets of every mode, float32 [K, H, W, 3] (K = ``modes``)."""
        return np.stack([self.target(original, ratio, instruction, k) for k in range(self.modes)])

    def mode_probabilities(self, image, original, embedding) -> np.ndarray:
        """p_k of the mode draw for the render ``image`` and embedding e(r), float [K]."""
        image, original = _as_image(image, "image"), _as_image(original, "original")
        i, r = self.decode(embedding)
        kind, s = ("colour", 0.0) if i is None else (VOCABULARY[i].kind, self.strength(r, i))
        return np.asarray(_probabilities_impl(jnp.asarray(image), jnp.asarray(original),
                                              jnp.float32(s), self._points(original),
                                              kind=kind, params=self.params))

    def target_of_embedding(self, original, embedding) -> np.ndarray:
        """The noise-free target for an embedding e(r) (the original for the null embedding)."""
        i, r = self.decode(embedding)
        original = _as_image(original, "original")
        return original.copy() if i is None else self.target(original, r, i)

    def edit(self, image, original, embedding, key: jax.Array, *,
             timestep_range: tuple[float, float] = (0.02, 0.98),
             guidance: tuple[float, float] = (7.5, 1.5)) -> np.ndarray:
        """Edit one view: float32 [H, W, 3] in [0, 1], deterministic given ``key``.

        The arguments are those of :meth:`edit_with_mode`, which also returns the drawn mode.
        """
        return self.edit_with_mode(image, original, embedding, key, timestep_range=timestep_range,
                                   guidance=guidance)[0]

    def edit_with_mode(self, image, original, embedding, key: jax.Array, *,
                       timestep_range: tuple[float, float] = (0.02, 0.98),
                       guidance: tuple[float, float] = (7.5, 1.5)) -> tuple[np.ndarray, int]:
        """(edited view float32 [H, W, 3] in [0, 1], the mode k it was drawn in).

        Args:
          image: float [H, W, 3], the current render of the view.
          original: float [H, W, 3], the original photo of the view (targets are functions of it).
          embedding: e(r) from ``encode`` and ``interpolate_embedding``.
          key: a ``jax.random`` key (see :func:`view_key`).
          timestep_range: (t_min, t_max) in [0, 1]; t ~ U(t_min, t_max), and a fraction
            cos(pi t / 2) of ``image`` survives.
          guidance: (text, image) classifier-free guidance scales; they scale the perturbation.
        """
        image = _as_image(image, "image")
        original = _as_image(original, "original")
        if image.shape != original.shape:
            raise DataError("image",
                            f"shape {image.shape} differs from the original's {original.shape}")
        t0, t1 = (float(t) for t in timestep_range)
        if not (0.0 <= t0 <= t1 <= 1.0):
            raise DataError("timestep_range",
                            f"need 0 <= t_min <= t_max <= 1, got {timestep_range!r}")
        gt, gi = (float(g) for g in guidance)
        if not (gt >= 0 and gi > 0 and math.isfinite(gt) and math.isfinite(gi)):
            raise DataError("guidance", f"need text >= 0 and image > 0 scales, got {guidance!r}")
        i, r = self.decode(embedding)
        kind, s = ("colour", 0.0) if i is None else (VOCABULARY[i].kind, self.strength(r, i))
        gscale = (gt / 7.5) * math.sqrt(1.5 / gi)
        out, mode = _edit_impl(jnp.asarray(image), jnp.asarray(original), jnp.float32(s), key,
                               jnp.asarray([t0, t1], jnp.float32), jnp.float32(gscale),
                               self._points(original), kind=kind, params=self.params)
        return np.asarray(out), int(mode)


def edit_views(editor, images: Sequence, originals: Sequence, embedding, run_key, ratio: float,
               iteration: int = 0, *, view_indices: Sequence[int] | None = None,
               timestep_range=(0.02, 0.98), guidance=(7.5, 1.5)) -> np.ndarray:
    """Edit several views with per-view keys ``view_key(run_key, k, ratio, iteration)``.

    Returns float32 [N, H, W, 3]. Works with any :class:`Editor`.
    """
    idx = range(len(images)) if view_indices is None else view_indices
    return np.stack([editor.edit(img, orig, embedding, view_key(run_key, k, ratio, iteration),
                                 timestep_range=timestep_range, guidance=guidance)
                     for k, img, orig in zip(idx, images, originals)])
