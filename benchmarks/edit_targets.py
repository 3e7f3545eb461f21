"""Targets of views larger than the editor: stretched, detail-keeping and paired edits.

    python benchmarks/edit_targets.py [--smoke] [--out DIR] [--work DIR]

The built-in person at 256 px (24 training and 4 held-out views), reconstructed, then
edited by "turn him into a bronze statue" in one subtask (r_0 = 0, e(0), what every
ProEdit run does first, then r = 1) with the bundled 64 px InstructPix2Pix, once with each
way of making a larger view's target (:mod:`jaxedit.editors.compose`): ``stretch`` (the
64 px edit enlarged, the targets before issue 77), ``detail`` (the render plus the edit's
change at 64 px), ``delta`` (the render plus e(r)'s edit minus e(0)'s of the same view
and noise: two editor images per view, none at e(0)), ``anchored`` (e(0)'s pair made on
the view's photo, less the photo: two images per view) and ``hybrid`` (the render at e(0),
detail after), and a control editor that gives the render back (r_0's own cost, no
editor's; it stops after r_0). Per composition: the editor
identity check's figures; r_0's and r = 1's snapshots against the input scene's renders
(PSNR, SSIM, LPIPS, Gaussians) and their held-out PSNR against the photos; r = 1's
renders against r_0's; the editor images per edited view of each subtask (counted at the
editor); and the composition's own targets of the input's held-out renders at e(0) and
e(1) (t = 0.98, one key per view) against those renders. Writes ``DIR/edit_targets.json``
(after each row), ``DIR/edit_targets.png`` (a held-out view; per composition: input, r_0,
r = 1) and ``DIR/edit_targets_r1_targets.png`` (per composition: the render, its targets
at e(0) and e(1)). ``--smoke``: the person at 64 px (the editor's size: every composition
edits alike, so only anchored and the control run), 8 views, a few steps. Subtasks run to
the run's own plateau and step guard (``--max-steps``, ``--patience`` to hold them);
``--r0-only`` stops after r_0;
``--refine-reset`` starts r_0 with the opacity reset (``edit --refine-opacity-reset``) and
writes ``DIR/edit_targets_refine_reset.json`` (``--rows control`` for the control alone).
"""

from __future__ import annotations

import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from common import machine_info, parse_args, write_json

ROOT = Path(__file__).resolve().parents[1]


def extra(p):
    p.add_argument("--work", type=Path, default=None,
                   help="keep the dataset, reconstruction and runs here (default: a temp dir)")
    p.add_argument("--rows", default=None,
                   help="comma list of delta, anchored, hybrid, detail, stretch, control "
                        "(default: all; --smoke: anchored, control)")
    p.add_argument("--max-steps", type=int, default=None,
                   help="each subtask's step guard (default: the run's, from the scene)")
    p.add_argument("--patience", type=int, default=None,
                   help="each subtask's plateau patience (default: the run's)")
    p.add_argument("--r0-only", action="store_true", help="stop every row after r_0")
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


class Counted:
    """``editor`` (which edits at its own size) counting the images it edits per phase:
    ``phase`` is set by the run's log (each subtask's start), "check" before."""

    def __init__(self, editor):
        self.editor, self.phase, self.images, self.calls = editor, "check", {}, {}
        self.lock = threading.Lock()

    def __getattr__(self, name):
        return getattr(self.editor, name)

    def _count(self, n: int) -> None:
        with self.lock:
            self.images[self.phase] = self.images.get(self.phase, 0) + int(n)
            self.calls[self.phase] = self.calls.get(self.phase, 0) + 1

    def edit_many(self, images, *args, **kwargs):
        self._count(len(images))
        return self.editor.edit_many(images, *args, **kwargs)

    def edit(self, image, *args, **kwargs):
        self._count(1)
        return self.editor.edit(image, *args, **kwargs)


class ViewsAsked:
    """Counts the views a run asks of a composed editor (its ``edit``/``edit_many``), per
    phase of ``counted``; set on the instance, so the identity check's editor is not counted."""

    def __init__(self, composed, counted):
        self.views: dict[str, int] = {}
        self.local = threading.local()  # edit_views calls from threads
        for name in ("edit", "edit_many"):
            fn = getattr(composed, name)

            def wrapped(images, *args, _fn=fn, _one=name == "edit", **kwargs):
                outer = not getattr(self.local, "inside", False)
                if outer:
                    with counted.lock:
                        self.views[counted.phase] = (self.views.get(counted.phase, 0)
                                                     + (1 if _one else len(images)))
                self.local.inside = True
                try:
                    return _fn(images, *args, **kwargs)
                finally:
                    self.local.inside = not outer
            setattr(composed, name, wrapped)


