"""The bundled editor's geometry edit ("make the ball bigger"), per scene: how much of the view
the ball covers in the input, the target and each edit, on the held-out views.

    python scripts/geometry_coverage.py --out benchmarks/results/cpu/geometry_coverage.json

`benchmarks/editor_quality.py` scores the instruction by PSNR over both of its scenes together
(`ball` and `tabletop`); this splits them and measures the ball itself. The edits are the
benchmark's full edits (T = 0.98, 20 DDIM steps, the editor's own guidance, 2 draws per view,
each with its own key). A pixel is the ball's where its colour is far from the background
(`ball`: the one textured sphere over the white backdrop) or red (`tabletop`: the red ball);
both thresholds are checked against the renders' own coverage on the inputs and targets.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import numpy as np


def ball_mask(rgb: np.ndarray, scene: str) -> np.ndarray:
    """bool [..., H, W]: the ball's pixels of composited views [..., H, W, 3] in [0, 1]."""
    if scene == "ball":
        return np.max(np.abs(rgb - 1.0), axis=-1) > 0.12
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    return (r > 0.35) & (r - np.maximum(g, b) > 0.25)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--draws", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--tolerance", type=float, default=0.03)
    args = p.parse_args(argv)

    from jaxedit.editors import bundled_editor
    from jaxedit.pipelines.train_editor.edit_data import (INSTRUCTIONS, _edited_scene, composite,
                                           procedural_views, to_uint8)
    from jaxedit.editors.jax_ip2p import JaxIP2PEditor
    from jaxedit.pipelines.train_editor.quality import psnr, run_edits
    from jaxedit.scenes import get_scene, render_scene

    prompt = "make the ball bigger"
    assert any(i.prompt == prompt for i in INSTRUCTIONS)
    folder = bundled_editor()
    editor = JaxIP2PEditor.from_pretrained(folder, size=64, steps=20)
    e = editor.encode(prompt)
    key = jax.random.key(args.seed)
    t0 = time.perf_counter()
    scenes = []
    for s, name in enumerate(("ball", "tabletop")):
        obj = get_scene(name)
        views = procedural_views(name, 64, 100, obj)
        held = np.flatnonzero(views.held_out)
        inputs = composite(views.rgba)[held]
        cams = views.cameras
        edited_scene = _edited_scene(obj, prompt)
        target_rgba = render_scene(edited_scene, cams, alpha=True)[held]
        # The targets as the edit dataset makes them (edit_data.scene_pairs): the ray caster's
        # RGB over the scene's backdrop, 8 bits; the inputs are composited as there too.
        targets = to_uint8(render_scene(edited_scene, cams)[held]).astype(np.float32) / 255
        inputs = to_uint8(inputs).astype(np.float32) / 255
        rows = np.repeat(np.arange(len(held)), args.draws)
        out = run_edits(editor, inputs[rows], inputs[rows], np.stack([e] * len(rows)),
                        jax.random.fold_in(key, s), 0.98)
        cov_in = ball_mask(inputs, name).mean(axis=(-2, -1))
        cov_t = ball_mask(targets, name).mean(axis=(-2, -1))
        cov_e = ball_mask(out, name).mean(axis=(-2, -1))
        within = np.abs(cov_e - cov_t[rows]) <= args.tolerance
        entry = {
            "scene": name, "views": int(len(held)), "draws": args.draws,
            "input_coverage_mean": float(cov_in.mean()),
            "target_coverage_mean": float(cov_t.mean()),
            "input_coverage": [round(float(x), 4) for x in cov_in],
            "target_coverage": [round(float(x), 4) for x in cov_t],
            "edit_coverage": [round(float(x), 4) for x in cov_e],
            "edits_within": int(within.sum()),
            "psnr_edit_vs_target": float(np.mean(psnr(out, targets[rows]))),
            "psnr_input_vs_target": float(np.mean(psnr(inputs, targets))),
        }
        if name == "ball":  # the mask against the render's own coverage (alpha)
            entry["mask_vs_alpha_input"] = float(np.abs(
                cov_in - views.rgba[held][..., 3].mean(axis=(-2, -1))).max())
            entry["mask_vs_alpha_target"] = float(np.abs(
                cov_t - target_rgba[..., 3].mean(axis=(-2, -1))).max())
        scenes.append(entry)
        print(name, {k: v for k, v in entry.items() if not isinstance(v, list)})
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({
        "what": "the ball's share of the view (its pixels found by colour: far from the white "
                "backdrop on `ball`, red on `tabletop`) in the held-out inputs, their targets "
                "and the bundled editor's full edits of `make the ball bigger`, per scene.",
        "command": "python scripts/geometry_coverage.py --out "
                   "benchmarks/results/cpu/geometry_coverage.json",
        "weights": "jaxedit/editors/weights/tiny-ip2p", "t": 0.98, "ddim_steps": 20,
        "guidance": list(editor.guidance), "seed": args.seed, "tolerance": args.tolerance,
        "seconds": round(time.perf_counter() - t0, 1), "scenes": scenes}, indent=1) + "\n")


if __name__ == "__main__":
    main()
