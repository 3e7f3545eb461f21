"""Targets of views larger than the editor: stretched edits against detail-keeping ones.

    python benchmarks/edit_targets.py [--smoke] [--out DIR] [--work DIR]

The built-in person at 256 px (24 training and 4 held-out views), reconstructed, then
refined by r_0 (e(0), what every ProEdit run does first) with the bundled 64 px
InstructPix2Pix, once with each way of making a larger view's target
(:mod:`jaxedit.editors.compose`): ``stretch`` (the 64 px edit enlarged, the targets before
issue 77) and ``detail`` (the render plus the edit's change at 64 px, the default), and a
control editor that gives the render back (r_0's own cost, no editor's). Per
composition: the editor identity check's figures, r_0's snapshot against the input
scene's renders (PSNR, SSIM, LPIPS, Gaussians), and the held-out PSNR against the photos of
the input scene and of r_0's snapshot. The run stops after r_0's snapshot. Writes
``DIR/edit_targets.json`` and ``DIR/edit_targets.png`` (a held-out view: input scene,
stretched r_0, detail r_0). ``--smoke``: the person at 64 px (the editor's size: both
compositions edit alike), 8 views, a few steps. r_0 runs to the run's own plateau and step
guard (``--max-steps``, ``--patience`` to hold it); ``--refine-reset`` starts it with the
opacity reset (``edit --refine-opacity-reset``) and writes ``DIR/edit_targets_refine_reset.json``
(``--rows control`` for the control alone).
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import machine_info, parse_args, write_json

ROOT = Path(__file__).resolve().parents[1]


def extra(p):
    p.add_argument("--work", type=Path, default=None,
                   help="keep the dataset, reconstruction and runs here (default: a temp dir)")
    p.add_argument("--rows", default="control,stretch,detail",
                   help="comma list of control, stretch, detail (the PNG needs both of the last)")
    p.add_argument("--max-steps", type=int, default=None,
                   help="r_0's step guard (default: the run's, from the scene)")
    p.add_argument("--patience", type=int, default=None,
                   help="r_0's plateau patience (default: the run's)")
    p.add_argument("--refine-reset", action="store_true",
                   help="start r_0 with the opacity reset (edit --refine-opacity-reset)")


class GivesBack:
    """The control: an editor that gives back the render it is shown, at every e(r) (what a
    perfect identity would do at e(0)), so r_0's own cost (its opacity reset, its steps)
    shows apart from any editor's."""

    name = "gives-back-the-render"
    guidance = (2.0, 1.5)

    def encode(self, prompt):
        import numpy as np

        return np.zeros((4,), np.float32)

    def edit(self, image, original, embedding, key, **kwargs):
        import numpy as np

        return np.asarray(image, np.float32)


class Stop(Exception):
    """Raised by the progress callback once r_0 is done: the benchmark needs only r_0."""


def cli(*argv: str) -> None:
    subprocess.run([sys.executable, "-m", "experiments", *argv, "--quiet"], cwd=ROOT,
                   check=True, stdout=subprocess.DEVNULL)


def held_out_photos(data):
    """The held-out photos of the dataset ``data``, float [M, H, W, 3]."""
    import numpy as np

    from jaxedit.io import load_nerfstudio

    dataset = load_nerfstudio(data)
    return np.asarray(dataset.images, np.float32)[np.asarray(dataset.test_indices)]


