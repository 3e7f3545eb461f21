"""``python -m experiments ablation``: ProEdit vs ND vs IN2N as statistics over seeds, instructions and scenes.

With the simulated editor (a test instrument whose noise-free targets are known; not
InstructPix2Pix) on built-in scenes: make each scene's dataset and reconstruct it once, then
edit the reconstruction with every method, for every instruction, for several seeds, and for
each requested number of divergent editor modes (``--editor-modes 1,3``: the single-outcome
editor and the editor with three modes per instruction, see :mod:`jaxedit.edit.simulated`).

Methods (rows): ``proedit`` (difficulty-aware schedule), ``nd`` (no decomposition, its own
step guard), ``nd_equal_steps`` (ND given ProEdit's total step count of the same seed, a third
per subtask r0 / r=1 / rn) and ``in2n`` (IN2N on 3DGS, a fixed budget of ProEdit's total step
count). The seed varies everything random in the edit (editor draws, view order, training);
the dataset and the reconstruction are the same for all seeds of a scene.

Scores at the held-out views (:func:`jaxedit.metrics.mode_scores`), none favouring a mode:
``psnr_best`` / ``ssim_best`` (best over modes of the per-scene PSNR / SSIM against the mode's
noise-free target at r = 1), ``mode_mixing`` (0: the scene shows one mode, 1: an even blend of
all), plus ``multiview_consistency``, ``psnr_vs_target`` (against mode 0 only, the old score),
steps and CPU seconds.

Writes ``RUN_DIR/ablation.json``::

    {"settings": {...}, "runs": [one record per (editor_modes, scene, prompt, seed, method)],
     "summary": [{"editor_modes", "scene", "prompt", "method", "metric",
                  "mean", "ci", "low", "high", "n"}],       # Student-t 95% CI over seeds
     "differences": [{... "method": other, "metric", "mean", "ci", ...}]}  # proedit - other,
                                                                            # paired by seed

(``prompt`` "all" averages the instructions per seed first), ``RUN_DIR/ablation.md`` (the
tables), ``RUN_DIR/views/*.png`` (seed 0: the modes' targets and every method's final test
views) and ``RUN_DIR/report.html``. An interrupted run resumes: finished records are kept when
the settings match.

Cost. The default (face and tabletop, all 5 instructions, 5 seeds, the 3-mode editor; 32 px,
12 + 4 views, 60-step subtask guard) is 50 (scene, instruction, seed) groups of four edits,
about 1000 training steps per group. Measured on the shared 2-core machine: about 27 ms of CPU
per editing step (32 px, ~8.7k Gaussians, edits and renders included), so about 25 minutes of
CPU in all with compiling and the two reconstructions (an estimate from a reduced run, not an
end-to-end measurement). ``--editor-modes 1,3`` adds the single-outcome editor and doubles it.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

HELP = ("ablation: proedit vs nd vs nd at equal steps vs in2n over seeds, instructions and "
        "scenes, with 95-percent confidence intervals (simulated editor)")

METHODS = ("proedit", "nd", "nd_equal_steps", "in2n")
SCENES = ("face", "tabletop")
#: Metrics summarised with confidence intervals (higher is better except where noted).
METRICS = ("psnr_best", "ssim_best", "mode_mixing", "multiview_consistency", "psnr_vs_target",
           "total_steps", "cpu_seconds")
ALL = "all"


def _csv(text: str) -> list[str]:
    return [t.strip() for t in str(text).split(",") if t.strip()]


def add_arguments(p) -> None:
    p.add_argument("--scenes", default=",".join(SCENES),
                   help="comma-separated built-in scenes (jaxedit.scenes.list_scenes())")
    p.add_argument("--prompts", default=None,
                   help="comma-separated instructions of the simulated editor (default: all)")
    p.add_argument("--seeds", type=int, default=5, help="seeds per instruction (0 .. N-1)")
    p.add_argument("--editor-modes", default="3",
                   help="comma-separated numbers of divergent editor modes to compare (1: the "
                        "single-outcome editor)")
    p.add_argument("--methods", default=",".join(METHODS),
                   help="comma-separated rows: proedit, nd, nd_equal_steps, in2n "
                        "(nd_equal_steps and in2n take ProEdit's step count, so need proedit)")
    p.add_argument("--size", type=int, default=32, help="image size in pixels")
    p.add_argument("--views", type=int, default=12, help="training views")
    p.add_argument("--test-views", type=int, default=4, help="held-out views (scored)")
    p.add_argument("--recon-iters", type=int, default=400, help="reconstruction steps")
    p.add_argument("--threshold", type=float, default=None, help="proedit difficulty threshold")
    p.add_argument("--max-steps", type=int, default=60, help="per-subtask step guard")
    p.add_argument("--warmup", type=int, default=10, help="W after each opacity reset")
    p.add_argument("--patience", type=int, default=20, help="plateau length ending a subtask")
    p.add_argument("--lr-sh-dc", type=float, default=0.025,
                   help="colour learning rate of the editing trainer (same for every method)")
    p.add_argument("--smoke", action="store_true", help="tiny sizes (CI): seconds, not minutes")


def smoke_overrides() -> dict:
    """Tiny sizes for CI. The cost is compiling (reconstruction, editing trainer, renderer,
    editor): in2n is left out, its trainer would be one more compile (~13 s of CPU); the
    driver's tests run it."""
    return dict(scenes=("ball",), prompts=("make it look like autumn",), seeds=2,
                editor_modes=(3,), methods=("proedit", "nd", "nd_equal_steps"), size=16,
                views=4, test_views=2, recon_iters=30, max_steps=8, warmup=2, patience=4)


