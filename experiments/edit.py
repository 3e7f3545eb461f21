"""``python -m experiments edit``: progressive instruction-guided editing of a 3DGS scene (ProEdit).

Writes into ``--out`` RUN_DIR: ``schedule.json`` (updated after every subtask, so a
run can be previewed while it works), ``metrics.json``, ``original/`` and
``subtasks/NN_rX.XXX/`` snapshots (scene.ply, renders, depth, metrics), a resumable
``checkpoint.npz`` and ``report.html``. ``--select R`` points ``selected.ply``
at a snapshot (also on a finished run with ``--select-only``); ``--resume``
continues a crashed run; ``--resume-from SNAPSHOT_DIR`` continues from any
snapshot with another schedule (more or fewer subtasks, another threshold).
``--view`` serves the scene in the browser while it is edited (``experiments/view.py``).

Steering (the run as a tree, :mod:`jaxedit.pipelines.steer_run`): ``--from NODE --refine``
redoes a step split in two, ``--from NODE --prompt TEXT`` (or another ``--seed``,
``--threshold``, ...) branches, ``--extend R_MAX`` goes past r = 1, ``--stop`` asks the
running edit to stop after its subtask, ``--tree`` prints the tree; a branch reuses the run's
recorded flags, so only what changes is given.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Callable
from pathlib import Path

from jaxedit.editors.compose import TARGETS
from jaxedit.errors import ranged
from jaxedit.pipelines.edit_run import EditorConfig, EditRunConfig

from .editors import DEFAULT as DEFAULT_EDITOR

HELP = "progressively edit a 3DGS scene with an instruction (ProEdit)"


#: Library arguments named unlike their flags (for error messages).
FIELD_FLAGS = {"run_dir": "--out"}

@dataclasses.dataclass(frozen=True)
class EditSettings(EditRunConfig):
    __doc__ = EditRunConfig.__doc__
    #: the command's editor without ``--editor``: the lab's offline test instrument
    editor: EditorConfig = EditorConfig(kind=DEFAULT_EDITOR)


def _config_flags():
    from jaxedit.edit.plan import MODES
    from jaxedit.edit.difficulty import DISTANCES

    from .editors import EDITORS
    from .flags import Flag, FlagSet

    return FlagSet(EditSettings, (
        Flag("plan.mode", choices=MODES),
        Flag("plan.threshold"),
        Flag("plan.target_subtasks"),
        Flag("plan.subtasks"),
        Flag("plan.difficulty_views"),
        Flag("train.densify.max_gaussians"),
        Flag("plan.schedule_method", choices=("bisect", "root")),
        Flag("plan.refine_first", off="--no-refine-first"),
        Flag("plan.refine_reset", "--refine-opacity-reset"),
        Flag("plan.consolidate", off="--no-consolidate"),
        Flag("plan.pipelined", off="--inline-edits"),
        Flag("plan.asynchronous", "--async", off="--sync", key="asynchronous"),
        Flag("downscale"),
        Flag("skip_missing_images"),
        Flag("plan.warmup"),
        Flag("plan.patience"),
        Flag("plan.max_steps"),
        Flag("plan.max_seconds", "--max-subtask-seconds"),
        Flag("plan.edit_every"),
        Flag("plan.guidance", metavar=("TEXT", "IMAGE")),
        Flag("plan.turntable_frames"),
        Flag("test_views"),
        Flag("editor.kind", "--editor", choices=EDITORS),
        Flag("editor.weights", "--ip2p-weights"),
        Flag("editor.device", "--ip2p-device"),
        Flag("editor.dtype", "--ip2p-dtype"),
        Flag("editor.size", "--ip2p-size"),
        Flag("editor.steps", "--ip2p-steps"),
        Flag("editor.batch", "--ip2p-batch"),
        Flag("editor.targets", "--edit-targets", choices=TARGETS),
        Flag("identity.accept_low", "--accept-low-identity"),
        Flag("distance", choices=DISTANCES),
        Flag("lpips_weights"),
    )).complete()


@dataclasses.dataclass(frozen=True)
class EditCommand:
    """What one ``edit`` command works on and does besides the edit's settings
    (:class:`jaxedit.pipelines.edit_run.EditRunConfig`).

    Attributes:
      preset: a method's whole config tree to start from (proedit, nd, in2n, igs2gs;
        None: the one --mode names); the flags given win over it.
      print_config: print the config tree this command would run (JSON, the nested keys
        --config reads) and exit.
      data: nerfstudio dataset folder (the scene's photos).
      scene: input splat file, any format load_scene reads (a reconstruction of --data).
      prompt: the editing instruction.
      select: subtask index (int) or ratio (float) to export as selected.ply.
      select_only: only (re)select a snapshot of the finished run in --out.
      resume: continue the interrupted run in --out from its checkpoint.
      resume_from: snapshot dir (RUN/subtasks/NN_rX.XXX) to continue from, new schedule.
      no_report: skip report.html.
      view: serve the scene in the browser while it is edited (viser; see `view`).
      view_port: port of --view on 127.0.0.1 (0: any free one).
      clip_weights: transformers CLIP folder: add IN2N's CLIP metrics to metrics.json.
      caption_orig: caption of the original (CLIP metrics).
      caption_edit: caption of the edit (CLIP metrics).
      local: auto: edit only the Gaussians the editor's relevance map lifts to (within
        --region / --masks); off: the whole scene (or only --region / --masks when given).
      region: box:xmin,ymin,zmin,xmax,ymax,zmax or sphere:cx,cy,cz,r in scene coordinates
        (their union); outside it nothing changes.
      masks: one mask image per frame, named as the frame (images/frame_00001.png takes
        DIR/frame_00001.png) or as its photo (process-data's original_file_path), at the
        view's size or a whole multiple of it; white = editable.
      from_node: a finished subtask of the run in --out to branch from: INDEX (the main
        branch) or BRANCH:INDEX, negative from the end (e.g. b1:-1); with --prompt, a new
        instruction from there, else the same one with the flags given (--seed, ...).
      refine: redo the step of --from NODE from the snapshot before it, split in two where
        the halves' difficulties meet, then the steps after it.
      ratio: the ratio --refine splits the step at (default: the difficulty-aware split).
      extend: go past r = 1 up to this ratio with extrapolated embeddings (experimental),
        from --from NODE (default: the main branch's last subtask).
      name: the new branch's name (default b1, b2, ...).
      branch: the branch --resume continues (default: the main one).
      stop: ask the edit running in --out to stop after its current subtask (--resume
        goes on).
      tree: print the run's tree of branches and subtasks.
      export: formats (comma list of ply, compressed-ply, spz, sog, splat) to write the
        selected snapshot (--select, else the last) in, as RUN/selected.spz etc.
    """

    preset: str | None = None
    print_config: bool = False
    data: Path | None = None
    scene: Path | None = None
    prompt: str | None = None
    select: str | None = None
    select_only: bool = False
    resume: bool = False
    resume_from: Path | None = None
    no_report: bool = False
    view: bool = False
    view_port: int = ranged(8080, low=0, high=65535)
    clip_weights: str | None = None
    caption_orig: str | None = None
    caption_edit: str | None = None
    local: str = "off"
    region: tuple[str, ...] = ()
    masks: Path | None = None
    from_node: str | None = None
    refine: bool = False
    ratio: float | None = ranged(None, low=0, open=True)
    extend: float | None = ranged(None, low=1, open=True)
    name: str | None = None
    branch: str | None = None
    stop: bool = False
    tree: bool = False
    export: tuple[str, ...] = ()

    def __post_init__(self):
        from jaxedit.errors import check_ranges

        from .export import export_formats

        check_ranges(self)
        object.__setattr__(self, "export", export_formats(self.export))


def _command_flags():
    from .flags import Flag, FlagSet

    clip = "CLIP metrics (local weights, see the README)"
    local = "local edits (only what the instruction touches changes)"
    steer = "steering a run in --out (a tree of branches from its snapshots)"
    from jaxedit.pipelines.presets import PRESETS

    return FlagSet(EditCommand, (
        Flag("preset", choices=tuple(PRESETS)), Flag("print_config"), Flag("data"), Flag("scene"), Flag("prompt"), Flag("select"), Flag("select_only"),
        Flag("resume"), Flag("resume_from"), Flag("no_report"), Flag("view"),
        Flag("view_port"), Flag("clip_weights", group=clip), Flag("caption_orig", group=clip),
        Flag("caption_edit", group=clip), Flag("local", choices=("auto", "off"), group=local),
        Flag("region", repeat=True, group=local, metavar="SPEC"),
        Flag("masks", group=local, metavar="DIR"),
        Flag("from_node", "--from", group=steer, metavar="NODE", key="from_node"),
        Flag("refine", group=steer), Flag("ratio", group=steer),
        Flag("extend", group=steer, metavar="R_MAX"), Flag("name", group=steer),
        Flag("branch", group=steer), Flag("stop", group=steer),
        Flag("tree", group=steer), Flag("export", metavar="FORMATS"))).complete()


def _flag_sets():
    from .distributed import distributed_flags

    return _config_flags(), _command_flags(), distributed_flags()


#: The command's flags: its settings' (:class:`jaxedit.pipelines.edit_run.EditRunConfig`), its
#: inputs' and actions' (:class:`EditCommand`) and the multi-process run's
#: (:class:`jaxedit.parallel.distributed.DistributedConfig`), all generated from the trees.
FLAGS = _flag_sets()


def add_arguments(p: argparse.ArgumentParser) -> None:
    FLAGS[1].add_to(p)
    FLAGS[0].add_to(p)
    FLAGS[2].add_to(p.add_argument_group(
        "several processes (jax.distributed; see the README's multi-host section)"))


def command_config(args) -> EditCommand:
    """The :class:`EditCommand` of ``args`` (range errors name the flag)."""
    return FLAGS[1].build(args)


def add_clip_metrics(args) -> dict | None:
    """IN2N's CLIP metrics of the final snapshot, merged into ``RUN_DIR/metrics.json``."""
    import json

    from jaxedit import DataError
    from jaxedit.io.files import atomic_write_text

    from .clip_metrics import clip_metrics_of_run

    if args.clip_weights is None:
        return None
    if not (args.caption_orig and args.caption_edit):
        raise DataError("--clip-weights", "needs --caption-orig and --caption-edit")
    clip = clip_metrics_of_run(args.out, clip_weights=args.clip_weights,
                               caption_orig=args.caption_orig, caption_edit=args.caption_edit,
                               device=args.ip2p_device)
    path = args.out / "metrics.json"
    metrics = json.loads(path.read_text())
    metrics["clip"] = clip
    atomic_write_text(path, json.dumps(metrics, indent=2) + "\n")
    return clip


def mode_defaults(mode: str):
    """The :class:`jaxedit.pipelines.edit_run.EditRunConfig` the command runs for ``--mode``
    without other flags: the mode's preset (:mod:`jaxedit.pipelines.presets`)."""
    from jaxedit.pipelines.presets import preset

    base = preset(mode)
    return EditSettings(**{f.name: getattr(base, f.name) for f in dataclasses.fields(base)}
                        | {"editor": dataclasses.replace(base.editor, kind=DEFAULT_EDITOR)})


def run_config(args):
    """The :class:`jaxedit.pipelines.edit_run.EditRunConfig` of ``args``: the flags given over
    ``--preset``'s tree, else ``--mode``'s (:func:`mode_defaults`; DataErrors name its fields)."""
    base = mode_defaults(args.preset or args.mode)
    return FLAGS[0].build(args, bases={f.name: getattr(base, f.name)
                                       for f in dataclasses.fields(base)})


def config_tree_json(tree) -> str:
    """``tree`` as the JSON ``--config`` reads back: nested tables of settings by field
    (without the fields another flag sets)."""
    import json

    from .configfiles import jsonable

    out = jsonable(dataclasses.asdict(tree))
    for path in FLAGS[0].derived:
        *parents, leaf = path.split(".")
        node = out
        for part in parents:
            node = node[part]
        node.pop(leaf)
    return json.dumps(out, indent=2)


def moved_postfix(records) -> dict:
    """The progress line's figures of the last finished subtask: how far its snapshot moved
    from the input scene (PSNR, LPIPS of the held-out renders; Gaussians against the input's)."""
    m = (records[-1].get("metrics") or {}) if records else {}
    if m.get("psnr_vs_input") is None:
        return {}
    return {"last": records[-1]["name"], "vs_input": f"{m['psnr_vs_input']:.1f}dB",
            "lpips": f"{m['lpips_vs_input']:.3f}",
            "gaussians": f"{m['num_gaussians']}/{m['input_gaussians']}"}


def progress_callback(quiet: bool):
    """A progress(spec, step, loss, state) that drives nested bars (overall + subtask).

    The subtask loop calls it after each chunk of steps with the subtask's step count so far.
    """
    from experiments.progress import Progress, configure

    configure(quiet=quiet)
    bars: dict = {}

    def progress(spec, step, loss, st):
        if "root" not in bars:
            bars["root"] = Progress(None, "edit")
        if bars.get("spec") != spec.index:
            if "child" in bars:
                bars["child"].close()
                bars["root"].update(1, **moved_postfix(st.records))
            bars["child"] = bars["root"].child(None, f"{spec.name} r{spec.ratio:.3f}")
            bars["spec"], bars["step"] = spec.index, 0
        # Called once per chunk of steps: advance by the steps it took.
        bars["child"].update(max(step - bars["step"], 0), loss=f"{loss:.4f}")
        bars["step"] = step

    def close():
        for k in ("child", "root"):
            if k in bars:
                bars[k].close()

    progress.close = close
    return progress


def check_processes(args, run_cfg) -> None:
    """Refuse what a multi-process edit cannot do: every process must run the same steps
    (no --async, whose edits depend on timing) from the same state (no resuming: only
    process 0 has the run directory)."""
    from jaxedit import DataError
    from jaxedit.parallel.distributed import process_count

    if process_count() == 1:
        return
    if run_cfg.plan.asynchronous:
        raise DataError("--async", "not with several processes: their edits would depend on "
                                   "timing and the processes' scenes drift apart; use --sync")
    for flag, value in (("--resume", args.resume), ("--resume-from", args.resume_from),
                        ("--view", args.view), ("--clip-weights", args.clip_weights)):
        if value:
            raise DataError(flag, "not with several processes yet (one process only)")


def steering(args) -> str | None:
    """Which steering operation ``args`` asks for (None: an ordinary edit)."""
    if args.stop:
        return "stop"
    if args.tree:
        return "tree"
    if args.from_node is not None or args.refine or args.extend is not None:
        return "branch"
    if args.branch not in (None, "main"):
        return "resume"
    return None


def out_use(args) -> str:
    """How the command uses --out (experiments/cli.py): --stop and --tree only signal or
    read a run; a branch holds the run's lock and keeps its config.json."""
    kind = steering(args)
    return "signal" if kind in ("stop", "tree") else "branch" if kind else "run"


#: Flags of a recorded command line that are actions of that one command, not settings.
_ACTIONS = {"--resume", "--select-only", "--view", "--print-config", "--refine", "--stop",
            "--tree"}
_ACTIONS_WITH_VALUE = {"--resume-from", "--select", "--view-port", "--from", "--ratio",
                       "--extend", "--name", "--branch"}


def recorded_settings(out: Path) -> list[str]:
    """The run's recorded command line (``config.json``) without its actions."""
    import json

    from jaxedit import DataError

    path = out / "config.json"
    try:
        argv = [str(a) for a in json.loads(path.read_text())["argv"]]
    except FileNotFoundError:
        raise DataError(path, "no config.json: not a run directory of `edit`") from None
    except (ValueError, KeyError, TypeError) as e:
        raise DataError(path, f"malformed run record ({e})") from None
    kept, skip = [], False
    for token in argv[1:]:
        name = token.split("=", 1)[0]
        if skip:
            skip = False
        elif name in _ACTIONS:
            continue
        elif name in _ACTIONS_WITH_VALUE:
            skip = "=" not in token
        else:
            kept.append(token)
    return kept


class Preloaded:
    """What steering commands read before their branch (the views, the input scene, the
    editor, the difficulty distance), kept between the commands of one process while the
    files and settings they were read with stay the same: the viewer's warm worker
    (:mod:`experiments.steer_worker`). A command line makes a new, empty one."""

    def __init__(self):
        self._kept: dict[str, tuple] = {}

    def get(self, kind: str, key, make: Callable):
        """``make()``, or what it gave for ``kind`` last time if ``key`` is the same."""
        kept = self._kept.get(kind)
        if kept is None or kept[0] != key:
            self._kept.pop(kind, None)  # the old one goes before the new one is read
            kept = self._kept[kind] = (key, make())
        return kept[1]


def _stamp(path) -> tuple:
    """What says a file (a dataset folder: its transforms.json) changed."""
    path = Path(path)
    path = path / "transforms.json" if path.is_dir() else path
    try:
        st = path.stat()
    except OSError:
        return (str(path),)
    return (str(path), st.st_mtime_ns, st.st_size)


def steering_inputs(out: Path, merged, run_cfg, preloaded: Preloaded) -> tuple:
    """(views, input scene, editor, difficulty distance) of a steering command on run ``out``."""
    from jaxedit.edit.difficulty import default_distance
    from jaxedit.pipelines.edit_run import load_inputs

    from .editors import make_editor

    scene = merged.scene if merged.scene is not None and Path(merged.scene).is_file() \
        else out / "original" / "scene.ply"
    reads = {f.name: getattr(run_cfg, f.name) for f in dataclasses.fields(run_cfg)
             if f.name != "plan"}  # branches change the plan only
    data, input_scene = preloaded.get(
        "inputs", (_stamp(merged.data), _stamp(scene), repr(reads)),
        lambda: load_inputs(run_cfg, merged.data, scene, editor_loaded=False))
    editor = preloaded.get("editor", repr(run_cfg.editor), lambda: make_editor(run_cfg.editor))
    distance = preloaded.get("distance", (run_cfg.distance, str(run_cfg.lpips_weights)),
                             lambda: default_distance(run_cfg.distance, run_cfg.lpips_weights))
    return data, input_scene, editor, distance


def recorded_run(out: Path):
    """(the run's recorded flags as parsed, their EditRunConfig)."""
    from .cli import parse

    merged = parse(["edit", *recorded_settings(out), "--out", str(out)])
    return merged, run_config(merged)


def warm_steering(out: Path, preloaded: Preloaded) -> bool:
    """Read run ``out``'s inputs into ``preloaded`` and prepare a refine in memory
    (:func:`jaxedit.pipelines.steer_run.warm_up`): the warm worker's start."""
    from jaxedit.pipelines import steer_run

    merged, run_cfg = recorded_run(out)
    data, input_scene, editor, distance = steering_inputs(out, merged, run_cfg, preloaded)
    return steer_run.warm_up(editor, run_cfg, data, input_scene, out, distance=distance)


def run_steering(args, kind: str) -> dict:
    """--stop, --tree, a new branch or a branch's --resume on the run in --out."""
    from jaxedit import DataError
    from jaxedit.edit.steer import parse_node
    from jaxedit.pipelines import steer_run
    from jaxedit.pipelines.report import write_report

    from .cli import parse
    from .export import export_selected

    if kind == "tree":
        print(steer_run.format_tree(args.out), flush=True)
        return {}
    if kind == "stop":
        return {"stop_requested": str(steer_run.request_stop(args.out))}
    steer_run.read_control(args.out)  # a garbled request: one line before anything
    # a valid one is stale: we hold the lock
    (args.out / steer_run.CONTROL_NAME).unlink(missing_ok=True)
    given = {token.split("=", 1)[0][2:].replace("-", "_") for token in args._argv
             if token.startswith("--")}  # what this command line changes
    merged = parse(["edit", *recorded_settings(args.out), *args._argv[1:]])
    if merged.local != "off" or merged.region or merged.masks is not None:
        raise DataError("--from", "branches of a local edit are not supported yet")
    run_cfg = run_config(merged)
    tree = steer_run.read_tree(args.out)
    if kind == "resume":
        if not args.resume:
            raise DataError("--branch", "names the branch --resume continues; add --resume")
        branch = tree.get(args.branch)
    else:
        if args.resume:
            raise DataError("--resume", "continues a branch (--branch NAME), not with --from")
        if args.refine and args.extend is not None:
            raise DataError("--refine", "either --refine or --extend")
        if args.ratio is not None and not args.refine:
            raise DataError("--ratio", "is --refine's split; add --refine")
        op = "refine" if args.refine else "extend" if args.extend is not None else "branch"
        settings = {"argv": list(args._argv), "ratio": args.ratio, "r_max": args.extend}
        for key in ("threshold", "target_subtasks", "guidance"):
            if key in given:
                settings[key] = getattr(merged, key)
        if op == "branch" and not given & {"prompt", "seed", "threshold", "target_subtasks",
                                           "guidance"}:
            raise DataError("--from", "a branch changes something: give --prompt, --seed, "
                                      "--threshold, --target-subtasks or --guidance (or "
                                      "--refine / --extend)")
        node = parse_node(args.from_node if args.from_node is not None else "-1")
        branch = steer_run.plan_branch(args.out, tree, op, node, name=args.name,
                                   prompt=args.prompt if "prompt" in given else None,
                                   seed=merged.seed, settings=settings)
    data, input_scene, editor, distance = steering_inputs(
        args.out, merged, run_cfg, getattr(args, "_preloaded", None) or Preloaded())
    log = (lambda m: None) if args.quiet else (lambda m: print(m, flush=True))
    log(f"{branch.op} {branch.name} from {branch.parent}")
    progress = progress_callback(args.quiet)
    try:
        out = steer_run.run_branch(editor, run_cfg, data, input_scene, args.out, branch,
                               distance=distance, resume=args.resume,
                               stop=steer_run.stop_requested(args.out, log),
                               progress=progress, log=log)
    finally:
        progress.close()
    records = out["schedule"]["subtasks"]
    folder = steer_run.branch_dir(args.out, branch.name)
    if merged.clip_weights is not None and not out["stopped"]:
        branch_clip_metrics(merged, args.out, folder, records)
    if not args.no_report:
        write_report(args.out)
    exported = ([] if out["stopped"] else
                export_selected(args.out, command_config(args).export, f"{branch.name}:-1", log))
    return {"exported": exported, "branch": branch.name, "op": branch.op, "parent": str(branch.parent),
            "stopped": out["stopped"], "run_dir": str(steer_run.branch_dir(args.out, branch.name)),
            "subtasks": [{"index": r["index"], "ratio": r["ratio"], "kind": r["kind"],
                          "difficulty": r["difficulty"], "done": bool(r.get("snapshot"))}
                         for r in records]}


def branch_clip_metrics(merged, run_dir: Path, folder: Path, records) -> dict:
    """IN2N's CLIP metrics of a branch's last snapshot against the run's original views,
    merged into the branch's metrics.json."""
    import json

    from jaxedit.io.files import atomic_write_text

    from .clip_metrics import clip_metrics_of_run

    if not (merged.caption_orig and merged.caption_edit):
        from jaxedit import DataError

        raise DataError("--clip-weights", "needs --caption-orig and --caption-edit")
    last = (folder / records[-1]["snapshot"]).parent
    clip = clip_metrics_of_run(run_dir, snapshot=last, clip_weights=merged.clip_weights,
                               caption_orig=merged.caption_orig,
                               caption_edit=merged.caption_edit, device=merged.ip2p_device)
    path = folder / "metrics.json"
    atomic_write_text(path, json.dumps(json.loads(path.read_text()) | {"clip": clip},
                                       indent=2) + "\n")
    return clip


def after_release(args) -> None:
    """``--view`` once the edit is over and the run's lock released (experiments/cli.py):
    the viewer and its watcher go on until Ctrl-C, and its refine / branch / extend
    buttons can take the run."""
    view = getattr(args, "_view", None)
    if view is None:
        return
    watcher, what = view
    watcher.viewer.edit_over(what)
    watcher.viewer.warm_up()
    print(f"{what}; the viewer keeps serving {watcher.viewer.url} (Ctrl-C to stop)", flush=True)
    watcher.serve_forever()


def run(args) -> dict:
    from jaxedit import DataError
    from jaxedit.parallel.distributed import split_edits
    from jaxedit.pipelines import select_snapshot
    from jaxedit.pipelines.edit_run import edit_files

    from .rundirs import writes
    from .editors import make_editor
    from .export import export_selected

    if args.print_config:
        print(config_tree_json(run_config(args)))
        return {}
    if args.out is None:
        raise DataError("--out", "required (the run directory)")
    exports = command_config(args).export
    kind = steering(args)
    if kind is not None:
        return run_steering(args, kind)
    log = (lambda m: None) if args.quiet else (lambda m: print(m, flush=True))
    if args.select_only and not writes(args):
        return {}
    if args.select_only:
        if args.select is None:
            raise DataError("--select", "required with --select-only")
        path = select_snapshot(args.out, args.select)
        return {"selected": str(path), "exported": export_selected(args.out, exports, args.select, log)}
    run_cfg = run_config(args)
    if args.resume and args.resume_from is not None:
        raise DataError("--resume", "use either --resume (same run) or --resume-from (a snapshot)")
    if args.clip_weights is not None and not (args.caption_orig and args.caption_edit):
        raise DataError("--clip-weights", "needs --caption-orig and --caption-edit")
    check_processes(args, run_cfg)
    # Views due at once are split over the processes.
    editor = split_edits(make_editor(run_cfg.editor))
    if not args.prompt and args.mode != "in2n":
        raise DataError("--prompt", "required (the editing instruction)")
    if args.data is None:
        raise DataError("--data", "required (a nerfstudio dataset folder)")
    if args.scene is None:
        raise DataError("--scene", "required (the input 3DGS .ply)")
    from .local_flags import local_spec

    watcher = None
    if args.view:
        from .view import watch_edit

        watcher = watch_edit(args.out, port=args.view_port)
    from jaxedit.pipelines import steer_run

    progress = progress_callback(args.quiet)
    if watcher is not None:  # the running subtask in the viewer's panel too
        progress = watcher.viewer.following(progress)
    stop = None
    if writes(args):
        # garbled: one line; a valid one is stale (we hold the lock)
        steer_run.read_control(args.out)
        (args.out / steer_run.CONTROL_NAME).unlink(missing_ok=True)
        stop = steer_run.stop_requested(args.out, log)
    try:
        out = edit_files(run_cfg, args.prompt or "", args.data, args.scene, editor=editor,
                         stop=stop,
                         local=lambda data: local_spec(args, run_cfg, data), seed=args.seed,
                         run_dir=args.out if writes(args) else None, resume=args.resume,
                         resume_from=args.resume_from,
                         select=args.select if writes(args) else None, progress=progress,
                         report=not args.no_report, log=log)
    finally:
        progress.close()
        if watcher is not None:
            watcher.stop()
    m = out["metrics"]
    if not writes(args):
        return {}
    if out["stopped"]:
        done = sum(1 for r in out["schedule"]["subtasks"] if r.get("snapshot"))
        print(f"stopped after {done} of {len(out['schedule']['subtasks'])} subtasks; "
              f"--resume goes on", flush=True)
        args._view = None if watcher is None else (watcher, "edit stopped")
        return {"stopped": True, "run_dir": str(args.out)}
    clip = add_clip_metrics(args)
    if clip is not None:
        m = m | {"clip_direction_similarity": clip.get("direction_similarity"),
                 "clip_direction_consistency": clip.get("direction_consistency")}
    keys = ("psnr_vs_target", "ssim_vs_target", "multiview_consistency", "edit_fit_psnr",
            "num_gaussians", "wall_time_s", "subtasks", "all_converged",
            "clip_direction_similarity", "clip_direction_consistency")
    exported = export_selected(args.out, exports, args.select, log)
    args._view = None if watcher is None else (watcher, "edit finished")
    return {k: m.get(k) for k in keys} | {"run_dir": str(args.out), "exported": exported}
