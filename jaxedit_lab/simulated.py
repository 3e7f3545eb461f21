"""A simulated instruction editor: an offline, deterministic stand-in for a 2D diffusion editor.

:class:`SimulatedEditor` implements the :class:`jaxedit.editors.Editor` protocol without any
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
   ``paint the orange parts blue``           local       the warm, coloured pixels only (chroma
                                                         0.12-0.24 ramp, red above blue) swap red
                                                         and blue; grey, white, black and cool
                                                         pixels keep their colour exactly
   ========================================  ==========  ===========================================

   The last is the *local* instruction (issue 35, :data:`LOCAL_VOCABULARY`): one part of the
   scene changes (the person's hair and skin, the tabletop's red ball and boxes, the face's
   orange suit) and the rest of every view is the original, bit for bit, so a local edit
   (``edit --local auto``) can be scored on what it must leave alone.

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
   place of T. The draw follows the mode the current render x already shows, *at the strength
   it shows it* (not at the requested r: a render half-way to mode c is nearer to every mode's
   full target than to c's partial one, so comparing at r favours the mode nearest the original):

       e_k   = min over s in {0, 0.05, ..., 1} of mean |x - T^k(s)|, s_k its argmin
       z_k   = (e_k - min_j e_j) / (sep(s_khat) + floor)      khat = argmin_j e_j
       rho   = mean |x - T^khat(s_r)| / (sep(s_r) + floor)
       tau   = beta t (1 + (lambda rho)^2)
       p_k   = softmax_k(-z_k / tau)

   where sep(s) is the mean distance between the modes' targets of strength s, t the SDEdit
   timestep of this call (the same draw as in section 3), ``mode_temperature`` beta = 0.15,
   ``mode_step_gain`` lambda = 1 and ``mode_floor`` 0.004 (differences below it are invisible).
   z_k is the render's evidence against mode k in units of what can be told apart where the
   render is; rho is the step the edit asks for in units of how far apart the modes are where
   it goes. Hence:

   - the original shows no mode (all T^k(0) are the original): a uniform draw;
   - a render equal to T^c(s) with s large enough for the modes to differ stays in c with a
     probability that rises as t falls (a lightly noised input keeps what it shows) and, with
     lambda > 0, falls with the step size rho (the paper's hypothesis: a small step has a small
     feasible output space). Measured from T^c at r_{i-1} to the scheduler's r_i (the
     ``face``-like test views, 4 texture / 8 shape subtasks; tests/test_simulated.py): 0.98-1.00
     (texture) and 0.93-1.00 (shape, s >= 0.18) at t = 0.45, 0.86-0.99 and 0.76-0.97 at
     t = 0.85; the whole rest of the edit at once holds 0.72 / 0.44-0.56 from the early ratios;
   - ``mode_step_gain=0`` is the negative control: the draw does not depend on r at all;
   - an even blend of modes is unstable (its evidence favours whichever mode it leans to), so a
     scene trained on its own edits drifts to one mode.

   Geometry-like modes (``geometry_lock``, default on, kind ``shape``): the edit warps the
   *render* on from the strength it shows (s_k) to the requested one with mode k's aspect,
   instead of re-deriving the shape from the original. A scene whose views disagree on the
   shape renders a ghost of several shapes; editing warps the ghost but never removes it, only
   training (moving Gaussians, whose learning rate is small) can: the failure of editing in one
   big step that the paper reports for geometry. Colour-like kinds re-derive their targets from
   the original, so a wrong colour is undone by the next edits.
   ``modes=1`` skips the draw: bit for bit the editor before modes existed.

The target families of sections 1 and 4 (the noise-free ground truth, T^k(s)) are in
:mod:`jaxedit_lab.simulated_targets`; this module holds the vocabulary and the editor.

Everything random comes from the ``key`` argument; equal inputs and key give equal bits. Use
:func:`jaxedit.editors.keys.view_key` to derive per-view keys from (run key, view index, ratio,
iteration).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxedit.errors import DataError, quoted
from jaxedit.editors.base import editor_guidance
from jaxedit.editors.diffusion import IP2P_GUIDANCE
from jaxedit.editors.masks import relevance_mask
from jaxedit_lab.simulated_targets import (BULGE_MAX, MAX_MODES, _MODE_ASPECTS, blur, _bulge, _sample,
                                _target_family, foreground)

EMBED_DIM = 8


# --------------------------------------------------------------------------------------------
# The vocabulary


@dataclasses.dataclass(frozen=True)
class Instruction:
    """One instruction of the vocabulary.

    Attributes:
      prompt: the text, matched after lower-casing and collapsing white space.
      kind: "colour", "material", "style", "texture", "shape" or "local".
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
#: Instructions that change one part of the scene only (issue 35), after :data:`VOCABULARY`
#: in the editor's embedding basis, so the global instructions keep their embeddings and bits.
LOCAL_VOCABULARY: tuple[Instruction, ...] = (
    Instruction("paint the orange parts blue", "local", 0.5, 8.0),
)
#: Every instruction the editor knows, in index order.
INSTRUCTIONS: tuple[Instruction, ...] = VOCABULARY + LOCAL_VOCABULARY


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
# The perturbation's random fields (module docstring, section 3)


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
# The mode draw


