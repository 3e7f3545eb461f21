"""``demo``: the README's first command, end to end on the built-in ``person`` scene.

    python -m experiments demo --out runs/demo [--scene-name face]

``person`` is Blender Cycles renders of a photo-textured man (256 px, copied at
``--size``: 256 / --size must be an integer); the procedural scenes (face, tabletop,
fence, ball) are rendered at ``--size`` by the ray caster.

Stages (make-scene and reconstruct are the in-process calls of those commands; the edit
is the call the edit command makes, :func:`jaxedit.pipelines.edit_run.edit_files`, with a
config tree, :func:`edit_config`; each stage directory is a complete, reproducible run
directory of its command, whose config.json gives the command line)::

    RUN_DIR/data/          make-scene person      (a nerfstudio dataset)
    RUN_DIR/reconstruct/   reconstruct            (scene.ply, test renders, metrics.json)
    RUN_DIR/edit/          edit --editor ip2p     (schedule.json, subtasks/, report.html)
    RUN_DIR/report.html    the edit's report, with the demo's stage timings
    RUN_DIR/metrics.json   time of each stage, time per subtask, the edit's metrics

The defaults (:class:`DemoConfig`) are sized to finish in about three minutes on a 2-core CPU.
``--reuse`` skips the stages whose outputs already exist (e.g. to re-run only the
edit with another ``--threshold``).
"""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import time
from pathlib import Path
from typing import Callable

from jaxedit.edit.plan import ProEditConfig
from jaxedit.errors import check_ranges, ranged

HELP = ("make the person scene, reconstruct it, edit it progressively (the bundled "
        "InstructPix2Pix), write the report")

STAGES = ("make-scene", "reconstruct", "edit")


#: The threshold under --distance ms-ssim: d(0, 1) of the bronze edit of face is ~0.07-0.11
#: there, so 0.025 splits it into several subtasks. Under LPIPS the threshold is left to the edit
#: command's default, a fraction of d(0, 1).
MS_SSIM_THRESHOLD = 0.025
#: The demo's instruction: a strong, easy-to-see material edit, known to both editors.
DEFAULT_PROMPT = "turn him into a bronze statue"


