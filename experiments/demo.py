"""``demo``: the README's first command, end to end on the built-in ``person`` scene.

    python -m experiments demo --out runs/demo [--scene-name face]

``person`` is Blender Cycles renders of a photo-textured man (256 px, copied at
``--size``: 256 / --size must be an integer); the procedural scenes (face, tabletop,
fence, ball) are rendered at ``--size`` by the ray caster.

Stages (each the in-process call of the command of the same name, so each
stage directory is a complete, reproducible run directory of that command)::

    RUN_DIR/data/          make-scene person      (a nerfstudio dataset)
    RUN_DIR/reconstruct/   reconstruct            (scene.ply, test renders, metrics.json)
    RUN_DIR/edit/          edit --editor ip2p     (schedule.json, subtasks/, report.html)
    RUN_DIR/report.html    the edit's report, with the demo's stage timings
    RUN_DIR/metrics.json   time of each stage, time per subtask, the edit's metrics

The default sizes are chosen to finish in under 10 minutes on a 2-core CPU.
``--reuse`` skips the stages whose outputs already exist (e.g. to re-run only the
edit with another ``--threshold``).
"""

from __future__ import annotations

import importlib.util
import json
import sys
import time
from pathlib import Path

HELP = ("make the person scene, reconstruct it, edit it progressively (the bundled "
        "InstructPix2Pix), write the report")

STAGES = ("make-scene", "reconstruct", "edit")


#: The threshold under the MS-SSIM fallback: d(0, 1) of the bronze edit of face is ~0.07-0.11
#: there, so 0.025 splits it into several subtasks. Under LPIPS the threshold is left to the edit
#: command's default, a quarter of d(0, 1).
MS_SSIM_THRESHOLD = 0.025
#: The demo's instruction: a strong, easy-to-see material edit, known to both editors.
DEFAULT_PROMPT = "turn him into a bronze statue"
#: Views the demo's difficulty is taken over (a seeded subset of the training views).
DIFFICULTY_VIEWS = 8


def add_arguments(p) -> None:
    from jaxedit.edit.plan import MODES, ProEditConfig

    plan = ProEditConfig()  # the flags passed on to the edit stage keep the edit's defaults
    p.add_argument("--scene-name", default="person",
                   help="built-in scene to use (person, or a procedural one: face, tabletop, ...)")
    p.add_argument("--prompt", default=None,
                   help=f"instruction (default: {DEFAULT_PROMPT!r}, one of the bundled editor's)")
    p.add_argument("--editor", default="ip2p", choices=["ip2p", "simulated"],
                   help="2D editor: ip2p, the small InstructPix2Pix bundled with jaxedit (JAX, "
                        "64 px), or simulated, the offline test instrument")
    p.add_argument("--size", type=int, default=64, help="image size of the scene's views")
    p.add_argument("--views", type=int, default=32, help="training views")
    p.add_argument("--test-views", type=int, default=4, help="held-out test views")
    p.add_argument("--iters", type=int, default=1500, help="reconstruction iterations")
    p.add_argument("--threshold", type=float, default=None,
                   help="subtask difficulty threshold of the scheduler (ignored with --subtasks); "
                        "default: d(0, 1) / 4 under LPIPS (the paper's ~4 subtasks for a texture "
                        f"edit), {MS_SSIM_THRESHOLD} under the MS-SSIM fallback")
    p.add_argument("--distance", default="auto", choices=["auto", "lpips", "ms-ssim"],
                   help="difficulty distance of the edit (auto: LPIPS-VGG when its weights are "
                        "converted, else MS-SSIM)")
    p.add_argument("--subtasks", type=int, default=None,
                   help="uniform schedule of N subtasks instead of the difficulty-aware one")
    p.add_argument("--mode", choices=MODES, default=plan.mode, help="editing mode")
    p.add_argument("--max-steps", type=int, default=None,
                   help="per-subtask training step guard of the edit (default: the edit's, "
                        "scaled with the views and resolution)")
    p.add_argument("--turntable-frames", type=int, default=plan.turntable_frames,
                   help="frames of each snapshot's turntable (0: none)")
    p.add_argument("--edit-arg", action="append", default=[], metavar="FLAG=VALUE",
                   help="extra flag for the edit stage, e.g. --edit-arg patience=30 (repeatable)")
    p.add_argument("--reuse", action="store_true",
                   help="skip stages whose outputs already exist in RUN_DIR")


