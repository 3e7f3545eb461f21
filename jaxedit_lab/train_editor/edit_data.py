"""The edit dataset the bundled InstructPix2Pix is trained on: (view, instruction, edited view).

Views come from the built-in scenes: the Cycles renders of ``person`` (its 72 training and 8
test cameras, RGBA, downscaled) and the procedural scenes, ray-cast on their rigs' spirals
(every ``HOLDOUT_EVERY``-th camera held out, as :func:`jaxedit.scenes.split_views` spaces
them) and, optionally, on a nearer sphere (:func:`off_orbit_views`, all trained on).
Held-out cameras are never trained on; the quality benchmark edits them, and
:func:`novel_dataset` the same scenes from cameras on none of the training spheres
(:func:`nearest_training_psnr` says how far each is from its nearest training frame).

Every instruction (:data:`INSTRUCTIONS`) has one or several *outcomes*, each a deterministic
function of the view, so a divergent instruction's outcome is drawn at random per training
example and the model must learn a multimodal distribution, as IP2P does from real data:

============================  ===========  =========================================================
prompt                        kind         outcomes (how the edited view is made)
============================  ===========  =========================================================
turn him into a bronze statue material     1: shading through a bronze ramp, inside the silhouette
make it black and white       colour       1: luma, inside the silhouette
splash some colour on it      colour       3: the shadows red, the mid-tones green or the highlights
                                           blue (colour replaced, shading kept)
add a neon accent             colour       3: the shadows yellow, the mid-tones magenta or the
                                           highlights cyan
make his shirt blue           local        1 (face): the shoulders' albedo changed, re-rendered
make the ball bigger          geometry     1 (ball, tabletop): the sphere scaled, re-rendered
============================  ===========  =========================================================

Image-space outcomes act inside the object's alpha (the white backdrop stays): a function of
each pixel's colour only, so they are consistent across views. The divergent instructions'
outcomes each change one luma band of the object (the terciles over its training orbit:
shadows, mid-tones, highlights, the same from every camera), so any two outcomes differ in
two bands where each differs from the original in one: pairwise farther apart than from the
original, and about equally far from it (a global recolouring would not do: to a perceptual
distance, red and blue versions of a view are closer to each other than to the original).
The local and geometry edits change the scene and render it again, so they are exactly 3D
consistent, shadows included.

:func:`build_dataset` is pure given its arguments (the ray caster is deterministic); the
arrays it returns are uint8 images, a few tens of MB at 64 px.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from jaxedit.errors import DataError, quoted

#: Every HOLDOUT_EVERY-th camera of a procedural scene's spiral is held out (person: its own
#: test split).
HOLDOUT_EVERY = 10


#: The kinds of instruction: the image-space edits (a material, colours), the local edit and
#: the geometry edit (a changed scene, rendered).
KINDS = ("material", "colour", "local", "geometry")


@dataclasses.dataclass(frozen=True)
class Instruction:
    """One instruction of the dataset.

    prompt: the text; kind: one of :data:`KINDS`; outcomes: the names of
    its outcomes (one for a deterministic edit); scenes: the scenes it applies to (None: all).
    """

    prompt: str
    kind: str
    outcomes: tuple[str, ...]
    scenes: tuple[str, ...] | None = None

    def applies_to(self, scene: str) -> bool:
        return self.scenes is None or scene in self.scenes

    def describe(self) -> dict:
        """The instructions.json entry."""
        return {"prompt": self.prompt, "kind": self.kind, "outcomes": len(self.outcomes),
                "outcome_names": list(self.outcomes),
                "scenes": list(self.scenes) if self.scenes else "all"}


INSTRUCTIONS: tuple[Instruction, ...] = (
    Instruction("turn him into a bronze statue", "material", ("bronze",)),
    Instruction("make it black and white", "colour", ("grey",)),
    Instruction("splash some colour on it", "colour", ("red shadows", "green mid-tones",
                                                       "blue highlights")),
    Instruction("add a neon accent", "colour", ("yellow shadows", "magenta mid-tones",
                                                 "cyan highlights")),
    Instruction("make his shirt blue", "local", ("blue shirt",), scenes=("face",)),
    Instruction("make the ball bigger", "geometry", ("bigger",), scenes=("ball", "tabletop")),
)

#: The scenes of the dataset: the rendered person and the procedural ones.
SCENES = ("person", "face", "tabletop", "fence", "ball")


def instruction(prompt: str) -> Instruction:
    for ins in INSTRUCTIONS:
        if ins.prompt == prompt:
            return ins
    raise DataError("prompt", f"not an instruction of the dataset: {quoted(prompt)}")


# ----------------------------------------------------------------------------- image outcomes

def luma(x: np.ndarray) -> np.ndarray:
    """Rec. 601 luma, float [..., 3] -> [...]."""
    return x[..., 0] * 0.299 + x[..., 1] * 0.587 + x[..., 2] * 0.114


def _ramp(t: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """Piecewise-linear colour ramp: t [...] in [0, 1], stops [K, 3] evenly spaced -> [..., 3]."""
    k = len(stops) - 1
    pos = np.clip(t, 0.0, 1.0) * k
    i = np.minimum(pos.astype(np.int64), k - 1)
    f = (pos - i)[..., None]
    return stops[i] * (1 - f) + stops[i + 1] * f


_BRONZE = np.array([[0.10, 0.05, 0.02], [0.45, 0.26, 0.10], [0.78, 0.55, 0.27],
                    [0.98, 0.86, 0.60]], np.float32)

_SPLASH = ((0.90, 0.10, 0.10), (0.10, 0.80, 0.20), (0.15, 0.30, 0.95))
_NEON = ((0.98, 0.85, 0.05), (0.95, 0.10, 0.85), (0.05, 0.85, 0.95))


def _bronze(x, bands):
    l_ = luma(x)
    return _ramp(np.clip((l_ - 0.5) * 1.25 + 0.5, 0, 1), _BRONZE)


def _grey(x, bands):
    return np.repeat(luma(x)[..., None], 3, -1)


#: Width of the soft edge between two luma bands.
BAND_EDGE = 0.05


def band_weight(l_: np.ndarray, bands: tuple[float, float], k: int) -> np.ndarray:
    """Membership in [0, 1] of luma ``l_`` [...] in band k (0: below bands[0], 1: between,
    2: above bands[1]), with soft edges."""
    def above(t):
        return np.clip((l_ - t) / BAND_EDGE + 0.5, 0, 1)
    lo, hi = above(bands[0]), above(bands[1])
    return (1 - lo, lo - hi, hi)[k]


def _in_band(k, effect):
    def edit(x, bands):
        w = band_weight(luma(x), bands, k)[..., None]
        return x * (1 - w) + effect(x) * w
    return edit


def _paint(colour, floor: float, gain: float):
    """The colour replaced by ``colour``, shaded by the luma: colour (floor + gain luma)."""
    c = np.asarray(colour, np.float32)
    return lambda x: np.clip(c * (floor + gain * luma(x)[..., None]), 0, 1)


#: (prompt, outcome) -> image function (rgb [..., 3], the scene's luma bands) -> [..., 3].
IMAGE_OUTCOMES: dict[tuple[str, str], Callable[[np.ndarray, tuple], np.ndarray]] = {
    ("turn him into a bronze statue", "bronze"): _bronze,
    ("make it black and white", "grey"): _grey,
    **{("splash some colour on it", name): _in_band(k, _paint(_SPLASH[k], 0.35, 0.9))
       for k, name in enumerate(("red shadows", "green mid-tones", "blue highlights"))},
    **{("add a neon accent", name): _in_band(k, _paint(_NEON[k], 0.45, 0.7))
       for k, name in enumerate(("yellow shadows", "magenta mid-tones", "cyan highlights"))},
}


def luma_bands(rgba: np.ndarray) -> tuple[float, float]:
    """The terciles of the object's luma over all views of a scene (rgba [N, H, W, 4]): the
    edges of its shadows, mid-tones and highlights."""
    covered = rgba[..., 3] > 0.5
    lo, hi = np.quantile(luma(rgba[..., :3])[covered], [1 / 3, 2 / 3])
    return float(lo), float(hi)


def apply_image_outcome(prompt: str, outcome: str, rgb: np.ndarray, alpha: np.ndarray,
                        bands: tuple[float, float], background=(1.0, 1.0, 1.0)) -> np.ndarray:
    """An image-space outcome inside the silhouette: float32 [..., H, W, 3] in [0, 1].

    ``rgb``: straight colour [..., H, W, 3]; ``alpha``: coverage [..., H, W]; ``bands``: the
    scene's :func:`luma_bands`; the result is composited over ``background`` as the
    original view is.
    """
    edited = IMAGE_OUTCOMES[(prompt, outcome)](rgb, bands)
    a = alpha[..., None]
    return (a * edited + (1 - a) * np.asarray(background, np.float32)).astype(np.float32)


# ----------------------------------------------------------------------------- scene outcomes

def _edited_scene(scene, prompt: str):
    """The procedural scene changed by a local or geometry instruction."""
    shapes = list(scene.shapes)
    names = [s.name for s in shapes]
    if prompt == "make his shirt blue":
        i = names.index("shoulders")
        shapes[i] = dataclasses.replace(shapes[i], color=(0.12, 0.25, 0.85), texture=None)
    elif prompt == "make the ball bigger":
        i = names.index("red_ball" if "red_ball" in names else "ball")
        s = shapes[i]
        grow = 1.7 if s.name == "red_ball" else 1.25
        size = tuple(v * grow for v in s.size)
        # A ball resting on the table stays on it: its centre rises with its radius.
        center = (s.center[0], s.center[1], s.center[2] + (size[2] - s.size[2])) \
            if s.name == "red_ball" else s.center
        shapes[i] = dataclasses.replace(s, size=size, center=center)
    else:
        raise DataError("prompt", f"{quoted(prompt)} is not a scene edit")
    return dataclasses.replace(scene, shapes=tuple(shapes))


# ----------------------------------------------------------------------------- views

@dataclasses.dataclass(frozen=True)
class SceneViews:
    """One scene's views: rgba float32 [N, H, W, 4] (straight colour, coverage), held_out bool
    [N], the scene's luma bands (:func:`luma_bands` of its training orbit, whatever cameras
    these are: an outcome recolours a surface by its colour, so the same surface falls in the
    same band from every camera), the rig cameras (None for a rendered dataset) and the
    instruction kinds (:attr:`Instruction.kind`) whose edit targets are made for these views
    (none: the views are inputs only, identity examples)."""

    name: str
    rgba: np.ndarray
    held_out: np.ndarray
    bands: tuple[float, float]
    cameras: object = None
    edit_kinds: tuple[str, ...] = KINDS


def person_views(size: int) -> SceneViews:
    """The person renders at ``size`` px (256 / size must be an integer), its test split held out."""
    import json

    from jaxedit.scenes import dataset_path
    from jaxedit.scenes.dataset import _rgba_downscaled

    root = dataset_path("person")
    meta = json.loads((root / "transforms.json").read_text())
    if 256 % size:
        raise DataError("size", f"256 / size must be an integer for person, got {size}")
    test = set(meta.get("test_filenames", []))
    files = [f["file_path"] for f in meta["frames"]]
    rgba = np.stack([_rgba_downscaled(root / f, 256 // size) for f in files])
    return SceneViews("person", rgba, np.array([f in test for f in files]), luma_bands(rgba))


def procedural_views(name: str, size: int, views: int, scene=None) -> SceneViews:
    """``views`` spiral cameras of a procedural scene, every HOLDOUT_EVERY-th held out."""
    from jaxedit.scenes import get_scene, render_scene, rig_cameras

    scene = get_scene(name) if scene is None else scene
    cams = rig_cameras(scene.rig, views, width=size)
    rgba = render_scene(scene, cams, alpha=True)
    held = (np.arange(views) % HOLDOUT_EVERY) == HOLDOUT_EVERY // 2
    return SceneViews(name, rgba, held, luma_bands(rgba), cams)


#: Novel cameras of a procedural scene (evaluation only, never trained on): off the training
#: orbit, on a sphere NOVEL_RADIUS times the rig's and over an elevation band
#: NOVEL_ELEVATION_DEG above the top of the rig's, so no training camera is near them.
NOVEL_RADIUS = 0.85
NOVEL_ELEVATION_DEG = (8.0, 22.0)

#: The nearer training cameras (``off_orbit_views``): on a sphere OFF_ORBIT_RADIUS times the
#: rig's, from the bottom of the rig's elevation band up to OFF_ORBIT_TOP_DEG, so the object
#: is seen larger than on the orbit and from above it, as close-ups and top views of a capture
#: see it. The novel cameras lie between the two spheres: no training camera is near them
#: (:func:`nearest_training_psnr`), but the nearer sphere's band spans their elevations.
OFF_ORBIT_RADIUS = 0.7
OFF_ORBIT_TOP_DEG = 85.0


def _rig_views(name: str, size: int, rig, views: int, scene, bands, held_out,
               edit_kinds: tuple[str, ...] = KINDS) -> SceneViews:
    from jaxedit.scenes import render_scene, rig_cameras

    cams = rig_cameras(rig, views, width=size)
    return SceneViews(name, render_scene(scene, cams, alpha=True), held_out, bands, cams,
                      edit_kinds)


def novel_views(name: str, size: int, views: int, scene=None,
                orbit_views: int = 100) -> SceneViews:
    """``views`` cameras of a procedural scene off its training orbit (:data:`NOVEL_RADIUS`,
    :data:`NOVEL_ELEVATION_DEG`), every one held out; its bands are those of the scene's
    ``orbit_views`` training cameras."""
    from jaxedit.scenes import get_scene

    scene = get_scene(name) if scene is None else scene
    rig = scene.rig
    top = rig.elevation_deg[1]
    novel = dataclasses.replace(rig, radius=rig.radius * NOVEL_RADIUS,
                                elevation_deg=(min(top + NOVEL_ELEVATION_DEG[0], 80.0),
                                               min(top + NOVEL_ELEVATION_DEG[1], 85.0)))
    bands = procedural_views(name, size, orbit_views, scene).bands
    return _rig_views(name, size, novel, views, scene, bands, np.ones(views, bool))


def off_orbit_views(name: str, size: int, views: int, scene, bands,
                    edit_kinds: tuple[str, ...] = KINDS) -> SceneViews:
    """``views`` training cameras of a procedural scene nearer than its orbit and up to above
    it (:data:`OFF_ORBIT_RADIUS`, :data:`OFF_ORBIT_TOP_DEG`), none held out, with the orbit's
    ``bands``; ``edit_kinds``: the instruction kinds whose edit targets are made for them
    (:class:`SceneViews`)."""
    rig = dataclasses.replace(scene.rig, radius=scene.rig.radius * OFF_ORBIT_RADIUS,
                              elevation_deg=(scene.rig.elevation_deg[0], OFF_ORBIT_TOP_DEG))
    return _rig_views(name, size, rig, views, scene, bands, np.zeros(views, bool), edit_kinds)


def composite(rgba: np.ndarray, background=(1.0, 1.0, 1.0)) -> np.ndarray:
    """[..., 4] straight RGBA -> [..., 3] over ``background`` (ray-cast RGB is already over it)."""
    a = rgba[..., 3:]
    return (a * rgba[..., :3] + (1 - a) * np.asarray(background, np.float32)).astype(np.float32)


# ----------------------------------------------------------------------------- the dataset

@dataclasses.dataclass(frozen=True)
class EditDataset:
    """All pairs, as uint8 images.

    inputs: uint8 [N, H, W, 3], the views; scene: int [N] index into ``scenes``; held_out:
      bool [N].
    targets: uint8 [M, H, W, 3], one per (view, instruction, outcome) that applies;
      target_view int [M] (row of ``inputs``), target_instruction int [M] (into
      ``instructions``), target_outcome int [M] (into that instruction's outcomes).
    """

    scenes: tuple[str, ...]
    instructions: tuple[Instruction, ...]
    inputs: np.ndarray
    scene: np.ndarray
    held_out: np.ndarray
    targets: np.ndarray
    target_view: np.ndarray
    target_instruction: np.ndarray
    target_outcome: np.ndarray

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in ("inputs", "scene", "held_out", "targets",
                                              "target_view", "target_instruction",
                                              "target_outcome")}

    def split(self, held_out: bool) -> np.ndarray:
        """Target rows whose view is (not) held out: int [K]."""
        return np.flatnonzero(self.held_out[self.target_view] == held_out)


def to_uint8(x: np.ndarray) -> np.ndarray:
    return np.round(np.clip(x, 0, 1) * 255).astype(np.uint8)


def scene_pairs(views: SceneViews, scene_obj=None):
    """(inputs float32 [N, H, W, 3], [(instruction index, outcome index, targets [N, H, W, 3])]);
    targets only for the instructions of the views' ``edit_kinds``."""
    rgb = composite(views.rgba)
    bands = views.bands
    pairs = []
    for i, ins in enumerate(INSTRUCTIONS):
        if not ins.applies_to(views.name) or ins.kind not in views.edit_kinds:
            continue
        if ins.kind in ("local", "geometry"):
            edited = _edited_scene(scene_obj, ins.prompt)
            from jaxedit.scenes import render_scene

            pairs.append((i, 0, render_scene(edited, views.cameras)))
            continue
        for k, outcome in enumerate(ins.outcomes):
            pairs.append((i, k, apply_image_outcome(ins.prompt, outcome, views.rgba[..., :3],
                                                    views.rgba[..., 3], bands)))
    return rgb, pairs


def build_dataset(size: int = 64, procedural_views_per_scene: int = 100,
                  scenes: tuple[str, ...] = SCENES, progress=None,
                  off_orbit_views_per_scene: int = 0,
                  off_orbit_edits: bool = True,
                  off_orbit_geometry_only: bool = False) -> EditDataset:
    """Render every scene's views and every outcome of every instruction that applies.

    A procedural scene has ``procedural_views_per_scene`` cameras on its orbit (every
    HOLDOUT_EVERY-th held out) and, after them, ``off_orbit_views_per_scene`` nearer
    training cameras (:func:`off_orbit_views`), with the instructions' edit targets if
    ``off_orbit_edits`` (only the geometry instruction's if ``off_orbit_geometry_only``) and
    as identity examples only if not. ``progress(name)`` is called after each scene (for a
    progress bar). Deterministic.
    """
    from jaxedit.scenes import get_scene, list_scenes

    for name in scenes:
        if name not in list_scenes():
            raise DataError("--scenes", f"unknown scene {name!r}; built-in scenes: "
                                        f"{', '.join(list_scenes())}")

    near_kinds = (("geometry",) if off_orbit_geometry_only else KINDS) if off_orbit_edits else ()

    def views_of(name):
        if name == "person":
            return [person_views(size)], None
        obj = get_scene(name)
        orbit = procedural_views(name, size, procedural_views_per_scene, obj)
        if not off_orbit_views_per_scene:
            return [orbit], obj
        return [orbit, off_orbit_views(name, size, off_orbit_views_per_scene, obj,
                                       orbit.bands, near_kinds)], obj

    return _assemble(scenes, views_of, progress)


def novel_dataset(size: int = 64, views_per_scene: int = 10,
                  scenes: tuple[str, ...] = SCENES, orbit_views: int = 100) -> EditDataset:
    """The procedural scenes of ``scenes`` seen from :func:`novel_views` cameras, with every
    outcome (in the bands of the scene's ``orbit_views`` training cameras), all held out (the
    person's renders have no camera off their arc to render)."""
    from jaxedit.scenes import get_scene

    def views_of(name):
        obj = get_scene(name)
        return [novel_views(name, size, views_per_scene, obj, orbit_views)], obj

    return _assemble(tuple(n for n in scenes if n != "person"), views_of)


def nearest_training_psnr(data: EditDataset, views, training: EditDataset) -> list[float]:
    """Per view of ``data`` (rows ``views``), the PSNR (dB) to the nearest training view of
    the same scene in ``training``: how novel a held-out camera is (near 30 dB and above:
    a near duplicate of a training frame)."""
    out = []
    for v in views:
        name = data.scenes[data.scene[v]]
        rows = np.flatnonzero(~training.held_out
                              & (training.scene == training.scenes.index(name)))
        x = data.inputs[v].astype(np.float64) / 255
        mse = np.mean((training.inputs[rows].astype(np.float64) / 255 - x) ** 2, axis=(1, 2, 3))
        out.append(float(-10 * np.log10(max(float(mse.min()), 1e-10))))
    return out


def _assemble(scenes: tuple[str, ...], views_of, progress=None) -> EditDataset:
    """The dataset of ``scenes``, each scene's ([SceneViews, ...], scene object) from
    ``views_of``."""
    inputs, scene_ids, held, targets, t_view, t_ins, t_out = [], [], [], [], [], [], []
    offset = 0
    for s, name in enumerate(scenes):
        camera_sets, obj = views_of(name)
        for views in camera_sets:
            rgb, pairs = scene_pairs(views, obj)
            n = len(rgb)
            inputs.append(to_uint8(rgb))
            scene_ids.append(np.full(n, s))
            held.append(views.held_out)
            for i, k, images in pairs:
                targets.append(to_uint8(images))
                t_view.append(offset + np.arange(n))
                t_ins.append(np.full(n, i))
                t_out.append(np.full(n, k))
            offset += n
        if progress is not None:
            progress(name)
    cat = np.concatenate
    return EditDataset(tuple(scenes), INSTRUCTIONS, cat(inputs), cat(scene_ids).astype(np.int32),
                       cat(held), cat(targets), cat(t_view).astype(np.int32),
                       cat(t_ins).astype(np.int32), cat(t_out).astype(np.int32))


def outcome_targets(data: EditDataset, view: int, instruction_index: int) -> np.ndarray:
    """float32 [K, H, W, 3]: every outcome of one instruction for one view (K outcomes)."""
    rows = np.flatnonzero((data.target_view == view) & (data.target_instruction == instruction_index))
    rows = rows[np.argsort(data.target_outcome[rows])]
    return data.targets[rows].astype(np.float32) / 255


def separation(data: EditDataset, distance, views) -> dict:
    """How far apart the outcomes of each divergent instruction are, by ``distance`` (the
    difficulty's: ``(a [H, W, 3], b [H, W, 3]) -> float``), averaged over ``views``.

    Returns {prompt: {"to_original": [K] mean d(original, outcome k), "pairwise": [K][K],
    "separated": bool}}: an instruction is well separated when every pairwise distance
    exceeds every distance to the original.
    """
    out = {}
    for i, ins in enumerate(data.instructions):
        if len(ins.outcomes) < 2:
            continue
        vs = [int(v) for v in views if ins.applies_to(data.scenes[data.scene[v]])]
        k = len(ins.outcomes)
        origs = [data.inputs[v].astype(np.float32) / 255 for v in vs]
        outs = [outcome_targets(data, v, i) for v in vs]  # each [K, H, W, 3]

        def mean_d(a, b):
            return float(np.mean([distance(x, y) for x, y in zip(a, b)]))

        to_orig = [mean_d(origs, [o[a] for o in outs]) for a in range(k)]
        pair = [[0.0 if a == b else mean_d([o[a] for o in outs], [o[b] for o in outs])
                 for b in range(k)] for a in range(k)]
        off = [pair[a][b] for a in range(k) for b in range(k) if a != b]
        out[ins.prompt] = {"outcomes": list(ins.outcomes), "to_original": to_orig,
                           "pairwise": pair, "separated": bool(min(off) > max(to_orig))}
    return out
