"""Local edits (issue 35): does ``edit --local auto`` leave the rest of the scene as it was?

    python benchmarks/local_edit.py [--smoke] [--out DIR] [--scenes person,tabletop]

Per scene (the built-in ``person``, Blender renders, and the procedural ``tabletop``), made
and reconstructed once (:func:`jaxedit.pipelines.cache.prepared_scene`, cached in
``DIR/local_edit_run/SCENE``), the simulated editor's local instruction ``paint the orange
parts blue`` (the warm, coloured pixels only swap red and blue: the person's hair and skin,
the tabletop's red ball and boxes; every other pixel of the target is the original) is run
twice with the same plan and seed: with ``local=LocalSpec("auto")`` (``edit --local auto``)
and as a global edit (``--local off``).

The region is the editable Gaussians of the local edit (:func:`jaxedit.edit.local.prepare`,
the same call and key as :func:`jaxedit.pipelines.run_edit`), rendered at the held-out
views (:func:`jaxedit.edit.local.render_editable`): inside where that weight is >= 0.5.
Scores at the held-out views:

- ``psnr_untouched``: renders vs the original reconstruction's renders, outside the region
  (goal >= 35 dB for the local edit; the global edit's figure for contrast);
- ``psnr_region_vs_target``: renders vs the editor's noise-free target (r = 1) inside the
  region (the local edit should be no worse than the global one);
- ``psnr_vs_target``: the whole view vs the target (``metrics.json``'s figure);
- ``frozen`` / ``frozen_bit_identical``: the input's Gaussians outside the editable set and
  how many of them the edit left bit for bit (means, scales, rotations, opacities, SH);
- ``relevance_seconds``: the time ``prepare`` took inside the edit (the editor's relevance
  per training view, the lifting, the rendered masks), beside the edits' wall times.

Writes ``DIR/local_edit.json`` and ``DIR/local_edit_SCENE.png`` (rows: held-out views;
columns: the reconstruction, the target, the global edit, the local edit, the region as a
heat overlay). ``--smoke``: the tabletop only, 32 px, 4 + 2 views, the dataset's initial cloud instead of
a reconstruction, one subtask of a few steps (its time is compiling: the global and the
local edit's trainers are compiled apart, the frozen mask being part of the state).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from common import parse_args, peak_rss_mb, write_json

PROMPT = "paint the orange parts blue"
SCENES = ("person", "tabletop")
FULL = dict(size=64, views=24, test_views=4, iters=1500, max_steps=300, patience=40,
            warmup=30, difficulty_views=8, subtasks=None)
#: --smoke: the procedural scene only, one subtask of a few steps on the initial cloud.
SMOKE = dict(size=32, views=4, test_views=2, iters=0, max_steps=8, patience=4, warmup=2,
             difficulty_views=2, subtasks=1)
SMOKE_POINTS = 2000
FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh")


def extra(p):
    p.add_argument("--scenes", default=None,
                   help=f"comma-separated built-in scenes (default {','.join(SCENES)}; "
                        "--smoke: tabletop)")
    p.add_argument("--seed", type=int, default=0, help="the edits' seed")


# ---------------------------------------------------------------------------
# Scores (pure)
# ---------------------------------------------------------------------------
def masked_psnr(a, b, mask) -> float | None:
    """PSNR (dB, peak 1) of images a, b float [N, H, W, 3] over the pixels of bool mask
    [N, H, W]; None for an empty mask."""
    mask = np.asarray(mask, bool)
    if not mask.any():
        return None
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64))[mask] ** 2))
    return float(-10.0 * np.log10(max(mse, 1e-12)))


def bit_identical(before, after, rows) -> int:
    """How many of the slots ``rows`` (bool [C0]) of Gaussians ``before`` (capacity C0) are
    alive in ``after`` (capacity >= C0) with every field of :data:`FIELDS` bit for bit."""
    rows = np.asarray(rows, bool)
    same = rows & np.asarray(after.alive)[:len(rows)]
    for name in FIELDS:
        a = np.asarray(getattr(before, name)).reshape(len(rows), -1)
        b = np.asarray(getattr(after, name))[:len(rows)].reshape(len(rows), -1)
        same &= np.all(a == b, axis=1)
    return int(same.sum())


def heat(image, weight):
    """``image`` float [H, W, 3] with ``weight`` [H, W] in [0, 1] as a red overlay."""
    w = np.clip(np.asarray(weight), 0, 1)[..., None]
    return (1 - 0.6 * w) * np.asarray(image) + 0.6 * w * np.array([1.0, 0.1, 0.0])


# ---------------------------------------------------------------------------
# One scene
# ---------------------------------------------------------------------------
def prepare_scene(out: Path, scene: str, sizes: dict, seed: int, log=print):
    """(EditData, the reconstruction's Gaussians) of a built-in scene, cached in ``out``."""
    from jaxedit.edit import EditData
    from jaxedit.gaussians import from_points
    from jaxedit.pipelines import reconstruct as recon_run
    from jaxedit.pipelines.cache import prepared_scene
    from jaxedit.train import TrainConfig

    iters = sizes["iters"]
    config = recon_run.ReconstructConfig(train=TrainConfig(iterations=iters)) if iters else None
    dataset, g, _ = prepared_scene(out, scene, size=sizes["size"], views=sizes["views"],
                                   test_views=sizes["test_views"], seed=0, config=config,
                                   log=log)
    if g is None:  # smoke: the dataset's initial cloud
        points, colors, _ = recon_run.capped_initial_points(dataset, SMOKE_POINTS, SMOKE_POINTS,
                                                            seed)
        g = from_points(points, colors, sh_degree=1)
    return EditData.from_dataset(dataset), g


def run_scene(out: Path, scene: str, sizes: dict, seed: int) -> dict:
    import jax

    from jaxedit.edit import ProEditConfig, TrainSettings
    from jaxedit.editors import SimulatedEditor
    from jaxedit.edit import local as L
    from jaxedit.edit.outputs import Renderer
    from jaxedit.io import write_image
    from jaxedit.pipelines import run_edit

    data, g = prepare_scene(out / "local_edit_run" / scene, scene, sizes, seed)
    editor = SimulatedEditor()
    config = ProEditConfig.for_mode("proedit", max_steps=sizes["max_steps"],
                                    patience=sizes["patience"], warmup=sizes["warmup"],
                                    difficulty_views=sizes["difficulty_views"],
                                    subtasks=sizes["subtasks"], asynchronous=False,
                                    turntable_frames=0)
    spec = L.LocalSpec("auto")
    # The region as run_edit makes it (same call, same key).
    editable, _, figures = L.prepare(spec, g, data.train_cameras, data.train_images,
                                     editor=editor, embedding=editor.encode(PROMPT),
                                     key=jax.random.fold_in(jax.random.key(seed), 35))
    renderer = Renderer(config.background)
    n_test = len(data.test_images)
    base = np.stack([renderer.rgb(g, data.test_cameras[i]) for i in range(n_test)])
    region_w = L.render_editable(g, data.test_cameras, editable)
    region = region_w >= 0.5
    target = np.stack([editor.target(o, 1.0, PROMPT) for o in data.test_images])
    frozen = np.asarray(L.frozen_of(g, editable))
    runs, renders = {}, {}
    for name, local in (("global", None), ("local", spec)):
        t0 = time.perf_counter()
        res = run_edit(editor, PROMPT, data, g, config=config,
                       settings=TrainSettings(), seed=seed, run_dir=None, report=False,
                       local=local)
        wall = time.perf_counter() - t0
        out_g = res["gaussians"]
        rgb = np.stack([renderer.rgb(out_g, data.test_cameras[i]) for i in range(n_test)])
        renders[name] = rgb
        m = res["metrics"]
        runs[name] = {
            "psnr_untouched": masked_psnr(rgb, base, ~region),
            "psnr_region_vs_target": masked_psnr(rgb, target, region),
            "psnr_region_vs_original": masked_psnr(rgb, base, region),
            "psnr_vs_target": m["psnr_vs_target"],
            "frozen_bit_identical": bit_identical(g, out_g, frozen),
            "num_gaussians": m["num_gaussians"], "subtasks": m["subtasks"],
            "total_steps": m["total_steps"], "seconds": wall,
            "relevance_seconds": (res["schedule"].get("local") or {}).get("seconds")}
        print(scene, name, {k: v for k, v in runs[name].items()})
    rows = [np.concatenate([base[i], target[i], renders["global"][i], renders["local"][i],
                            heat(base[i], region_w[i])], axis=1) for i in range(n_test)]
    image = out / f"local_edit_{scene}.png"
    write_image(image, np.clip(np.concatenate(rows, axis=0), 0, 1).astype(np.float32))
    return {"scene": scene, "input_gaussians": int(g.num_alive()),
            "editable": figures["editable"], "frozen": int(frozen.sum()),
            "train_mask_fraction": figures["mask_fraction"],
            "test_region_fraction": float(region.mean()),
            "target_unchanged_outside_region": masked_psnr(target, np.stack(data.test_images),
                                                           ~region),
            "relevance_seconds_alone": figures["seconds"], "runs": runs, "image": image.name}


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv, extra)
    sizes = SMOKE if args.smoke else FULL
    text = args.scenes or ("tabletop" if args.smoke else ",".join(SCENES))
    scenes = [s.strip() for s in text.split(",") if s.strip()]
    t0 = time.perf_counter()
    results = [run_scene(args.out, s, sizes, args.seed) for s in scenes]
    write_json(args.out, "local_edit", {
        "prompt": PROMPT, "settings": {**sizes, "seed": args.seed, "scenes": scenes},
        "results": results, "wall_s": time.perf_counter() - t0, "peak_rss_mb": peak_rss_mb(),
        "goal": "psnr_untouched >= 35 dB (local); psnr_region_vs_target local >= global"})


if __name__ == "__main__":
    main()