def _require_commands() -> None:
    """Fail loudly, before any work, when a stage's command is not installed."""
    missing = [name for name in STAGES
               if importlib.util.find_spec(f"experiments.{name.replace('-', '_')}") is None]
    if missing:
        raise RuntimeError(f"demo needs the command(s) {', '.join(missing)} "
                           f"(experiments/{missing[0].replace('-', '_')}.py is missing)")


def _stage_argv(command: str, flags: dict) -> list[str]:
    """argv for a stage, keeping only flags its parser knows (None values dropped)."""
    from experiments import cli
    from jaxedit import DataError

    known = {s for a in cli.command_parser(command).arguments for s in a.option_strings}
    argv = [command]
    for flag, value in flags.items():
        if value is None or value is False:
            continue
        if flag.startswith("--") and flag not in known:
            raise DataError(flag, f"the {command} command has no such flag")
        if value is True:
            argv.append(flag)
        elif flag.startswith("--"):
            argv += [flag, str(value)]
        else:  # positional
            argv.append(str(value))
    return argv


def _run_stage(argv: list[str]) -> dict:
    """Parse and run one command in this process, as ``python -m experiments`` would."""
    from experiments import cli

    try:
        args = cli.parse(argv)
    except SystemExit as e:  # argparse already printed its one-line error
        from jaxedit import DataError

        raise DataError(argv[0], f"bad flags for this stage: {' '.join(argv[1:])}") from e
    # config.json records sys.argv: make it this stage's command line, not the demo's,
    # so the stage directory alone tells how to reproduce it.
    saved, sys.argv = sys.argv, [sys.argv[0], *argv]
    try:
        cli.write_run_config(args)
    finally:
        sys.argv = saved
    return args._module.run(args) or {}


def _default_prompt(editor: str) -> str:
    """DEFAULT_PROMPT where the editor knows it, else its first instruction."""
    if editor == "simulated":
        from jaxedit.editors.simulated import SimulatedEditor

        vocabulary = list(SimulatedEditor().instructions)
    else:
        from jaxedit.editors import instructions

        vocabulary = [i["prompt"] for i in instructions()]
    return DEFAULT_PROMPT if DEFAULT_PROMPT in vocabulary or not vocabulary else vocabulary[0]


def _scene_size(name: str, size: int) -> dict:
    """make-scene's size flag: --size for a procedural scene, --downscale for a rendered one."""
    from jaxedit import scenes

    return {f"--{k}": v for k, v in scenes.size_arguments(name, size).items()}


def _edit_extra(pairs: list[str]) -> dict:
    from jaxedit import DataError

    extra = {}
    for pair in pairs:
        flag, sep, value = pair.partition("=")
        if not flag:
            raise DataError("--edit-arg", f"expected FLAG=VALUE, got {pair!r}")
        extra["--" + flag.lstrip("-")] = value if sep else True
    return extra