class Stop(Exception):
    """Raised by the progress callback once the benchmark has what it needs."""


def cli(*argv: str) -> None:
    subprocess.run([sys.executable, "-m", "experiments", *argv, "--quiet"], cwd=ROOT,
                   check=True, stdout=subprocess.DEVNULL)


def held_out_photos(data):
    """The held-out photos of the dataset ``data``, float [M, H, W, 3]."""
    import numpy as np

    from jaxedit.io import load_nerfstudio

    dataset = load_nerfstudio(data)
    return np.asarray(dataset.images, np.float32)[np.asarray(dataset.test_indices)]


def renders_of(renders_dir: Path):
    """A snapshot's renders (PNG, sorted), float [M, H, W, 3]."""
    import numpy as np

    from jaxedit.io import read_image

    return np.stack([read_image(p)[..., :3] for p in sorted(renders_dir.glob("*.png"))])


def held_out_psnr(renders_dir: Path, photos) -> float:
    """Mean PSNR (dB) of a snapshot's renders (PNG) against the held-out photos."""
    from jaxedit.edit.outputs import image_scores

    return image_scores(renders_of(renders_dir), photos)["psnr"]


def probe_targets(composed, renders, photos, prompt: str) -> tuple[dict, list]:
    """The composition's targets of ``renders`` [M, H, W, 3] (photos as the editor's
    originals) at e(0) and e(1), t = 0.98, one key per view: their PSNR / mean change
    against the renders, and the targets themselves [2][M, H, W, 3]."""
    import jax
    import numpy as np

    from jaxedit.edit.outputs import image_scores
    from jaxedit.editors.base import edit_views

    keys = jax.random.split(jax.random.key(7), len(renders))
    out, images = {}, []
    for name, emb in (("e0", composed.encode("")), ("e1", composed.encode(prompt))):
        got = np.stack([np.asarray(x, np.float32) for x in edit_views(
            composed, list(renders), list(photos), emb, keys, timestep_range=(0.98, 0.98))])
        images.append(got)
        out[name] = {"psnr_vs_render": image_scores(got, renders)["psnr"],
                     "mean_abs_change": float(np.abs(got - renders).mean())}
    return out, images


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv, extra)
    import dataclasses
    import json

    import numpy as np

    from jaxedit.edit import ProEditConfig
    from jaxedit.edit.identity import IdentityFloor
    from jaxedit.edit.outputs import distance_to_input
    from jaxedit.editors.compose import EDITS_PER_VIEW, with_targets
    from jaxedit.io import read_image, write_image
    from jaxedit.pipelines.edit_run import EditorConfig, EditRunConfig, edit_files, make_editor

    prompt = "turn him into a bronze statue"
    size, views, test_views, iters = (64, 8, 2, 60) if args.smoke else (256, 24, 4, 500)
    plan = dict(subtasks=1, consolidate=False, turntable_frames=0, asynchronous=False,
                max_steps=20 if args.smoke else args.max_steps,
                patience=10 if args.smoke else args.patience, refine_reset=args.refine_reset,
                **({"warmup": 4} if args.smoke else {}))
    name = "edit_targets" + ("_refine_reset" if args.refine_reset else "")
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        data, recon = work / "data", work / "recon"
        t0 = time.perf_counter()
        if not (recon / "scene.ply").exists():
            cli("make-scene", "person", "--out", str(data), "--downscale", str(256 // size),
                "--views", str(views), "--test-views", str(test_views))
            cli("reconstruct", "--data", str(data), "--out", str(recon), "--iters", str(iters))
        reconstruct_s = time.perf_counter() - t0
        photos = held_out_photos(data)
        rows, panels, probes = [], [], []
        rows_asked = args.rows or ("anchored,control" if args.smoke else
                                   "delta,anchored,hybrid,detail,stretch,control")
        for targets in rows_asked.split(","):
            control = targets == "control"
            editor_cfg = EditorConfig(kind="ip2p", steps=5,
                                      targets="detail" if control else targets)
            config = EditRunConfig(plan=ProEditConfig.for_mode("proedit", **plan),
                                   editor=editor_cfg, identity=IdentityFloor(accept_low=True))
            counted = asked = None
            if control:
                editor = GivesBack()
            else:
                counted = Counted(make_editor(dataclasses.replace(editor_cfg, targets="stretch")))
                editor = with_targets(counted, targets)
                asked = ViewsAsked(editor, counted)
            last = 0 if control or args.r0_only else 1

            def progress(spec, step, loss, st, last=last):
                if spec.index > last:
                    raise Stop

            lines: list[str] = []

            def log(line, counted=counted):
                lines.append(line)
                start = re.match(r"subtask \d+ (\S+) \(", line)  # "subtask 1 r1 (edit) r = "
                if counted is not None and start:
                    counted.phase = start.group(1)

            run = work / f"edit_{targets}"
            t0 = time.perf_counter()
            try:
                edit_files(config, prompt, data, recon / "scene.ply", seed=0, run_dir=run,
                           progress=progress, log=log, report=False, editor=editor)
            except Stop:
                pass
            seconds = time.perf_counter() - t0
            schedule = json.loads((run / "schedule.json").read_text())
            done = [s for s in schedule["subtasks"][:last + 1] if s.get("snapshot")]
            r0 = done[0]
            row = {"targets": targets, "identity": {
                k: schedule["identity"][k] for k in ("psnr", "lpips", "timestep", "views",
                                                     "editor_calls", "passed")}}
            input_renders = renders_of(run / "original" / "renders")
            for s in done:
                key = "r0" if s is r0 else "r1"
                m = s["metrics"]
                snap = run / Path(s["snapshot"]).parent / "renders"
                row[key] = {k: m[k] for k in ("ratio", "psnr_vs_input", "ssim_vs_input",
                                              "lpips_vs_input", "num_gaussians",
                                              "input_gaussians", "gaussians_vs_input")}
                row[f"{key}_steps"], row[f"{key}_converged"] = s["steps"], s["converged"]
                row[f"{key}_guard"], row[f"{key}_seconds"] = s.get("guard"), s["seconds"]
                row.setdefault("held_out_psnr", {"input": held_out_psnr(
                    run / "original" / "renders", photos)})[key] = held_out_psnr(snap, photos)
            if "r1" in row:
                r0_renders = renders_of(run / Path(r0["snapshot"]).parent / "renders")
                r1_renders = renders_of(run / Path(done[1]["snapshot"]).parent / "renders")
                d = distance_to_input(r1_renders, r0_renders)
                row["r1_vs_r0"] = {"psnr": d["psnr_vs_input"], "ssim": d["ssim_vs_input"],
                                   "lpips": d["lpips_vs_input"]}
            row["seconds"] = seconds
            if counted is not None:
                row["editor_images"] = dict(counted.images)
                row["editor_calls"] = dict(counted.calls)
                row["views_edited"] = dict(asked.views)
                row["editor_images_per_view"] = {
                    k: counted.images.get(k, 0) / v for k, v in asked.views.items() if v}
                row["editor_images_per_view_at_r_gt_0"] = EDITS_PER_VIEW[targets]
                counted.phase = "probe"
                probe, images = probe_targets(editor, input_renders, photos, prompt)
                row["targets_of_input_renders"] = probe
                probes.append([input_renders[0]] + [x[0] for x in images])
            row["log"] = [line for line in lines if "WARNING" in line or "identity" in line]
            rows.append(row)
            r1 = row.get("r1", {})
            print(f"{targets:8s} identity {schedule['identity']['psnr']:.1f} dB; r_0 "
                  f"{row['r0']['psnr_vs_input']:.2f} dB from the input (held-out "
                  f"{row['held_out_psnr']['r0']:.2f}); r = 1 "
                  f"{r1.get('psnr_vs_input', float('nan')):.2f} dB, LPIPS "
                  f"{r1.get('lpips_vs_input', float('nan')):.3f}", flush=True)
            if not control:
                views_dir = [run / "original" / "renders"] + [
                    run / Path(s["snapshot"]).parent / "renders" for s in done]
                panels.append(np.concatenate(
                    [read_image(v / "view_000.png")[..., :3] for v in views_dir], axis=1))
            write_json(args.out, name, {
                "smoke": args.smoke, "scene": "person", "size": size, "views": views,
                "test_views": test_views, "reconstruct_iters": iters, "prompt": prompt,
                "editor": "bundled, 5 DDIM steps", "plan": plan, "reconstruct_s": reconstruct_s,
                "editor_images_per_view_at_r_gt_0": EDITS_PER_VIEW, "rows": rows,
                "image": f"{name}.png: a held-out view, a row per composition ("
                         + ", ".join(r["targets"] for r in rows if r["targets"] != "control")
                         + "): input scene | r_0 | r = 1",
                "targets_image": f"{name}_r1_targets.png: a held-out input render, a row per "
                                 "composition: render | target at e(0) | target at e(1)",
                "machine": machine_info()})
        widths = {p.shape[1] for p in panels}
        if panels and len(widths) == 1:
            write_image(args.out / f"{name}.png",
                        np.ascontiguousarray(np.concatenate(panels, axis=0), np.float32))
        if probes:
            write_image(args.out / f"{name}_r1_targets.png", np.ascontiguousarray(
                np.concatenate([np.concatenate(p, axis=1) for p in probes], axis=0), np.float32))


if __name__ == "__main__":
    main()
