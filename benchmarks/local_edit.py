"""Local edits (issue 35): does ``edit --local auto`` leave the rest of the scene as it was?

    python benchmarks/local_edit.py [--smoke] [--out DIR] [--cases face,person]
                                    [--seed S] [--seeds N]

Two cases, each a built-in scene made and reconstructed once
(:func:`jaxedit.pipelines.cache.prepared_scene`, cached in ``DIR/local_edit_run/SCENE``) and
edited with the same plan and seed: with ``local=LocalSpec("auto")`` (``edit --local
auto``), as a global edit (``--local off``), and locally again with each subtask as long as
the global edit's (``local_global_steps``: the control that takes the plateau test's say
over the lengths away; skipped, with the reason, when the two plans differ in length):

- ``face``: the trained editor that ships with jaxedit (the bundled small InstructPix2Pix,
  :func:`jaxedit.editors.bundled_editor`, JAX) with its local instruction ``make his shirt
  blue`` on the scene it was trained for. Its relevance is the "Watch Your Steps" noise
  difference (:meth:`jaxedit.editors.jax_ip2p.JaxIP2PEditor.relevance`). The target is the scene with the
  shoulders' albedo changed, ray-cast again at the held-out cameras (what the editor was
  trained to produce, :func:`jaxedit_lab.train_editor.edit_data._edited_scene`).
- ``person`` (Blender renders): the simulated editor's local instruction ``paint the orange
  parts blue`` (the warm, coloured pixels swap red and blue: his hair and skin; every other
  pixel of the target is the original); the target is the editor's noise-free r = 1 edit.

The region is the editable Gaussians of the local edit (:func:`jaxedit.edit.local.plan_local`,
the same call and key as :func:`jaxedit.pipelines.run_edit`), rendered at the held-out
views (:func:`jaxedit.edit.local.render_editable`): inside where that weight is at least
:data:`jaxedit.edit.local.OWNED` (0.5).
Scores at the held-out views:

- ``psnr_untouched``: renders vs the original reconstruction's renders, outside the region
  (goal >= 35 dB for the local edit; the global edit's figure for contrast);
- ``psnr_region_vs_target``: renders vs the target inside the region (the local edit should
  be no worse than the global one);
- ``psnr_region_core_vs_target`` / ``psnr_region_border_vs_target``: the same over the
  region's core (the editable Gaussians hold at least :data:`CORE` of the pixel) and over
  its border (frozen Gaussians hold the rest, which the local edit cannot change and the
  global one can): where a difference between the two sits (``test_region_border_share``:
  the border's share of the region's pixels);
- ``psnr_vs_target``: the whole view vs the target;
- ``frozen`` / ``frozen_bit_identical``: the input's Gaussians outside the editable set and
  how many of them the edit left bit for bit (means, scales, rotations, opacities, SH);
- ``relevance_seconds``: the time ``prepare`` took inside the edit (the editor's relevance
  per training view, the lifting, the rendered masks), beside the edits' wall times;
  ``relevance_seconds_alone``: the benchmark's own first call (cold: it compiles).

With ``--seeds N`` each case is edited at seeds S .. S + N - 1 (one reconstruction; the
seed keys the relevance, the edits and their training) and ``paired`` gives local minus
global per seed with a 95 % interval: one seed's difference inside the region is within
the edits' own seed-to-seed spread (about 0.3 dB on the person). ``paired`` also gives the
steps local minus global and the equal-steps control minus global.

Writes ``DIR/local_edit.json`` and ``DIR/local_edit_CASE.png`` (rows: held-out views;
columns: the reconstruction, the target, the global edit, the local edit, the region as a
heat overlay; 2x nearest-neighbour). ``--smoke``: the face case only, 32 px, 4 + 2 views, the
dataset's initial cloud instead of a reconstruction, one subtask of a few steps, 2 DDIM steps.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
from common import parse_args, peak_rss_mb, write_json

#: case -> (scene, editor, instruction).
CASES = {"face": ("face", "ip2p", "make his shirt blue"),
         "person": ("person", "simulated", "paint the orange parts blue")}
FULL = dict(size=64, views=24, test_views=4, iters=1500, max_steps=300, patience=40,
            warmup=30, difficulty_views=8, subtasks=None, ip2p_steps=10)
#: --smoke: the face case only, one subtask of a few steps on the initial cloud.
SMOKE = dict(size=32, views=4, test_views=2, iters=0, max_steps=6, patience=3, warmup=2,
             difficulty_views=2, subtasks=1, ip2p_steps=2)
SMOKE_POINTS = 1000
#: A region pixel is in its core when the editable Gaussians hold this much of its weight.
CORE = 0.95
FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh")


def extra(p):
    p.add_argument("--cases", default=None,
                   help=f"comma-separated cases (default {','.join(CASES)}; --smoke: face)")
    p.add_argument("--seed", type=int, default=0, help="the first edit seed")
    p.add_argument("--seeds", type=int, default=1,
                   help="edit seeds --seed .. --seed + N - 1, paired local vs global (the "
                        "reconstruction is the same)")


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


# ---------------------------------------------------------------------------
# One case
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


def make_editor(kind: str, sizes: dict):
    if kind == "simulated":
        from jaxedit_lab.simulated import SimulatedEditor

        return SimulatedEditor()
    from jaxedit.edit.buffer import pick_devices
    from jaxedit.editors.jax_ip2p import load_bundled

    return load_bundled(devices=[pick_devices()[1]], steps=sizes["ip2p_steps"])


def targets(case: str, editor, prompt: str, data, sizes: dict) -> np.ndarray:
    """float32 [T, H, W, 3]: what the edit should look like at the held-out views."""
    if case == "person":
        return np.stack([editor.target(o, 1.0, prompt) for o in data.test_images])
    from jaxedit_lab.train_editor.edit_data import _edited_scene
    from jaxedit.scenes import get_scene, render_scene, scene_cameras
    from jaxedit.scenes.dataset import PROCEDURAL_DEFAULTS

    scene = get_scene(CASES[case][0], 0)  # prepared_scene's seed
    cameras, _, test = scene_cameras(scene, views=sizes["views"], test_views=sizes["test_views"],
                                     size=sizes["size"])
    return np.asarray(render_scene(_edited_scene(scene, prompt), cameras[test],
                                   supersample=PROCEDURAL_DEFAULTS["supersample"]), np.float32)


def edit_seed(case: str, seed: int, data, g, editor, config, renderer, base, target) -> tuple:
    """The global and the local edit of one seed: (the seed's record, {name: renders})."""
    import jax

    from jaxedit.edit import EditTrainConfig
    from jaxedit.edit import local as L
    from jaxedit.errors import DataError
    from jaxedit.edit.hooks import NO_HOOKS
    from jaxedit.pipelines import run_edit
    from jaxedit_lab.ablation.controls import ControlConfig

    prompt = CASES[case][2]
    spec = L.LocalSpec("auto")
    # The region as run_edit makes it (same call, same key).
    plan = L.plan_local(spec, g, data.train_cameras, data.train_images, editor=editor,
                        embedding=editor.encode(prompt),
                        key=jax.random.fold_in(jax.random.key(seed), 35))
    n_test = len(data.test_images)
    region_w = L.render_editable(g, data.test_cameras, plan.editable)
    region = region_w >= L.OWNED
    # The region's core (the editable Gaussians hold nearly all of the pixel) and its
    # border (frozen Gaussians hold a share the edit cannot change): where a difference
    # between the local and the global edit sits.
    core, border = region_w >= CORE, region & (region_w < CORE)
    frozen = np.asarray(L.frozen_of(g, plan.editable))
    runs, renders = {}, {"region_weight": region_w}
    arms = (("global", None, config), ("local", spec, config),
            # the local edit at the global edit's step count per subtask: what is left of
            # the difference once the plateau test no longer decides the lengths
            ("local_global_steps", spec, None))
    for name, local, arm_config in arms:
        if arm_config is None:
            arm_config = ControlConfig(**dataclasses.asdict(config),
                                       subtask_steps=tuple(runs["global"]["subtask_steps"]))
        t0 = time.perf_counter()
        try:
            # the editor is a controlled instrument, not a user's: no identity floor (as the
            # lab's ablation runs)
            res = run_edit(editor, prompt, data, g, config=arm_config,
                           settings=EditTrainConfig(), seed=seed, run_dir=None, report=False,
                           local=local, hooks=getattr(arm_config, "hooks", lambda: NO_HOOKS)(),
                           identity=None)
        except DataError as e:   # the local plan has another subtask count than the global
            runs[name] = {"skipped": str(e)}
            continue
        wall = time.perf_counter() - t0
        out_g = res["gaussians"]
        rgb = np.stack([renderer.rgb(out_g, data.test_cameras[i]) for i in range(n_test)])
        renders[name] = rgb
        m = res["metrics"]
        runs[name] = {
            "psnr_untouched": masked_psnr(rgb, base, ~region),
            "psnr_region_vs_target": masked_psnr(rgb, target, region),
            "psnr_region_core_vs_target": masked_psnr(rgb, target, core),
            "psnr_region_border_vs_target": masked_psnr(rgb, target, border),
            "psnr_region_vs_original": masked_psnr(rgb, base, region),
            "psnr_vs_target": masked_psnr(rgb, target, np.ones(region.shape, bool)),
            "frozen_bit_identical": bit_identical(g, out_g, frozen),
            "num_gaussians": m["num_gaussians"], "subtasks": m["subtasks"],
            "total_steps": m["total_steps"],
            "subtask_steps": [r["steps"] for r in res["schedule"]["subtasks"]],
            "seconds": wall,
            "relevance_seconds": (res["schedule"].get("local") or {}).get("seconds")}
        print(case, f"seed {seed}", name, runs[name], flush=True)
    record = {"seed": seed, "editable": plan.figures["editable"], "frozen": int(frozen.sum()),
              "train_mask_fraction": plan.figures["mask_fraction"],
              "test_region_fraction": float(region.mean()),
              "test_region_border_share": float(border.sum() / max(region.sum(), 1)),
              "target_vs_original_outside_region": masked_psnr(
                  target, np.stack(data.test_images), ~region),
              "target_vs_original_inside_region": masked_psnr(
                  target, np.stack(data.test_images), region),
              "relevance_seconds_alone": plan.figures["seconds"], "runs": runs}
    return record, renders


def paired(records: list[dict]) -> dict:
    """Over the seeds: local minus global inside the region and outside it (paired, 95 %
    interval), the local edit's lowest untouched PSNR, and whether every frozen Gaussian kept
    its bits."""
    from jaxedit.metrics import paired_differences

    def of(name, key):
        return [r["runs"][name][key] for r in records]

    equal = [r for r in records if "skipped" not in r["runs"]["local_global_steps"]]
    return {"seeds": [r["seed"] for r in records],
            "region_local_minus_global": paired_differences(
                of("local", "psnr_region_vs_target"), of("global", "psnr_region_vs_target")),
            "steps_local_minus_global": paired_differences(
                of("local", "total_steps"), of("global", "total_steps")),
            "region_local_global_steps_minus_global": paired_differences(
                [r["runs"]["local_global_steps"]["psnr_region_vs_target"] for r in equal],
                [r["runs"]["global"]["psnr_region_vs_target"] for r in equal])
            if equal else None,
            "seeds_local_global_steps": [r["seed"] for r in equal],
            "untouched_local_minus_global": paired_differences(
                of("local", "psnr_untouched"), of("global", "psnr_untouched")),
            "untouched_local_min": min(of("local", "psnr_untouched")),
            "frozen_all_bit_identical": all(
                r["runs"]["local"]["frozen_bit_identical"] == r["frozen"] for r in records)}


def run_case(out: Path, case: str, sizes: dict, seeds: list[int]) -> dict:
    from jaxedit.edit import ProEditConfig
    from jaxedit.edit import local as L
    from jaxedit.edit.outputs import Renderer
    from jaxedit.io import write_image

    scene, kind, prompt = CASES[case]
    data, g = prepare_scene(out / "local_edit_run" / scene, scene, sizes, seeds[0])
    editor = make_editor(kind, sizes)
    config = ProEditConfig.for_mode("proedit", max_steps=sizes["max_steps"],
                                    patience=sizes["patience"], warmup=sizes["warmup"],
                                    difficulty_views=sizes["difficulty_views"],
                                    subtasks=sizes["subtasks"], asynchronous=False,
                                    turntable_frames=0)
    renderer = Renderer(config.background)
    n_test = len(data.test_images)
    base = np.stack([renderer.rgb(g, data.test_cameras[i]) for i in range(n_test)])
    target = targets(case, editor, prompt, data, sizes)
    records, first = [], None
    for seed in seeds:
        record, renders = edit_seed(case, seed, data, g, editor, config, renderer, base,
                                    target)
        records.append(record)
        first = first or renders
    rows = [np.concatenate([base[i], target[i], first["global"][i], first["local"][i],
                            L.heat_overlay(base[i], first["region_weight"][i])], axis=1)
            for i in range(n_test)]
    sheet = np.clip(np.concatenate(rows, axis=0), 0, 1).astype(np.float32)
    image = out / f"local_edit_{case}.png"
    write_image(image, np.repeat(np.repeat(sheet, 2, 0), 2, 1))
    return {"case": case, "scene": scene, "editor": kind, "prompt": prompt,
            "input_gaussians": int(g.num_alive()), "per_seed": records,
            "paired": paired(records) if len(records) > 1 else None,
            "image": image.name, "image_seed": seeds[0]}


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv, extra)
    sizes = SMOKE if args.smoke else FULL
    text = args.cases or ("face" if args.smoke else ",".join(CASES))
    cases = [s.strip() for s in text.split(",") if s.strip()]
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        raise SystemExit(f"unknown case {unknown[0]!r}; known: {', '.join(CASES)}")
    t0 = time.perf_counter()
    if args.seeds < 1:
        raise SystemExit(f"--seeds must be at least 1, got {args.seeds}")
    seeds = list(range(args.seed, args.seed + args.seeds))
    results = [run_case(args.out, c, sizes, seeds) for c in cases]
    write_json(args.out, "local_edit", {
        "settings": {**sizes, "seeds": seeds, "cases": cases}, "smoke": args.smoke,
        "results": results, "wall_s": time.perf_counter() - t0, "peak_rss_mb": peak_rss_mb(),
        "goal": "psnr_untouched >= 35 dB (local); psnr_region_vs_target local >= global "
                "(paired over the seeds)"})


if __name__ == "__main__":
    main()