def run(args) -> dict:
    from experiments.progress import Progress, configure, nested
    from jaxedit import DataError
    from jaxedit.edit.difficulty import lpips_weights_to_use
    from jaxedit.io.files import atomic_write_text
    from jaxedit.pipelines.report import read_json, write_report

    if args.out is None:  # the README's default; record its config like any run dir
        from experiments import cli

        args.out = Path("runs/demo")
        cli.write_run_config(args)
    out = Path(args.out)
    for name in ("size", "views", "test_views", "iters", "max_steps"):
        if getattr(args, name) is not None and getattr(args, name) < 1:
            raise DataError(f"--{name.replace('_', '-')}", f"must be >= 1, got {getattr(args, name)}")
    _require_commands()
    configure(quiet=args.quiet)
    prompt = args.prompt or _default_prompt(args.editor)
    threshold = args.threshold
    if threshold is None and lpips_weights_to_use(args.distance) is None:
        threshold = MS_SSIM_THRESHOLD
    common = {"--seed": args.seed, "--quiet": args.quiet}
    data, recon, edit = out / "data", out / "reconstruct", out / "edit"
    plans = [
        ("make-scene", data / "transforms.json", _stage_argv("make-scene", {
            "name": args.scene_name, "--out": data, **_scene_size(args.scene_name, args.size),
            "--views": args.views, "--test-views": args.test_views, **common})),
        ("reconstruct", recon / "scene.ply", _stage_argv("reconstruct", {
            "--data": data, "--out": recon, "--iters": args.iters, **common})),
        ("edit", edit / "schedule.json", _stage_argv("edit", {
            "--data": data, "--scene": recon / "scene.ply", "--prompt": prompt,
            "--editor": args.editor, "--mode": args.mode,
            "--threshold": None if args.subtasks else threshold, "--distance": args.distance,
            "--subtasks": args.subtasks, "--max-steps": args.max_steps,
            # 8 of the 32 views for the difficulty: under LPIPS-VGG on a CPU each view costs
            # ~20 s of scheduling; a full edit defaults to every view up to 16.
            "--difficulty-views": DIFFICULTY_VIEWS,
            "--turntable-frames": args.turntable_frames, "--out": edit, **common,
            **_edit_extra(args.edit_arg)})),
    ]
    seconds: dict[str, float] = {}
    t_start = time.perf_counter()
    # Relative stage costs measured on the default demo (make-scene is seconds), for the ETA.
    with Progress(len(plans), "demo", weights=[0.03, 0.47, 0.5]) as bar, nested(bar):
        for name, product, argv in plans:
            bar.set_postfix(stage=name)
            if args.reuse and product.exists():
                seconds[name] = 0.0
            else:
                t0 = time.perf_counter()
                _run_stage(argv)
                seconds[name] = round(time.perf_counter() - t0, 2)
                if not product.exists():
                    raise RuntimeError(f"stage {name} finished without writing {product}")
            bar.update(1)

    schedule = read_json(edit / "schedule.json")
    recon_metrics = read_json(recon / "metrics.json", required=False) or {}
    edit_metrics = read_json(edit / "metrics.json", required=False) or {}
    subtask_seconds = {s.get("name", str(i)): s.get("seconds")
                       for i, s in enumerate(schedule.get("subtasks", []))}
    total = round(time.perf_counter() - t_start, 2)
    metrics = {
        "prompt": prompt, "scene": args.scene_name, "total_s": total, "stage_s": seconds,
        "subtask_s": subtask_seconds,
        "reconstruct": {k: v for k, v in recon_metrics.items()
                        if k in ("test_psnr", "test_ssim", "num_gaussians", "wall_time_s")},
        "edit": edit_metrics,
    }
    atomic_write_text(out / "metrics.json", json.dumps(metrics, indent=2) + "\n")
    notes = {"demo total (s)": total,
             **{f"stage {k} (s)": v for k, v in seconds.items()},
             "reconstruction test PSNR (dB)": recon_metrics.get("test_psnr")}
    if not (edit / "report.html").exists():  # the edit command writes its own unless told not to
        write_report(edit)
    report = write_report(edit, out=out / "report.html", notes=notes,
                          title=f"jaxedit demo: {prompt}", config_path=out / "config.json")
    headline = {k: edit_metrics.get(k) for k in ("psnr_vs_target", "ssim_vs_target",
                                                 "multiview_consistency", "num_gaussians")
                if k in edit_metrics}
    return {"report": str(report), "total_s": total, "stage_s": seconds,
            "subtask_s": subtask_seconds, **headline}