@dataclasses.dataclass(frozen=True)
class DemoConfig:
    """The demo's settings: the scene, its reconstruction and the edit, sized to finish in
    about three minutes on a 2-core CPU (the edit's own defaults are sized for a real
    capture; where the demo differs, the field says why).

    Attributes:
      scene_name: built-in scene to use (person, or a procedural one: face, tabletop, ...).
      prompt: instruction (None: 'turn him into a bronze statue', one of the bundled
        editor's instructions).
      editor: 2D editor: ip2p, the small InstructPix2Pix bundled with jaxedit (JAX, 64 px),
        or simulated, the offline test instrument.
      size: image size of the scene's views.
      views: training views (16: every view is edited at the start of each subtask, so the
        views set the cost of a subtask's initial sweep).
      test_views: held-out test views.
      iters: reconstruction iterations (1000: about 35 dB on the held-out views).
      threshold: subtask difficulty threshold of the scheduler (ignored with --subtasks;
        None: the edit's default under LPIPS, 0.025 under MS-SSIM).
      distance: difficulty distance of the edit (auto: LPIPS with the bundled AlexNet).
      subtasks: uniform schedule of N subtasks instead of the difficulty-aware one.
      mode: editing mode.
      max_steps: per-subtask training step guard of the edit (None: the edit's, scaled with
        the views and resolution).
      turntable_frames: frames of each snapshot's turntable (0: none).
      difficulty_views: views the difficulty is taken over (a seeded subset of the training
        views; under LPIPS-VGG on a CPU each view costs about a second per ratio).
      patience: steps without a new minimum of the running mean loss that end a subtask
        (the edit's 60 is sized for captures of hundreds of views; 16 views of 64 px reach
        their plateau sooner).
      ip2p_steps: DDIM steps per edit of the bundled editor (5: on held-out person views
        its 5-step edits are within 29-32 dB PSNR of its 20-step edits, 10-step within
        37-40 dB, while an edit moves the view about 15 dB; at 0.13 s an edit instead of
        0.25 s, and the edits are most of the demo's time).
      refine_first: run the extra subtask r_0 = 0 that refines the scene with the editor
        before the edit (off: the bundled editor's identity edit is lossy, about 17 dB on
        held-out views, so at r = 0 it only blurs the reconstruction).
      target_subtasks: edit subtasks the scheduler is asked for (the paper's ~4 for a
        texture edit; None: the edit's threshold d(0, 1) / 4, which splits a d(0, r) that
        grows evenly into 4 to 8 subtasks depending on which side of it each quarter falls).
      edit_arg: another setting of the edit stage as FLAG=VALUE (or FLAG, a switch), one of
        the edit command's settings flags, e.g. warmup=20 or sync.
      reuse: skip stages whose outputs already exist in RUN_DIR.
    """

    scene_name: str = "person"
    prompt: str | None = None
    editor: str = "ip2p"
    size: int = ranged(64, low=1)
    views: int = ranged(16, low=1)
    test_views: int = ranged(4, low=1)
    iters: int = ranged(1000, low=1)
    threshold: float | None = ranged(None, low=0, open=True)
    distance: str = "auto"
    subtasks: int | None = ranged(None, low=1)
    mode: str = ProEditConfig.mode
    max_steps: int | None = ranged(None, low=1)
    turntable_frames: int = ranged(ProEditConfig.turntable_frames, low=0)
    difficulty_views: int = ranged(4, low=1)
    patience: int = ranged(30, low=1)
    ip2p_steps: int = ranged(5, low=1)
    refine_first: bool = False
    target_subtasks: int | None = ranged(4, low=1)
    edit_arg: tuple[str, ...] = ()
    reuse: bool = False

    def __post_init__(self):
        check_ranges(self)


def _config_flags():
    from jaxedit.edit.difficulty import DISTANCES
    from jaxedit.edit.plan import MODES

    from .flags import Flag, FlagSet

    return FlagSet(DemoConfig, (
        Flag("scene_name"), Flag("prompt"), Flag("editor", choices=("ip2p", "simulated")),
        Flag("size"), Flag("views"), Flag("test_views"), Flag("iters"), Flag("threshold"),
        Flag("distance", choices=DISTANCES), Flag("subtasks"), Flag("mode", choices=MODES),
        Flag("max_steps"), Flag("turntable_frames"), Flag("difficulty_views"),
        Flag("patience"), Flag("ip2p_steps"), Flag("refine_first"), Flag("target_subtasks"),
        Flag("edit_arg", repeat=True, metavar="FLAG=VALUE"), Flag("reuse"))).complete()


#: The command's flags, generated from :class:`DemoConfig`.
FLAGS = (_config_flags(),)


def add_arguments(p) -> None:
    FLAGS[0].add_to(p)


def run_config(args) -> DemoConfig:
    """The :class:`DemoConfig` of ``args`` (range errors name the flag)."""
    return FLAGS[0].build(args)


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
    # config.json records this stage's command line, not the demo's, so the stage
    # directory alone tells how to reproduce it.
    cli.write_run_config(args, argv=argv)
    return args._module.run(args) or {}


def _default_prompt(editor: str) -> str:
    """DEFAULT_PROMPT where the editor knows it, else its first instruction."""
    if editor == "simulated":
        from jaxedit_lab.simulated import SimulatedEditor

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
    """{field path of the edit's config tree: value} of ``--edit-arg`` FLAG=VALUE pairs
    (a switch alone: FLAG), each read as the edit command reads that flag."""
    from jaxedit import DataError

    from .edit import FLAGS

    extra = {}
    for pair in pairs:
        flag, sep, value = pair.partition("=")
        if not flag.strip("-"):
            raise DataError("--edit-arg", f"expected FLAG=VALUE, got {pair!r}")
        try:
            field, extra_value = FLAGS[0].field_value(flag, value if sep else None)
        except ValueError as e:
            raise DataError("--edit-arg", str(e)) from None
        extra[field] = extra_value
    return extra