def stamp_prepared(out: Path, wanted: dict) -> None:
    """:func:`jaxedit.pipelines.cache.stamp_prepared` (kept here for this module's callers)."""
    from jaxedit.pipelines.cache import stamp_prepared as stamp

    stamp(out, wanted)


def prepare(out: Path, *, scene_name: str, size: int, views: int, test_views: int,
            recon_iters: int, seed: int, log=print):
    """(EditData, reconstructed Gaussians, recon metrics): dataset + reconstruction, cached on disk."""
    from jaxedit.edit.progressive import EditData
    from jaxedit.io import load_nerfstudio, load_ply
    from jaxedit.pipelines.reconstruct import reconstruct
    from jaxedit.scenes import make_scene
    from jaxedit.train import DensifyConfig, TrainConfig

    data_dir, recon_dir = out / "data", out / "recon"
    wanted = {"scene": scene_name, "size": size, "views": views, "test_views": test_views,
              "recon_iters": recon_iters, "seed": seed}
    stamp_prepared(out, wanted)
    if not (data_dir / "transforms.json").exists():
        log(f"making the {scene_name} scene ({views}+{test_views} views, {size}px)")
        make_scene(scene_name, data_dir, size=size, views=views, test_views=test_views, seed=seed)
    dataset = load_nerfstudio(data_dir)
    if not (recon_dir / "scene.ply").exists():
        log(f"reconstructing {scene_name} ({recon_iters} steps)")
        dens = DensifyConfig(refine_every=100, warmup=min(500, recon_iters // 5),
                             reset_every=max(recon_iters // 2, 1), max_gaussians=50_000)
        config = TrainConfig(iterations=recon_iters, sh_degree=1, sh_degree_interval=max(
            recon_iters // 4, 1), densify=dens)
        reconstruct(dataset, recon_dir, config, seed=seed, checkpoint_every=0)
    recon = json.loads((recon_dir / "metrics.json").read_text())
    return EditData.from_dataset(dataset), load_ply(recon_dir / "scene.ply"), recon


# ---------------------------------------------------------------------------
# Statistics (pure)
# ---------------------------------------------------------------------------
def _values(runs, *, prompts, method, metric, seeds) -> list[float] | None:
    """Per-seed values of one scene and editor setting, averaged over ``prompts`` (one prompt,
    or the complete ones for "all"); None if a seed lacks any of them."""
    out = []
    for seed in seeds:
        vals = [r[metric] for r in runs if r["method"] == method and r["seed"] == seed
                and r["prompt"] in prompts and r.get(metric) is not None]
        if len(vals) != len(prompts):
            return None
        out.append(sum(vals) / len(vals))
    return out


def summarise(runs: list[dict]) -> tuple[list[dict], list[dict]]:
    """(summary rows, paired-difference rows) of the run records; see the module docstring."""
    from jaxedit.metrics import mean_ci, paired_differences

    summary, differences = [], []
    groups = sorted({(r["editor_modes"], r["scene"]) for r in runs})
    for modes, scene in groups:
        mine = [r for r in runs if r["editor_modes"] == modes and r["scene"] == scene]
        prompts = list(dict.fromkeys(r["prompt"] for r in mine))
        methods = [m for m in METHODS if any(r["method"] == m for r in mine)]
        seeds = sorted({r["seed"] for r in mine})
        # An interrupted run has a partial last instruction: each row uses the seeds that
        # every method finished (so differences stay paired), "all" the complete instructions.
        done = {(r["prompt"], r["seed"]) for r in mine
                if all(any(q["prompt"] == r["prompt"] and q["seed"] == r["seed"]
                           and q["method"] == m for q in mine) for m in methods)}
        finished = {p: [sd for sd in seeds if (p, sd) in done] for p in prompts}
        complete = [p for p in prompts if len(finished[p]) == len(seeds)]
        for prompt in prompts + ([ALL] if len(complete) > 1 else []):
            over = complete if prompt == ALL else [prompt]
            use = seeds if prompt == ALL else finished[prompt]
            if not use:
                continue
            for metric in METRICS:
                base = None
                for method in methods:
                    vals = _values(mine, prompts=over, method=method, metric=metric, seeds=use)
                    if vals is None:
                        continue
                    key = {"editor_modes": modes, "scene": scene, "prompt": prompt,
                           "method": method, "metric": metric}
                    summary.append(key | mean_ci(vals))
                    if method == "proedit":
                        base = vals
                    elif base is not None:
                        differences.append(key | paired_differences(base, vals))
    return summary, differences


def tables(summary: list[dict], differences: list[dict], *,
           metrics=("psnr_best", "mode_mixing", "multiview_consistency")) -> str:
    """Markdown: per editor-modes setting and metric, (scene, instruction) x methods with
    mean ± 95% CI, then the paired differences proedit - other (``*``: CI excludes 0)."""
    from jaxedit.report import ablation_table

    text = []
    for modes in sorted({r["editor_modes"] for r in summary}):
        for metric in metrics:
            digits = 3 if metric.startswith(("ssim", "mode")) else 2
            header, rows = ablation_table(summary, differences, editor_modes=modes,
                                          metric=metric, digits=digits)
            text.append(f"\n### editor modes = {modes}: {metric} (mean ± 95% CI over seeds)\n")
            text.append("| " + " | ".join(header) + " |")
            text.append("|" + "---|" * len(header))
            text += ["| " + " | ".join(row) + " |" for row in rows]
    text.append("\n`*`: the 95% CI of the paired difference excludes 0.")
    return "\n".join(text) + "\n"


# ---------------------------------------------------------------------------
# Running
# ---------------------------------------------------------------------------
def _score(editor, prompt, data, gaussians, background) -> tuple[dict, object, object]:
    """(mode scores, renders [N, H, W, 3], mode targets [K, N, H, W, 3]) at the test views."""
    import numpy as np

    from jaxedit.edit.progressive import Renderer
    from jaxedit.metrics import mode_scores

    renderer = Renderer(background)
    rgb = np.stack([renderer.rgb(gaussians, data.test_cameras[i])
                    for i in range(len(data.test_images))])
    targets = np.stack([editor.mode_targets(o, 1.0, prompt) for o in data.test_images], axis=1)
    return mode_scores(rgb, targets), rgb, targets


def _write_views(path: Path, targets, renders: dict) -> None:
    """One PNG: a row per mode target, then a row per method's final test views."""
    import numpy as np

    from jaxedit.io import write_image
    from jaxedit.viz import image_grid

    rows = list(targets) + [renders[m] for m in renders]
    grid = image_grid(np.concatenate(rows), ncols=len(rows[0]))
    path.parent.mkdir(parents=True, exist_ok=True)
    write_image(path, np.ascontiguousarray(np.clip(grid, 0.0, 1.0)))


def _slug(text: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in text.lower()).strip("_")[:40]


def run_ablation(out: Path, *, scenes=SCENES, prompts=None, seeds=5, editor_modes=(3,),
                 methods=METHODS, size=32, views=12, test_views=4, recon_iters=400,
                 threshold=None, max_steps=60, warmup=10, patience=20, lr_sh_dc=0.025,
                 recon_seed=0, report=True, log=print) -> dict:
    """Run the ablation into ``out``; returns the contents of ablation.json."""
    from jaxedit import DataError
    from jaxedit.edit.progressive import ProEditConfig, TrainSettings, run_edit
    from jaxedit.edit.simulated import SimulatedEditor
    from jaxedit.io.files import atomic_write_text
    from jaxedit.scenes import list_scenes

    out = Path(out)
    bad = [s for s in scenes if s not in list_scenes()]
    if bad or not scenes:
        raise DataError("--scenes", f"unknown scene(s) {bad}; built-in: {', '.join(list_scenes())}"
                        if bad else f"no scene given; built-in: {', '.join(list_scenes())}")
    bad = [m for m in methods if m not in METHODS]
    if bad or not methods:
        raise DataError("--methods", f"unknown method(s) {bad}; choose from {', '.join(METHODS)}"
                        if bad else f"no method given; choose from {', '.join(METHODS)}")
    if any(m in methods for m in ("nd_equal_steps", "in2n")) and "proedit" not in methods:
        raise DataError("--methods", "nd_equal_steps and in2n take ProEdit's step count: "
                                     "include proedit")
    if seeds < 1:
        raise DataError("--seeds", f"must be >= 1, got {seeds}")
    editors = {int(k): SimulatedEditor(modes=int(k)) for k in editor_modes}
    prompts = tuple(prompts) if prompts else next(iter(editors.values())).instructions
    for p in prompts:
        try:
            next(iter(editors.values())).encode(p)  # unknown instructions fail here
        except DataError as e:
            raise DataError("--prompts", e.problem) from None
    order = [m for m in METHODS if m in methods]  # proedit first: the others need its steps
    settings_json = {"scenes": list(scenes), "prompts": list(prompts), "seeds": seeds,
                     "editor_modes": sorted(editors), "methods": order, "size": size,
                     "views": views, "test_views": test_views, "recon_iters": recon_iters,
                     "threshold": threshold, "max_steps": max_steps, "warmup": warmup,
                     "patience": patience, "lr_sh_dc": lr_sh_dc, "recon_seed": recon_seed}
    out.mkdir(parents=True, exist_ok=True)
    path = out / "ablation.json"
    runs: list[dict] = []
    if path.exists():
        old = json.loads(path.read_text())
        if isinstance(old, dict) and old.get("settings") == settings_json:
            runs = list(old.get("runs", []))
            log(f"resuming: {len(runs)} finished runs in {path}")

    def save(extra=None):
        payload = {"settings": settings_json, "runs": runs} | (extra or {})
        atomic_write_text(path, json.dumps(payload, indent=2) + "\n")

    total = len(scenes) * len(prompts) * seeds * len(editors) * len(order)
    t_start = time.perf_counter()
    for scene_name in scenes:
        data, scene, recon = prepare(out / scene_name, scene_name=scene_name, size=size,
                                     views=views, test_views=test_views,
                                     recon_iters=recon_iters, seed=recon_seed, log=log)
        settings = TrainSettings(lr_sh_dc=lr_sh_dc, sh_degree=scene.sh_degree)
        for modes, editor in editors.items():
            for prompt in prompts:
                for seed in range(seeds):
                    renders = {}
                    steps = {}
                    for method in order:
                        tag = (modes, scene_name, prompt, seed, method)
                        prior = next((r for r in runs if (r["editor_modes"], r["scene"],
                                                          r["prompt"], r["seed"],
                                                          r["method"]) == tag), None)
                        if prior is not None:  # finished before an interruption
                            steps[method] = prior["total_steps"]
                            continue
                        mode, cap = method, max_steps
                        if method == "nd_equal_steps":
                            mode, cap = "nd", max(-(-int(steps["proedit"]) // 3), 1)
                        elif method == "in2n":
                            cap = int(steps["proedit"])
                        cfg = ProEditConfig.for_mode(
                            mode, threshold=threshold if mode == "proedit" else None,
                            max_steps=cap, warmup=warmup if mode != "in2n" else None,
                            patience=patience, asynchronous=False)
                        t0, c0 = time.perf_counter(), time.process_time()
                        res = run_edit(editor, prompt, data, scene, config=cfg,
                                       settings=settings, seed=seed, run_dir=None, report=False)
                        scores, rgb, targets = _score(editor, prompt, data, res["gaussians"],
                                                      cfg.background)
                        renders[method] = rgb
                        m = res["metrics"]
                        steps[method] = int(m["total_steps"])
                        runs.append({
                            "editor_modes": modes, "scene": scene_name, "prompt": prompt,
                            "seed": seed, "method": method, **scores,
                            "psnr_vs_target": m.get("psnr_vs_target"),
                            "multiview_consistency": m.get("multiview_consistency"),
                            "total_steps": steps[method], "subtasks": m.get("subtasks"),
                            "all_converged": m.get("all_converged"),
                            "ratios": [s["ratio"] for s in res["schedule"]["subtasks"]],
                            "seconds": time.perf_counter() - t0,
                            "cpu_seconds": time.process_time() - c0})
                        save()
                        log(f"[{len(runs)}/{total}] modes={modes} {scene_name} '{prompt}' "
                            f"seed {seed} {method}: psnr_best {scores['psnr_best']:.2f}, "
                            f"mixing {scores['mode_mixing']:.2f}, {steps[method]} steps, "
                            f"{time.perf_counter() - t_start:.0f} s so far")
                    if seed == 0 and renders:
                        _write_views(out / "views" / f"m{modes}_{scene_name}_{_slug(prompt)}.png",
                                     targets, renders)
    summary, differences = summarise(runs)
    save({"summary": summary, "differences": differences,
          "wall_time_s": time.perf_counter() - t_start})
    atomic_write_text(out / "ablation.md", "# Ablation (simulated editor)\n\n"
                      f"Settings: `{json.dumps(settings_json)}`\n" + tables(summary, differences))
    if report:
        from jaxedit.report import write_report

        write_report(out)
    return {"settings": settings_json, "runs": runs, "summary": summary,
            "differences": differences}


def run(args) -> dict:
    from jaxedit import DataError

    from experiments.cli import check_minimums

    if args.out is None:
        raise DataError("--out", "required (the ablation run directory)")
    check_minimums(args, {"size": 8, "views": 1, "test_views": 1, "recon_iters": 1,
                          "max_steps": 1, "warmup": 0, "patience": 1, "seeds": 1})
    for name in ("threshold", "lr_sh_dc"):
        if getattr(args, name) is not None and not getattr(args, name) > 0:
            raise DataError(f"--{name.replace('_', '-')}", f"must be > 0, got {getattr(args, name)}")
    from jaxedit.edit.simulated import MAX_MODES

    try:
        modes = tuple(int(m) for m in _csv(args.editor_modes))
    except ValueError:
        modes = ()
    if not modes or not all(1 <= m <= MAX_MODES for m in modes):
        raise DataError("--editor-modes", f"expected integers in 1..{MAX_MODES} like 1,3, got "
                        f"{args.editor_modes!r}")
    if args.prompts is not None and not _csv(args.prompts):
        raise DataError("--prompts", f"no instruction given in {args.prompts!r} (leave the flag "
                                     f"out for all of them)")
    if args.smoke:
        # --smoke sets these itself: a value given beside it would be silently dropped.
        defaults = argparse.ArgumentParser()
        add_arguments(defaults)
        given = [f"--{k.replace('_', '-')}" for k in smoke_overrides()
                 if k != "prompts" and getattr(args, k) != defaults.get_default(k)]
        given += ["--prompts"] if args.prompts is not None else []
        if given:
            raise DataError(given[0], f"--smoke sets {', '.join(given)} itself; give either "
                                      f"--smoke or {', '.join(given)}")
    kw = dict(scenes=tuple(_csv(args.scenes)), prompts=tuple(_csv(args.prompts or "")) or None,
              seeds=args.seeds, editor_modes=modes, methods=tuple(_csv(args.methods)),
              size=args.size, views=args.views, test_views=args.test_views,
              recon_iters=args.recon_iters, max_steps=args.max_steps, warmup=args.warmup,
              patience=args.patience)
    if args.smoke:
        kw.update(smoke_overrides())
    log = (lambda m: None) if args.quiet else (lambda m: print(m, flush=True))
    result = run_ablation(args.out, threshold=args.threshold, lr_sh_dc=args.lr_sh_dc,
                          recon_seed=args.seed, log=log, **kw)
    return {f"m{r['editor_modes']} {r['scene']} {r['method']} {r['metric']}":
            round(r["mean"], 4) for r in result["summary"]
            if r["prompt"] in (ALL, result["settings"]["prompts"][0])
            and r["metric"] in ("psnr_best", "mode_mixing")
            and (r["prompt"] == ALL or len(result["settings"]["prompts"]) == 1)}