def mode_probabilities(evidence, step_ratio, timestep, *, temperature: float, step_gain: float):
    """p_k of the mode draw (module docstring, section 4). NumPy or JAX.

    Args:
      evidence: float [K], z_k >= 0, how much worse mode k explains the render than the best
        mode does, in units of the modes' separation at the render's own strength.
      step_ratio: float [], rho = the step the edit asks for / the modes' separation at the
        requested strength.
      timestep: float [], the SDEdit timestep t in [0, 1].
      temperature, step_gain: beta and lambda of tau = beta t (1 + (lambda rho)^2).
    Returns:
      float [K], softmax_k(-z_k / tau).
    """
    xp = jnp if isinstance(evidence, jax.Array) else np
    tau = temperature * xp.maximum(timestep, 1e-3) * (1.0 + (step_gain * step_ratio) ** 2)
    logits = -evidence / tau
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
    mode_temperature: float = 0.15
    mode_step_gain: float = 1.0
    mode_floor: float = 0.004
    geometry_lock: bool = True


_MODE_STREAM = 0x6D6F6465  # fold_in tag of the mode draw: the other draws keep their bits


#: Strengths at which the draw looks for the mode a render shows (its own strength).
_OWN_STRENGTHS = np.linspace(0.0, 1.0, 21, dtype=np.float32)


def _mean_pair_distance(images):
    """Mean over pairs j < k of mean |images[j] - images[k]|, of float [K, H, W, 3] -> []."""
    k = images.shape[0]
    pairs = [jnp.mean(jnp.abs(images[a] - images[b])) for a in range(k) for b in range(a)]
    return sum(pairs) / len(pairs)


class ModeEvidence(NamedTuple):
    """What the mode draw sees (module docstring, section 4); arrays of one edit.

    partial: float [K, H, W, 3], T^k at the requested strength s.
    evidence: float [K], z_k.
    own: float [K], s_k, the strength at which mode k best explains the render.
    step_ratio: float [], rho.
    """

    partial: jax.Array
    evidence: jax.Array
    own: jax.Array
    step_ratio: jax.Array