def edit_config(config: DemoConfig):
    """The edit stage's :class:`jaxedit.pipelines.edit_run.EditRunConfig`: the edit command's
    defaults for the demo's mode, the demo's settings, then its ``edit_arg`` ones."""
    from jaxedit.edit.difficulty import lpips_weights_to_use

    from .edit import mode_defaults
    from .flags import with_fields

    threshold = config.threshold
    if threshold is None and lpips_weights_to_use(config.distance) is None:
        threshold = MS_SSIM_THRESHOLD
    values = {
        "editor.kind": config.editor, "distance": config.distance,
        "plan.threshold": None if config.subtasks else threshold,
        "plan.target_subtasks": (None if config.subtasks or threshold is not None
                                 else config.target_subtasks),
        "plan.refine_first": config.refine_first, "plan.subtasks": config.subtasks,
        "plan.max_steps": config.max_steps, "plan.difficulty_views": config.difficulty_views,
        "plan.patience": config.patience, "plan.turntable_frames": config.turntable_frames,
        "editor.steps": config.ip2p_steps if config.editor == "ip2p" else None}
    # None: the edit's own default, as a flag not given.
    values = {k: v for k, v in values.items() if v is not None}
    return with_fields(mode_defaults(config.mode), values | _edit_extra(list(config.edit_arg)))


def _edit_argv(run_cfg, mode: str, inputs: dict) -> list[str]:
    """The edit command line that runs ``run_cfg`` on ``inputs`` ({flag: value}), for the
    edit folder's config.json (and its report's "reproduce with")."""
    from .edit import FLAGS, mode_defaults

    argv = ["edit", "--mode", mode]
    for flag, value in inputs.items():
        if value is True:
            argv.append(flag)
        elif value is not None and value is not False:
            argv += [flag, str(value)]
    return argv + FLAGS[0].argv(run_cfg, mode_defaults(mode))


def _editor_warm_up(editor, edit_cfg, data: Path, seed: int) -> Callable[[], None]:
    """The call that compiles the edit's editor program (:func:`jaxedit.editors.warm_up`) for
    the views of ``data`` and the difficulty's batch: run on a thread while the
    reconstruction trains, so that the compile overlaps the training instead of delaying the
    difficulty schedule (on a GPU an SD 1.5-size editor program compiles for about 45 s)."""
    import functools

    import jax

    from jaxedit.editors import warm_up
    from jaxedit.io import nerfstudio_view_size
    from jaxedit.io.nerfstudio import dataset_downscale

    height, width = nerfstudio_view_size(data, downscale=dataset_downscale(data, edit_cfg.downscale))
    # the difficulty's call: its views in one batch where the editor takes batches
    views = max(1, min(int(getattr(editor, "batch", 1)), edit_cfg.plan.difficulty_views or 1))
    return functools.partial(warm_up, editor, height, width, jax.random.key(seed), views=views,
                             guidance=edit_cfg.plan.guidance)


def _run_edit(run_cfg, argv: list[str], *, prompt: str, data: Path, scene: Path, out: Path,
              seed: int, quiet: bool, editor=None) -> None:
    """The edit stage: :func:`jaxedit.pipelines.edit_run.edit_files`, the call the edit command
    makes, with the edit command's progress bars; ``out`` gets the config.json the edit
    command writes for ``argv``, the same run."""
    from experiments import cli
    from jaxedit.pipelines.edit_run import edit_files

    from .edit import progress_callback
    from .editors import make_editor

    cli.write_run_config(cli.parse(argv), argv=argv)
    progress = progress_callback(quiet)
    log = (lambda m: None) if quiet else (lambda m: print(m, flush=True))
    try:
        edit_files(run_cfg, prompt, data, scene, seed=seed, run_dir=out,
                   editor=make_editor(run_cfg.editor) if editor is None else editor,
                   progress=progress, log=log)
    finally:
        progress.close()


