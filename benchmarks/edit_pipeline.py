"""Edit pipeline benchmark: where the time of a progressive edit goes, sync vs threaded editor.

    python benchmarks/edit_pipeline.py [--smoke] [--out DIR] [--devices N]

A small synthetic scene (a coloured ball of Gaussians rendered from an orbit: the
renders are the "photos", so the input reconstruction is exact) is edited with the
simulated editor in the deterministic (sync) schedule and with the producer thread
(async; with ``--devices 2`` the editor runs on its own XLA host device). Written
to ``DIR/edit_pipeline.json`` per mode: seconds and steps per subtask, editor time vs
trainer time, how often / how long the trainer waited for the editor and the editor
for the trainer (utilisation counters of :mod:`jaxedit.edit.buffer`), edits made vs
consumed, peak memory. Timings on a shared CPU are noisy; the first subtask of the
first mode includes compilation.
"""

from __future__ import annotations

import os
import sys
import time


def _early_devices(argv):
    # XLA reads the host device count once, before jax is imported.
    if "--devices" in argv:
        n = int(argv[argv.index("--devices") + 1])
        if n > 1:
            os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                                       + f" --xla_force_host_platform_device_count={n}")


_early_devices(sys.argv)

from common import parse_args, peak_rss_mb, write_json  # noqa: E402


def extra(p):
    p.add_argument("--devices", type=int, default=1, help="XLA host devices (2: editor apart)")
    p.add_argument("--size", type=int, default=48)
    p.add_argument("--views", type=int, default=12)
    p.add_argument("--points", type=int, default=600)
    p.add_argument("--max-steps", type=int, default=120)


def synthetic(size: int, views: int, points: int):
    import dataclasses

    import numpy as np

    from jaxedit import camera as cl
    from jaxedit import gaussians as gl
    from jaxedit.edit import EditData
    from jaxedit.edit.outputs import Renderer

    rng = np.random.default_rng(0)
    d = rng.normal(size=(points, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    g = gl.from_points(d * 0.5, np.clip(0.5 + 0.4 * d[:, [2, 0, 1]], 0, 1), sh_degree=1,
                       init_opacity=0.8)
    g = dataclasses.replace(g, log_scales=g.log_scales + 0.3)
    n = views + 2
    cams = cl.orbit(n, radius=2.5, width=size, height=size, elevation_deg=15)
    r = Renderer()
    images = np.stack([r.rgb(g, cams[i]) for i in range(n)])
    train, test = np.arange(views), np.arange(views, n)
    return EditData.create(images[train], cams[train], images[test], cams[test]), g


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv, extra)
    import jax

    from jaxedit.edit import ProEditConfig, EditTrainConfig
    from jaxedit.pipelines import run_edit
    from jaxedit_lab.simulated import SimulatedEditor

    if args.smoke:
        args.size, args.views, args.points, args.max_steps = 32, 6, 200, 16
    data, scene = synthetic(args.size, args.views, args.points)
    editor = SimulatedEditor()
    results = {}
    for name, asynchronous in (("sync", False), ("async", True)):
        cfg = ProEditConfig.for_mode("proedit", subtasks=2, max_steps=args.max_steps,
                                     warmup=max(args.max_steps // 8, 2),
                                     patience=max(args.max_steps // 4, 4), loss_window=8,
                                     edit_every=5, asynchronous=asynchronous)
        t0 = time.perf_counter()
        out = run_edit(editor, "turn him into a bronze statue", data, scene, config=cfg,
                       settings=EditTrainConfig(lr_sh_dc=0.025), seed=0, run_dir=None)
        wall = time.perf_counter() - t0
        m = out["metrics"]
        u = m["utilisation"]
        subtasks = [{k: s[k] for k in ("name", "ratio", "steps", "seconds", "converged")}
                    for s in out["schedule"]["subtasks"]]
        train_s = sum(s["seconds"] for s in subtasks)
        # Sync: the editor runs inline, so trainer time = subtask time - editor time.
        # Async: the trainer only loses the time it waited.
        trainer_s = train_s - (u["editor_seconds"] if not asynchronous else u["trainer_wait_s"])
        steps = sum(s["steps"] for s in subtasks)
        results[name] = {
            "subtasks": subtasks, "wall_time_s": wall, "subtask_seconds": train_s,
            "editor_seconds": u["editor_seconds"], "trainer_seconds": trainer_s,
            "steps": steps, "ms_per_step": 1e3 * trainer_s / max(steps, 1),
            "edits": u["edits"], "edits_consumed": u["consumed"],
            "ms_per_edit": 1e3 * u["editor_seconds"] / max(u["edits"], 1),
            "trainer_waits": u["trainer_waits"], "trainer_wait_s": u["trainer_wait_s"],
            "editor_waits": u["editor_waits"], "editor_wait_s": u["editor_wait_s"],
            "polls": u["polls"], "empty_polls": u["empty_polls"],
            "psnr_vs_target": m["psnr_vs_target"], "num_gaussians": m["num_gaussians"]}
        print(name, {k: v for k, v in results[name].items() if k != "subtasks"})
    write_json(args.out, "edit_pipeline", {
        "settings": {"size": args.size, "views": args.views, "points": args.points,
                     "max_steps": args.max_steps, "devices": [str(d) for d in jax.devices()]},
        "results": results, "peak_rss_mb": peak_rss_mb(),
        "note": "noisy shared-CPU timings; sync runs first and pays the compilation"})


if __name__ == "__main__":
    main()
