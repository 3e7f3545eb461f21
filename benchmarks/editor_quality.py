"""Quality of the bundled InstructPix2Pix on held-out cameras
(:mod:`jaxedit_lab.train_editor.quality`).

Rebuilds the edit dataset with the settings the model lists in its ``instructions.json``,
keeps the held-out cameras only, and measures per instruction: the full edit's PSNR against
its target (nearest outcome), identity with E(""), the outcome frequencies and mixing of the
divergent instructions from fresh noise, SDEdit holding at T = 0.45 / 0.85 for a small ratio
step and for the jump to r = 1, and d(0, r) along the text interpolation (the difficulty's
distance: LPIPS where its weights are, else MS-SSIM). The divergent instructions' outcomes
are classed with :mod:`jaxedit_lab.outcome_class` (one outcome / unedited / mixed /
other, against the unedited input); identity is measured at ProEdit's SDEdit range (T = 0.45,
0.85) and at T = 0.98, beside the VAE round trip; ``goals`` checks issue 51's goals on
these figures. Also writes ``editor_quality.png``: per held-out view and instruction, the
input, each outcome's target and four edits at T = 0.98.

The held-out cameras lie on the training orbits; each one's PSNR to the nearest training
frame of its scene is in ``nearest_training_psnr_db``. ``novel`` holds the same figures (but
holding and interpolation) on ``--novel-views`` cameras per procedural scene off the orbits
(:func:`jaxedit_lab.train_editor.edit_data.novel_views`: nearer, above the elevation
band), with their own nearest-frame PSNRs and goals, and ``editor_quality_novel.png``.

    python benchmarks/editor_quality.py                 # the committed record (CPU, minutes)
    python benchmarks/editor_quality.py --smoke         # CI: two views, two DDIM steps
    python benchmarks/editor_quality.py --weights runs/editor/model
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from common import parse_args, peak_rss_mb, write_json
from experiments.flags import guidance_pair

import jax


def _extra(p):
    p.add_argument("--weights", type=Path, default=None,
                   help="diffusers folder (default: the bundled editor)")
    p.add_argument("--steps", type=int, default=20, help="DDIM steps per edit")
    p.add_argument("--draws", type=int, default=4, help="edits per view (divergent)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--guidance", type=guidance_pair, default=None,
                   help="TEXT,IMAGE classifier-free guidance scales of every edit (default: "
                        "the editor's own, what its folder recommends, as an edit run uses)")
    p.add_argument("--novel-views", type=int, default=6,
                   help="cameras off the training orbit per procedural scene (0: none)")


def contact_sheet(editor, data, views, key, path: Path, guidance=None) -> None:
    """A PNG: one row per (held-out view, instruction): input, outcome targets, 4 edits."""
    from jaxedit_lab.train_editor.edit_data import outcome_targets
    from jaxedit_lab.train_editor.quality import run_edits
    from jaxedit.io.images import write_image

    inputs = data.inputs.astype(np.float32) / 255
    rows = []
    for v in views:
        for i, ins in enumerate(data.instructions):
            if not ins.applies_to(data.scenes[data.scene[v]]):
                continue
            e = editor.encode(ins.prompt)
            edited = run_edits(editor, inputs[[v] * 4], inputs[[v] * 4], np.stack([e] * 4),
                               jax.random.fold_in(key, 1000 * v + i), 0.98, guidance)
            targets = list(outcome_targets(data, v, i))
            blank = np.ones_like(inputs[v])
            cells = [inputs[v], *targets, *[blank] * (3 - len(targets)), blank, *edited]
            rows.append(np.concatenate(cells, 1))
    write_image(path, np.concatenate(rows, 0))


def goals(result: dict) -> dict:
    """Issue 51's goals, each with the figures it is judged on and whether it is met."""
    out = {}
    divergent = {p: e for p, e in result["instructions"].items() if "outcome_frequencies" in e}
    freq_ok = {p: e["outcome_frequencies"] is not None
               and all(f is not None and 0.20 <= f <= 0.45 for f in e["outcome_frequencies"])
               for p, e in divergent.items()}
    # Beside each frequency goal, its 95 % interval over the views (judged on the value; the
    # interval says whether a miss or a pass near the edge could be the views' sampling).
    def interval(e, name):
        return e.get("intervals", {}).get(name)

    out["single_outcome_fraction >= 0.8"] = {
        p: {"value": e["single_outcome_fraction"],
            "interval": interval(e, "single_outcome_fraction"),
            "met": e["single_outcome_fraction"] is not None
            and e["single_outcome_fraction"] >= 0.8} for p, e in divergent.items()}
    out["each outcome 20-45 % of edited draws"] = {
        p: {"value": e["outcome_frequencies"], "interval": interval(e, "outcome_frequencies"),
            "met": freq_ok[p]} for p, e in divergent.items()}
    vae = result.get("vae_roundtrip_psnr_db")
    ident = result["identity_psnr_db"]
    low = {t: v for t, v in ident.items() if float(t) <= 0.85}
    out["identity within 1 dB of the VAE round trip at T <= 0.85"] = {
        "identity_psnr_db": low, "vae_roundtrip_psnr_db": vae,
        "met": vae is not None and all(v >= vae - 1.0 for v in low.values())}
    t98 = result.get("identity_t098_psnr_db")
    out["identity >= 25 dB at T = 0.98 (no colour cast)"] = {
        "value": t98, "met": t98 is not None and t98 >= 25.0}
    single = {p: e for p, e in result["instructions"].items() if "outcome_frequencies" not in e}
    per_scene = [(f"{p} ({scene})", x) for p, e in single.items()
                 for scene, x in e["per_scene"].items()]
    out["one-outcome edit closer to its target than the input, per scene"] = {
        who: {"edit_psnr": x["psnr"], "input_psnr": x["psnr_unedited"],
              "ceiling_psnr": x.get("psnr_ceiling"), "met": x["psnr"] > x["psnr_unedited"]}
        for who, x in per_scene}
    # Not issue 51's goal, beside it: where a target differs from its input by less than the
    # autoencoder loses (the input above the ceiling: a small ball grown on `tabletop`), no
    # edit through the latents passes the input; against the input's round trip the edit's
    # own part is what is judged.
    out["(beside it) the edit closer to its target than the input's VAE round trip"] = {
        who: {"edit_psnr": x["psnr"], "vae_roundtrip_psnr": x.get("psnr_vae_roundtrip"),
              "met": x.get("psnr_vae_roundtrip") is not None
              and x["psnr"] > x["psnr_vae_roundtrip"]} for who, x in per_scene}
    return out


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv, _extra)
    from jaxedit.edit.difficulty import default_distance
    from jaxedit.editors.jax_ip2p import JaxIP2PEditor
    from jaxedit.editors import bundled_editor
    from jaxedit_lab.train_editor import rebuild_dataset, trained_on
    from jaxedit_lab.train_editor.edit_data import (NOVEL_ELEVATION_DEG, NOVEL_RADIUS,
                                                          nearest_training_psnr, novel_dataset,
                                                          separation)
    from jaxedit_lab.train_editor.quality import evaluate

    folder = args.weights or bundled_editor()
    settings = trained_on(folder)
    size = int(settings["size"])
    steps = 2 if args.smoke else args.steps
    t0 = time.perf_counter()
    data = rebuild_dataset(settings)
    held = np.flatnonzero(data.held_out)
    if args.smoke:  # one held-out view of each scene
        held = np.array([held[data.scene[held] == s][0] for s in range(len(data.scenes))])
    dataset_s = time.perf_counter() - t0
    editor = JaxIP2PEditor.from_pretrained(folder, size=size, steps=steps)
    distance = default_distance("auto")
    key = jax.random.key(args.seed)
    t0 = time.perf_counter()
    result = evaluate(editor, data, held, key, distance=distance,
                      draws=1 if args.smoke else args.draws,
                      hold_views=2 if args.smoke else 16, interp_views=1 if args.smoke else 8,
                      ratios=(0.0, 0.5, 1.0) if args.smoke else tuple(np.linspace(0, 1, 9)),
                      guidance=args.guidance, log=print)
    seconds = time.perf_counter() - t0
    # The dataset's own property: how far apart the divergent outcomes are on these views.
    result["separation"] = separation(data, distance, held)
    # How novel each held-out view is: PSNR to the nearest training frame of its scene.
    near = nearest_training_psnr(data, held, data)
    result["nearest_training_psnr_db"] = {
        name: [round(x, 2) for v, x in zip(held, near) if data.scene[v] == s]
        for s, name in enumerate(data.scenes)}
    args.out.mkdir(parents=True, exist_ok=True)
    contact_sheet(editor, data, held[:: max(1, len(held) // 6)][:6], jax.random.fold_in(key, 7),
                  args.out / "editor_quality.png", args.guidance)
    if args.novel_views:  # cameras off the training orbits: the same figures, no holding
        novel = novel_dataset(size, 1 if args.smoke else args.novel_views,
                              tuple(settings["scenes"]), int(settings["procedural_views"]))
        views = np.arange(len(novel.inputs))
        t0 = time.perf_counter()
        result["novel"] = evaluate(editor, novel, views, jax.random.fold_in(key, 11),
                                   draws=1 if args.smoke else args.draws, hold_views=0,
                                   guidance=args.guidance, log=print)
        result["novel"]["cameras"] = {"radius": NOVEL_RADIUS,
                                      "elevation_above_band_deg": list(NOVEL_ELEVATION_DEG)}
        near = nearest_training_psnr(novel, views, data)
        result["novel"]["nearest_training_psnr_db"] = {
            name: [round(x, 2) for v, x in zip(views, near) if novel.scene[v] == s]
            for s, name in enumerate(novel.scenes)}
        result["novel"]["goals"] = goals(result["novel"])
        seconds += time.perf_counter() - t0
        contact_sheet(editor, novel, views[:: max(1, len(views) // 4)][:4],
                      jax.random.fold_in(key, 13), args.out / "editor_quality_novel.png",
                      args.guidance)
    from jaxedit_lab import outcome_class as oc

    result["outcome_measure"] = {
        "module": "jaxedit_lab.outcome_class",
        "classes": "outcome k / unedited / mixed / other, against the unedited input",
        "edited_progress": oc.EDITED_PROGRESS, "pure_share": oc.PURE_SHARE,
        "other_residual": oc.OTHER_RESIDUAL}
    result["goals"] = goals(result)
    result["held_out_note"] = (
        "held-out views are the dataset's held-out cameras (every "
        f"{settings['holdout_every']}th procedural camera, person's test views), on the "
        "training orbits (nearest_training_psnr_db says how near); 'novel' has the same figures "
        "on cameras off the orbits (procedural scenes: nearer, above the elevation band)")
    write_json(args.out, "editor_quality", {"command": " ".join(["python",
                                                                 "benchmarks/editor_quality.py",
                                                                 *(argv or __import__("sys")
                                                                   .argv[1:])]),
                                            "draws_per_view": args.draws,
        # The bundled folder by its place in the package, not this machine's path.
        "weights": str(folder) if args.weights else "jaxedit/editors/weights/tiny-ip2p",
        "smoke": args.smoke, "size": size, "ddim_steps": steps,
        "distance": getattr(distance, "name", getattr(distance, "__name__", str(distance))),
        "dataset": settings, "held_out_views": int(len(held)),
        "seconds": {"dataset": round(dataset_s, 1), "evaluation": round(seconds, 1)},
        "peak_rss_mb": round(peak_rss_mb(), 1), **result})


if __name__ == "__main__":
    from jaxedit.errors import DataError

    try:
        main()
    except DataError as e:  # --weights: a folder with no training record, unreadable weights
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