def _mode_evidence(image, original, s, points, kind: str, modes: int, floor: float):
    """The :class:`ModeEvidence` of render ``image`` for an edit of strength ``s``."""
    families = [_target_family(original, kind, points, k) for k in range(modes)]
    grid = jnp.asarray(_OWN_STRENGTHS)
    # [K, G, H, W, 3]: every mode at every strength of the grid
    paths = jnp.stack([jax.vmap(f)(grid) for f in families])
    dist = jnp.mean(jnp.abs(image[None, None] - paths), axis=(2, 3, 4))  # [K, G]
    best = jnp.argmin(dist, axis=1)
    e = jnp.min(dist, axis=1)
    k_hat = jnp.argmin(e)
    # the modes' separation where the render is: evidence is relative to what can be told apart
    sep_own = _mean_pair_distance(paths[:, best[k_hat]])
    evidence = (e - jnp.min(e)) / (sep_own + floor)
    partial = jnp.stack([f(s) for f in families])
    step = jnp.mean(jnp.abs(image - partial[k_hat]))
    step_ratio = step / (_mean_pair_distance(partial) + floor)
    return ModeEvidence(partial, evidence, grid[best], step_ratio)


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

    geometry = None
    if params.modes == 1:  # the single-outcome editor, exactly as before modes existed
        mode = jnp.int32(0)
        family = _target_family(original, kind, points)
        target = family(s)
    else:
        ev = _mode_evidence(image, original, s, points, kind, params.modes, params.mode_floor)
        p = mode_probabilities(ev.evidence, ev.step_ratio, t,
                               temperature=params.mode_temperature,
                               step_gain=params.mode_step_gain)
        mode = jax.random.categorical(jax.random.fold_in(key, _MODE_STREAM), jnp.log(p))
        families = [_target_family(original, kind, points, k) for k in range(params.modes)]
        family = lambda v: jax.lax.switch(mode, families, v)  # noqa: E731
        target = ev.partial[mode]
        if kind == "shape" and params.geometry_lock:
            # geometry is what the render already has: the edit warps the render on from the
            # strength it shows, so a ghost of two shapes stays a ghost (only training,
            # by moving Gaussians, can remove it)
            mask_r = foreground(image)
            warps = [functools.partial(lambda a, k: _bulge(image, mask_r, a, _MODE_ASPECTS[k]),
                                       k=k) for k in range(params.modes)]
            own = ev.own[mode]
            geometry = lambda v: jax.lax.switch(  # noqa: E731
                mode, warps, jnp.clip((v - own) * BULGE_MAX, -BULGE_MAX, BULGE_MAX))
    diff = jnp.abs(image - target)
    gap = jnp.mean(diff)
    local = blur(jnp.mean(diff, axis=-1), max(h, w) / 16.0)

    # the edit of this view: a jittered strength, a displaced pattern, a colour cast
    s_view = s * (1.0 + params.jitter * gscale * gap * _normals(u_jit))
    edited = family(s_view) if geometry is None else geometry(s_view)
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
def _probabilities_impl(image, original, s, t, points, *, kind, params: _Params):
    ev = _mode_evidence(image, original, s, points, kind, params.modes, params.mode_floor)
    return mode_probabilities(ev.evidence, ev.step_ratio, t, temperature=params.mode_temperature,
                              step_gain=params.mode_step_gain)


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
        world point seen by each pixel (for a built-in scene: ``jaxedit.scenes.surface_views``).
        When ``edit``/``target`` receive an ``original`` equal to one of these views (up to 8-bit
        rounding), the marble veins are a function of the world position instead of the colour.
      modes: number K of divergent outcomes per instruction, 1 .. MAX_MODES. 1 (default) is the
        single-outcome editor (bit for bit the editor before modes existed); K > 1 draws one of
        K modes per edit call (module docstring, section 4).
      mode_temperature: beta of the draw's temperature tau = beta t (1 + (lambda rho)^2).
      mode_step_gain: lambda, how fast holding a mode falls with the step size relative to the
        modes' separation (the paper's hypothesis); 0 removes any dependence on the step (the
        negative control of the mechanism).
      mode_floor: separations below this (image units) cannot be told apart.
      geometry_lock: shape modes edit the geometry the render shows instead of re-deriving it
        from the original (a ghost of two shapes is not undone by editing; section 4).
    """

    name = "simulated"
    #: The guidance of an edit that names none: InstructPix2Pix's, where its perturbation
    #: has the amplitude the module docstring gives.
    guidance = IP2P_GUIDANCE

    def __init__(self, *, noise: float = 0.004, colour: float = 0.12, shift: float = 0.05,
                 jitter: float = 1.0, surfaces: tuple | None = None, modes: int = 1,
                 mode_temperature: float = 0.15, mode_step_gain: float = 1.0,
                 mode_floor: float = 0.004, geometry_lock: bool = True):
        for field, v in (("noise", noise), ("colour", colour), ("shift", shift),
                         ("jitter", jitter), ("mode_step_gain", mode_step_gain)):
            if not (math.isfinite(v) and v >= 0):
                raise DataError(f"SimulatedEditor.{field}",
                                f"must be a finite number >= 0, got {v!r}")
        for field, v in (("mode_floor", mode_floor), ("mode_temperature", mode_temperature)):
            if not (math.isfinite(v) and v > 0):
                raise DataError(f"SimulatedEditor.{field}", f"must be a finite number > 0, got "
                                f"{v!r}")
        if isinstance(modes, bool) or not isinstance(modes, (int, np.integer)) \
                or not 1 <= modes <= MAX_MODES:
            raise DataError("SimulatedEditor.modes",
                            f"must be an integer in 1..{MAX_MODES}, got {modes!r}")
        self.params = _Params(float(noise), float(colour), float(shift), float(jitter),
                              int(modes), float(mode_temperature), float(mode_step_gain),
                              float(mode_floor), bool(geometry_lock))
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

    # ---- vocabulary and embeddings ----------------------------------------------------------

    @property
    def instructions(self) -> tuple[str, ...]:
        return tuple(i.prompt for i in INSTRUCTIONS)

    def _index(self, instruction) -> int:
        if isinstance(instruction, (int, np.integer)):
            if 0 <= int(instruction) < len(INSTRUCTIONS):
                return int(instruction)
            raise DataError("instruction",
                            f"index {instruction} out of range 0..{len(INSTRUCTIONS) - 1}")
        key = _normalise_prompt(instruction)
        for i, ins in enumerate(INSTRUCTIONS):
            if ins.prompt == key:
                return i
        raise DataError("prompt", f"unknown instruction {quoted(instruction)} for the simulated "
                        f"editor; known: {', '.join(repr(p) for p in self.instructions)}")

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
        coords = z[1:1 + len(INSTRUCTIONS)]
        residual = np.abs(np.concatenate([[z[0] - 1.0],
                                          z[1 + len(INSTRUCTIONS):]])).max(initial=0.0)
        active = np.flatnonzero(np.abs(coords) > 1e-4)
        if residual > 1e-3 or len(active) > 1:
            raise DataError("embedding", "not an interpolation r E(p) + (1 - r) E('') of one "
                            "instruction of the simulated editor")
        if len(active) == 0:
            return None, 0.0
        i = int(active[0])
        r = float(coords[i])
        if r < -1e-4:
            raise DataError("embedding", f"ratio {r:.4f} below 0")
        # 1 within the basis' rounding is 1; past it, an extended edit (extrapolated)
        return i, 1.0 if abs(r - 1.0) <= 1e-4 else max(r, 0.0)

    def strength(self, ratio: float, instruction) -> float:
        """s(r) of the instruction: the fraction of the full edit present in the r-target."""
        ins = INSTRUCTIONS[self._index(instruction)]
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
        ins = INSTRUCTIONS[i]
        s = strength(float(ratio), ins.midpoint, ins.steepness)
        return np.asarray(_target_impl(jnp.asarray(original), jnp.float32(s),
                                       self._points(original), kind=ins.kind, mode=int(mode)))

    def mode_targets(self, original, ratio: float, instruction) -> np.ndarray:
        """The targets of every mode, float32 [K, H, W, 3] (K = ``modes``)."""
        return np.stack([self.target(original, ratio, instruction, k) for k in range(self.modes)])

    def mode_probabilities(self, image, original, embedding, timestep: float = 0.5) -> np.ndarray:
        """p_k of the mode draw for the render ``image``, embedding e(r) and SDEdit timestep t,
        float [K]."""
        image, original = _as_image(image, "image"), _as_image(original, "original")
        if not 0.0 <= float(timestep) <= 1.0:
            raise DataError("timestep", f"must be in [0, 1], got {timestep!r}")
        i, r = self.decode(embedding)
        kind, s = ("colour", 0.0) if i is None else (INSTRUCTIONS[i].kind, self.strength(r, i))
        return np.asarray(_probabilities_impl(jnp.asarray(image), jnp.asarray(original),
                                              jnp.float32(s), jnp.float32(timestep),
                                              self._points(original), kind=kind,
                                              params=self.params))

    def target_of_embedding(self, original, embedding) -> np.ndarray:
        """The noise-free target for an embedding e(r) (the original for the null embedding)."""
        i, r = self.decode(embedding)
        original = _as_image(original, "original")
        return original.copy() if i is None else self.target(original, r, i)

    def relevance(self, image, original, embedding, key: jax.Array, *,
                  timestep_range: tuple[float, float] = (0.02, 0.98),
                  guidance: tuple[float, float] | None = None) -> np.ndarray:
        """Where the instruction changes the view: float32 [H, W] in {0, 1}.

        From the noise-free target: |target - original| (channel mean), normalised,
        smoothed and thresholded (:func:`jaxedit.editors.base.relevance_mask`). ``image``,
        ``key``, ``timestep_range`` and ``guidance`` are the protocol's; the target does
        not depend on them.
        """

        original = _as_image(original, "original")
        target = self.target_of_embedding(original, embedding)
        return np.asarray(relevance_mask(np.abs(target - original).mean(-1)))

    def edit(self, image, original, embedding, key: jax.Array, *,
             timestep_range: tuple[float, float] = (0.02, 0.98),
             guidance: tuple[float, float] | None = None) -> np.ndarray:
        """Edit one view: float32 [H, W, 3] in [0, 1], deterministic given ``key``.

        The arguments are those of :meth:`edit_with_mode`, which also returns the drawn mode.
        """
        return self.edit_with_mode(image, original, embedding, key, timestep_range=timestep_range,
                                   guidance=guidance)[0]

    def edit_with_mode(self, image, original, embedding, key: jax.Array, *,
                       timestep_range: tuple[float, float] = (0.02, 0.98),
                       guidance: tuple[float, float] | None = None) -> tuple[np.ndarray, int]:
        """(edited view float32 [H, W, 3] in [0, 1], the mode k it was drawn in).

        Args:
          image: float [H, W, 3], the current render of the view.
          original: float [H, W, 3], the original photo of the view (targets are functions of it).
          embedding: e(r) from ``encode`` and ``interpolate_embedding``.
          key: a ``jax.random`` key (see :func:`view_key`).
          timestep_range: (t_min, t_max) in [0, 1]; t ~ U(t_min, t_max), and a fraction
            cos(pi t / 2) of ``image`` survives.
          guidance: (text, image) classifier-free guidance scales; they scale the perturbation
            (None: :attr:`guidance`, InstructPix2Pix's 7.5, 1.5, where the scale is 1).
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
        gt, gi = editor_guidance(self, guidance)
        i, r = self.decode(embedding)
        kind, s = ("colour", 0.0) if i is None else (INSTRUCTIONS[i].kind, self.strength(r, i))
        gscale = (gt / IP2P_GUIDANCE[0]) * math.sqrt(IP2P_GUIDANCE[1] / gi)
        out, mode = _edit_impl(jnp.asarray(image), jnp.asarray(original), jnp.float32(s), key,
                               jnp.asarray([t0, t1], jnp.float32), jnp.float32(gscale),
                               self._points(original), kind=kind, params=self.params)
        return np.asarray(out), int(mode)
