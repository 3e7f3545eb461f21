"""``python -m experiments ablation``: ProEdit vs no decomposition (ND) vs IN2N, scored on ground truth.

On the built-in ``face`` scene with the simulated editor (whose noise-free target
is known for every view): make the dataset, reconstruct it, then edit the same
reconstruction with each mode and score the result at held-out views against the
target (PSNR, SSIM), plus multi-view consistency, Gaussian count and wall time.

Writes ``RUN_DIR/ablation.json`` ({mode: {metric: value}}), ``RUN_DIR/ablation.md``
(a small table), the dataset in ``RUN_DIR/data``, the reconstruction in
``RUN_DIR/recon`` and one edit run directory per mode in ``RUN_DIR/<mode>/``, and
``RUN_DIR/report.html`` comparing them. Every mode runs in the deterministic
(``--sync``) schedule with the same seed, trainer and learning rates.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

HELP = "ablation on the face scene: proedit vs nd vs in2n against the simulated ground truth"

MODES = ("proedit", "nd", "in2n")
# Extra row: ND given the same total number of training steps as ProEdit's run (its three
# subtasks r0 / r=1 / rn each get a third), so that the comparison is not just "more steps".
EXTRA = ("nd_equal_steps",)
KEYS = ("psnr_vs_target", "ssim_vs_target", "multiview_consistency", "edit_fit_psnr",
        "num_gaussians", "wall_time_s", "subtasks", "total_steps", "all_converged")


def add_arguments(p) -> None:
    p.add_argument("--scene-name", default="face", help="built-in scene")
    p.add_argument("--prompt", default="turn him into a bronze statue",
                   help="instruction of the simulated editor")
    p.add_argument("--modes", default=",".join(MODES + EXTRA),
                   help="comma-separated rows to run: proedit, nd, in2n, nd_equal_steps (ND with "
                        "ProEdit's total step count)")
    p.add_argument("--size", type=int, default=64, help="image size in pixels")
    p.add_argument("--views", type=int, default=24, help="training views")
    p.add_argument("--test-views", type=int, default=4, help="held-out views (scored)")
    p.add_argument("--recon-iters", type=int, default=1500, help="reconstruction steps")
    p.add_argument("--threshold", type=float, default=None, help="proedit difficulty threshold")
    p.add_argument("--max-steps", type=int, default=300, help="per-subtask step guard")
    p.add_argument("--warmup", type=int, default=40, help="W after each opacity reset")
    p.add_argument("--patience", type=int, default=60, help="plateau length ending a subtask")
    p.add_argument("--lr-sh-dc", type=float, default=0.025,
                   help="colour learning rate of the editing trainer (same for every mode)")
    p.add_argument("--smoke", action="store_true", help="tiny sizes (CI): seconds, not minutes")


def smoke_overrides() -> dict:
    return dict(size=32, views=8, test_views=2, recon_iters=100, max_steps=16, warmup=6,
                patience=8, turntable_frames=0, report=False)


def prepare(out: Path, *, scene_name: str, size: int, views: int, test_views: int,
            recon_iters: int, seed: int, log=print):
    """(EditData, reconstructed Gaussians, recon metrics): dataset + reconstruction, cached on disk."""
    from jaxedit.edit.progressive import EditData
    from jaxedit.io import load_nerfstudio, load_ply
    from jaxedit.scenes import make_scene
    from jaxedit.train import DensifyConfig, TrainConfig

    from experiments.reconstruct import reconstruct

    data_dir, recon_dir = out / "data", out / "recon"
    if not (data_dir / "transforms.json").exists():
        log(f"making the {scene_name} scene ({views}+{test_views} views, {size}px)")
        make_scene(scene_name, data_dir, size=size, views=views, test_views=test_views, seed=seed)
    dataset = load_nerfstudio(data_dir)
    if not (recon_dir / "scene.ply").exists():
        log(f"reconstructing ({recon_iters} steps)")
        dens = DensifyConfig(refine_every=100, warmup=min(500, recon_iters // 5),
                             reset_every=max(recon_iters // 2, 1), max_gaussians=50_000)
        config = TrainConfig(iterations=recon_iters, sh_degree=1, sh_degree_interval=max(
            recon_iters // 4, 1), densify=dens)
        reconstruct(dataset, recon_dir, config, seed=seed, checkpoint_every=0, progress=False)
    recon = json.loads((recon_dir / "metrics.json").read_text())
    return EditData.from_dataset(dataset), load_ply(recon_dir / "scene.ply"), recon


def table(results: dict) -> str:
    """Markdown table of the modes (rows) and the main metrics (columns)."""
    cols = ("psnr_vs_target", "ssim_vs_target", "multiview_consistency", "edit_fit_psnr",
            "num_gaussians", "subtasks", "total_steps", "wall_time_s")
    head = "| mode | " + " | ".join(cols) + " |\n|" + "---|" * (len(cols) + 1) + "\n"
    rows = []
    for mode, m in results.items():
        cells = []
        for c in cols:
            v = m.get(c)
            cells.append("-" if v is None else f"{v:.3f}" if isinstance(v, float) else str(v))
        rows.append(f"| {mode} | " + " | ".join(cells) + " |")
    return head + "\n".join(rows) + "\n"


def run_ablation(out: Path, *, scene_name="face", prompt="turn him into a bronze statue",
                 modes=MODES, size=64, views=24, test_views=4, recon_iters=1500, threshold=None,
                 max_steps=300, warmup=40, patience=60, lr_sh_dc=0.025, seed=0,
                 turntable_frames=12, report=True, log=print) -> dict:
    """Run the ablation into ``out``; returns {mode: metrics} (also ablation.json / .md)."""
    from jaxedit.edit.progressive import (ProEditConfig, Renderer, TrainSettings, run_edit,
                                          scene_metrics)
    from jaxedit.edit.simulated import SimulatedEditor
    from jaxedit.io.files import atomic_write_text

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    data, scene, recon = prepare(out, scene_name=scene_name, size=size, views=views,
                                 test_views=test_views, recon_iters=recon_iters, seed=seed,
                                 log=log)
    editor = SimulatedEditor()
    settings = TrainSettings(lr_sh_dc=lr_sh_dc, sh_degree=scene.sh_degree)
    results: dict = {}
    if (out / "ablation.json").exists():  # keep rows of an earlier run (e.g. --modes in2n)
        results = json.loads((out / "ablation.json").read_text())
    # The unedited reconstruction, scored the same way: the floor every mode should beat.
    from jaxedit.edit.progressive import EditContext, SubtaskTrainer
    ctx = EditContext(editor, prompt, data, ProEditConfig(),
                      SubtaskTrainer(settings, num_input=int(scene.num_alive())),
                      Renderer(), None)
    base = scene_metrics(ctx, scene, 0.0)
    results["input"] = {k: base.get(k) for k in KEYS} | {"recon_test_psnr": recon["test_psnr"]}
    for row in modes:
        mode, steps = row, max_steps
        if row == "nd_equal_steps":
            done = results.get("proedit", {}).get("total_steps")
            if done is None:
                log("nd_equal_steps needs the proedit row first: skipped")
                continue
            mode, steps = "nd", max(-(-int(done) // 3), 1)
        elif row == "in2n":
            # IN2N trains for a fixed number of iterations: give it ProEdit's total.
            done = results.get("proedit", {}).get("total_steps")
            steps = int(done) if done else 3 * max_steps
        cfg = ProEditConfig.for_mode(mode, threshold=threshold if mode == "proedit" else None,
                                     max_steps=steps, warmup=warmup if mode != "in2n" else None,
                                     patience=patience, asynchronous=False,
                                     turntable_frames=turntable_frames)
        log(f"editing with mode {mode} ({row}, max {steps} steps per subtask)")
        t0 = time.perf_counter()
        res = run_edit(editor, prompt, data, scene, config=cfg, settings=settings, seed=seed,
                       run_dir=out / row, report=report, log=log)
        m = res["metrics"]
        results[row] = {k: m.get(k) for k in KEYS} | {
            "ratios": [s["ratio"] for s in res["schedule"]["subtasks"]],
            "utilisation": m.get("utilisation"), "seconds": time.perf_counter() - t0}
        atomic_write_text(out / "ablation.json", json.dumps(results, indent=2) + "\n")
    summary = {"prompt": prompt, "scene": scene_name, "size": size, "views": views,
               "test_views": test_views, "max_steps": max_steps, "lr_sh_dc": lr_sh_dc}
    atomic_write_text(out / "ablation.json", json.dumps(results, indent=2) + "\n")
    atomic_write_text(out / "ablation.md", f"Ablation on `{scene_name}`: \"{prompt}\" "
                      f"({json.dumps(summary)})\n\n" + table(results))
    if report:
        try:
            from jaxedit.report import write_report
        except ImportError:
            pass
        else:
            write_report(out)
    return results


def run(args) -> dict:
    from jaxedit import DataError

    if args.out is None:
        raise DataError("--out", "required (the ablation run directory)")
    modes = tuple(m.strip() for m in args.modes.split(",") if m.strip())
    bad = [m for m in modes if m not in MODES + EXTRA]
    if bad or not modes:
        raise DataError("--modes", f"unknown mode(s) {bad}; choose from {', '.join(MODES)}")
    kw = dict(size=args.size, views=args.views, test_views=args.test_views,
              recon_iters=args.recon_iters, max_steps=args.max_steps, warmup=args.warmup,
              patience=args.patience)
    if args.smoke:
        kw.update(smoke_overrides())
    log = (lambda m: None) if args.quiet else (lambda m: print(m, flush=True))
    results = run_ablation(args.out, scene_name=args.scene_name, prompt=args.prompt, modes=modes,
                           threshold=args.threshold, lr_sh_dc=args.lr_sh_dc, seed=args.seed,
                           log=log, **kw)
    return {mode: {k: r.get(k) for k in ("psnr_vs_target", "ssim_vs_target",
                                         "multiview_consistency", "num_gaussians",
                                         "wall_time_s")} for mode, r in results.items()}