def held_out_psnr(renders_dir: Path, photos) -> float:
    """Mean PSNR (dB) of a snapshot's renders (PNG) against the held-out photos."""
    import numpy as np

    from jaxedit.edit.outputs import image_scores
    from jaxedit.io import read_image

    renders = np.stack([read_image(p) for p in sorted(renders_dir.glob("*.png"))])
    return image_scores(renders, photos)["psnr"]


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv, extra)
    import json

    import numpy as np

    from jaxedit.edit import ProEditConfig
    from jaxedit.edit.identity import IdentityFloor
    from jaxedit.io import read_image, write_image
    from jaxedit.pipelines.edit_run import EditorConfig, EditRunConfig, edit_files

    size, views, test_views, iters = (64, 8, 2, 60) if args.smoke else (256, 24, 4, 500)
    plan = dict(subtasks=1, consolidate=False, turntable_frames=0, asynchronous=False,
                max_steps=20 if args.smoke else args.max_steps,
                patience=10 if args.smoke else args.patience, refine_reset=args.refine_reset)
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        data, recon = work / "data", work / "recon"
        t0 = time.perf_counter()
        if not (recon / "scene.ply").exists():
            cli("make-scene", "person", "--out", str(data), "--downscale", str(256 // size),
                "--views", str(views), "--test-views", str(test_views))
            cli("reconstruct", "--data", str(data), "--out", str(recon), "--iters", str(iters))
        reconstruct_s = time.perf_counter() - t0
        rows, panels = [], []
        for targets in args.rows.split(","):
            editor = EditorConfig(kind="ip2p", steps=5,
                                  targets="detail" if targets == "control" else targets)
            config = EditRunConfig(plan=ProEditConfig.for_mode("proedit", **plan), editor=editor,
                                   identity=IdentityFloor(accept_low=True))

            def progress(spec, step, loss, st):
                if spec.index > 0:
                    raise Stop

            run = work / f"edit_{targets}"
            lines: list[str] = []
            t0 = time.perf_counter()
            try:
                edit_files(config, "turn him into a bronze statue", data, recon / "scene.ply",
                           seed=0, run_dir=run, progress=progress, log=lines.append,
                           report=False, editor=GivesBack() if targets == "control" else None)
            except Stop:
                pass
            schedule = json.loads((run / "schedule.json").read_text())
            r0 = schedule["subtasks"][0]
            m = r0["metrics"]
            rows.append({"targets": targets, "identity": {
                k: schedule["identity"][k] for k in ("psnr", "lpips", "timestep", "views",
                                                     "editor_calls", "passed")},
                "r0": {k: m[k] for k in ("psnr_vs_input", "ssim_vs_input", "lpips_vs_input",
                                         "num_gaussians", "input_gaussians",
                                         "gaussians_vs_input")},
                "r0_steps": r0["steps"], "r0_converged": r0["converged"],
                "r0_guard": r0.get("guard"),
                "r0_seconds": r0["seconds"], "seconds": time.perf_counter() - t0,
                "log": [line for line in lines if "WARNING" in line or "identity" in line]})
            photos = held_out_photos(data)
            rows[-1]["held_out_psnr"] = {
                "input": held_out_psnr(run / "original" / "renders", photos),
                "r0": held_out_psnr(run / Path(r0["snapshot"]).parent / "renders", photos)}
            print(f"{targets:8s} identity {schedule['identity']['psnr']:.1f} dB; r_0 "
                  f"{m['psnr_vs_input']:.2f} dB / LPIPS {m['lpips_vs_input']:.3f} from the "
                  f"input, {m['num_gaussians']} of {m['input_gaussians']} Gaussians", flush=True)
            if targets == "control":
                continue
            if not panels:
                panels.append(read_image(run / "original" / "renders" / "view_000.png")[..., :3])
            panels.append(read_image(run / Path(r0["snapshot"]).parent / "renders"
                                     / "view_000.png")[..., :3])
        args.out.mkdir(parents=True, exist_ok=True)
        if len(panels) == 3:
            write_image(args.out / "edit_targets.png",
                        np.ascontiguousarray(np.concatenate(panels, axis=1), np.float32))
    name = "edit_targets" + ("_refine_reset" if args.refine_reset else "")
    write_json(args.out, name, {
        "smoke": args.smoke, "scene": "person", "size": size, "views": views,
        "test_views": test_views, "reconstruct_iters": iters, "editor": "bundled, 5 DDIM steps",
        "plan": plan, "reconstruct_s": reconstruct_s, "rows": rows,
        "image": "edit_targets.png: a held-out view; input scene | stretch r_0 | detail r_0",
        "machine": machine_info()})


if __name__ == "__main__":
    main()