def run(args) -> dict:
    from experiments.progress import Progress, configure, nested
    from jaxedit.compilation import compile_stats
    from jaxedit.io.files import atomic_write_text
    from jaxedit.pipelines.report import read_json, write_report

    if args.out is None:  # the README's default; record its config like any run dir
        from experiments import cli

        args.out = Path("runs/demo")
        cli.write_run_config(args)
    out = Path(args.out)
    config = run_config(args)
    _require_commands()
    configure(quiet=args.quiet)
    prompt = config.prompt or _default_prompt(config.editor)
    common = {"--seed": args.seed, "--quiet": args.quiet}
    data, recon, edit = out / "data", out / "reconstruct", out / "edit"
    # The edit runs through the library's call with its config tree; the first two stages
    # are their commands run in this process.
    edit_cfg = edit_config(config)
    edit_argv = _edit_argv(edit_cfg, config.mode, {
        "--data": data, "--scene": recon / "scene.ply", "--prompt": prompt, "--out": edit,
        **common})
    make_argv = _stage_argv("make-scene", {
        "name": config.scene_name, "--out": data, **_scene_size(config.scene_name, config.size),
        "--views": config.views, "--test-views": config.test_views, **common})
    recon_argv = _stage_argv("reconstruct", {
        "--data": data, "--out": recon, "--iters": config.iters, **common})
    warmed = []  # the edit's editor, built before the reconstruction and warmed up during it

    def reconstruct():
        if config.reuse and (edit / "schedule.json").exists():
            return _run_stage(recon_argv)
        from jaxedit.pipelines.edit_run import on_a_thread

        from .editors import make_editor

        warmed.append(make_editor(edit_cfg.editor))  # missing weights stop the demo here
        with on_a_thread(_editor_warm_up(warmed[0], edit_cfg, data, args.seed)):
            _run_stage(recon_argv)

    plans = [
        ("make-scene", data / "transforms.json", lambda: _run_stage(make_argv)),
        ("reconstruct", recon / "scene.ply", reconstruct),
        ("edit", edit / "schedule.json", lambda: _run_edit(
            edit_cfg, edit_argv, prompt=prompt, data=data, scene=recon / "scene.ply", out=edit,
            seed=args.seed, quiet=args.quiet, editor=warmed[0] if warmed else None)),
    ]
    seconds: dict[str, float] = {}
    compiles_before = compile_stats()
    t_start = time.perf_counter()
    # Relative stage costs measured on the default demo (make-scene is seconds), for the ETA.
    with Progress(len(plans), "demo", weights=[0.03, 0.47, 0.5]) as bar, nested(bar):
        for name, product, stage in plans:
            bar.set_postfix(stage=name)
            if config.reuse and product.exists():
                seconds[name] = 0.0
            else:
                t0 = time.perf_counter()
                stage()
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
        "prompt": prompt, "scene": config.scene_name, "total_s": total, "stage_s": seconds,
        "subtask_s": subtask_seconds,
        "reconstruct": {k: v for k, v in recon_metrics.items()
                        if k in ("test_psnr", "test_ssim", "num_gaussians", "wall_time_s")},
        "edit": edit_metrics,
        "compiles": compile_stats(since=compiles_before),
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
    compiles = {k: metrics["compiles"][k] for k in ("count", "seconds", "cache_hits")}
    return {"report": str(report), "total_s": total, "stage_s": seconds,
            "subtask_s": subtask_seconds, "compiles": compiles, **headline}
