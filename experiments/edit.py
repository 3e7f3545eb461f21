"""``python -m experiments edit``: progressive instruction-guided editing of a 3DGS scene (ProEdit).

Writes into ``--out`` RUN_DIR: ``schedule.json`` (updated after every subtask, so a
run can be previewed while it works), ``metrics.json``, ``original/`` and
``subtasks/NN_rX.XXX/`` snapshots (scene.ply, renders, depth, metrics), a resumable
``checkpoint.npz`` and ``report.html``. ``--select R`` points ``selected.ply``
at a snapshot (also on a finished run with ``--select-only``); ``--resume``
continues a crashed run; ``--resume-from SNAPSHOT_DIR`` continues from any
snapshot with another schedule (more or fewer subtasks, another threshold).
``--view`` serves the scene in the browser while it is edited (``experiments/view.py``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "progressively edit a 3DGS scene with an instruction (ProEdit)"


#: Library arguments named unlike their flags (for error messages).
FIELD_FLAGS = {"run_dir": "--out", "batch": "--ip2p-batch"}

def _config_flags():
    from jaxedit.edit.plan import MODES
    from jaxedit.pipelines.edit import EditRunConfig

    from .flags import Flag, FlagSet

    return FlagSet(EditRunConfig, (
        Flag("plan.mode", choices=MODES),
        Flag("plan.threshold"),
        Flag("plan.target_subtasks"),
        Flag("plan.subtasks"),
        Flag("plan.difficulty_views"),
        Flag("train.densify.max_gaussians"),
        Flag("plan.schedule_method", choices=("bisect", "root")),
        Flag("plan.refine_first", off="--no-refine-first"),
        Flag("plan.consolidate", off="--no-consolidate"),
        Flag("plan.asynchronous", "--async", off="--sync", key="asynchronous"),
        Flag("downscale"),
        Flag("plan.warmup"),
        Flag("plan.patience"),
        Flag("plan.max_steps"),
        Flag("plan.max_seconds", "--max-subtask-seconds"),
        Flag("plan.edit_every"),
        Flag("plan.turntable_frames"),
        Flag("test_views"),
    ))


def _flag_sets():
    from .cli import distributed_flags

    return _config_flags(), distributed_flags()


#: The command's settings' flags, generated from :class:`jaxedit.pipelines.edit.EditRunConfig`,
#: and the multi-process run's (:class:`jaxedit.parallel.distributed.DistributedConfig`).
FLAGS = _flag_sets()


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", type=Path, help="nerfstudio dataset folder (the scene's photos)")
    p.add_argument("--scene", type=Path, help="input 3DGS .ply (a reconstruction of --data)")
    p.add_argument("--prompt", default=None, help="the editing instruction")
    p.add_argument("--editor", default="simulated", choices=["simulated", "ip2p", "ip2p-torch"],
                   help="2D editor (simulated: offline test instrument; ip2p: InstructPix2Pix "
                        "in JAX, the small model bundled with jaxedit unless --ip2p-weights; "
                        "ip2p-torch: the torch + diffusers reference)")
    p.add_argument("--ip2p-weights", type=Path, default=None,
                   help="local diffusers folder of the InstructPix2Pix weights (--editor ip2p, "
                        "ip2p-torch; default: the bundled small model)")
    FLAGS[0].add_to(p)
    FLAGS[1].add_to(p.add_argument_group(
        "several processes (jax.distributed; see the README's multi-host section)"))
    p.add_argument("--select", default=None,
                   help="subtask index (int) or ratio (float) to export as selected.ply")
    p.add_argument("--select-only", action="store_true",
                   help="only (re)select a snapshot of the finished run in --out")
    p.add_argument("--resume", action="store_true",
                   help="continue the interrupted run in --out from its checkpoint")
    p.add_argument("--resume-from", type=Path, default=None,
                   help="snapshot dir (RUN/subtasks/NN_rX.XXX) to continue from, new schedule")
    p.add_argument("--no-report", action="store_true", help="skip report.html")
    p.add_argument("--view", action="store_true",
                   help="serve the scene in the browser while it is edited (viser; see `view`)")
    p.add_argument("--view-port", type=int, default=8080, help="port of --view on 127.0.0.1")
    real = p.add_argument_group("real models (local weights, see the README)")
    real.add_argument("--ip2p-device", default=None,
                      help="torch device of --editor ip2p-torch (default cuda:0, else cpu); the "
                           "JAX editor runs on the editor's JAX device (the second if any)")
    real.add_argument("--ip2p-dtype", default=None,
                      help="networks' dtype (default float32 on the CPU; bfloat16 (JAX) or "
                           "float16 (torch) on accelerators)")
    real.add_argument("--ip2p-size", type=int, default=None,
                      help="IP2P working resolution (px; default: the bundled editor's 64, "
                           "512 for other weights)")
    from jaxedit.editors.diffusion import DDIM_STEPS

    real.add_argument("--ip2p-steps", type=int, default=DDIM_STEPS,
                      help="DDIM steps per IP2P edit (default %(default)s)")
    real.add_argument("--ip2p-batch", type=int, default=None,
                      help="--editor ip2p: most views per editor call when several are due at "
                           "once (a subtask's initial sweep, the difficulty's views); default 8 "
                           "per accelerator, 1 on the CPU")
    real.add_argument("--distance", default="auto", choices=["auto", "lpips", "ms-ssim"],
                      help="difficulty distance; auto/lpips (default): LPIPS as in the paper, "
                           "with the bundled AlexNet weights or --lpips-weights; ms-ssim")
    real.add_argument("--lpips-weights", type=Path, default=None,
                      help="LPIPS .safetensors/.npz written by convert-lpips (e.g. --net vgg); "
                           "default: the bundled LPIPS-AlexNet")
    real.add_argument("--clip-weights", default=None,
                      help="transformers CLIP folder: add IN2N's CLIP metrics to metrics.json")
    real.add_argument("--caption-orig", default=None, help="caption of the original (CLIP metrics)")
    real.add_argument("--caption-edit", default=None, help="caption of the edit (CLIP metrics)")
    from .local_flags import add_local_arguments  # issue 35: --local, --region, --masks

    add_local_arguments(p)


def make_editor(args):
    from jaxedit import DataError

    if args.editor == "simulated":
        from jaxedit.editors.simulated import SimulatedEditor

        return SimulatedEditor()
    from jaxedit.editors import bundled_editor, native_size

    # Without --ip2p-weights: the small InstructPix2Pix shipped in the package.
    weights = args.ip2p_weights or bundled_editor()
    size = args.ip2p_size or native_size(weights)
    if args.editor == "ip2p":
        from jaxedit.edit.buffer import pick_devices
        from jaxedit.editors.jax_ip2p import load_editor

        # The editor's device of pick_devices, the one run_edit gives the editor.
        return load_editor(weights, devices=[pick_devices()[1]], dtype=args.ip2p_dtype,
                           size=size, steps=args.ip2p_steps, batch=args.ip2p_batch)
    try:
        from jaxedit.editors.ip2p import load_editor
    except ImportError as e:  # torch / diffusers are optional extras
        raise DataError("--editor", f"ip2p-torch is unavailable ({e})") from None
    return load_editor(weights, device=args.ip2p_device, dtype=args.ip2p_dtype, size=size,
                       steps=args.ip2p_steps)


def make_distance(args):
    """The difficulty's perceptual distance (--distance, --lpips-weights): LPIPS with the
    bundled AlexNet or the given weights, or MS-SSIM when asked for."""
    from jaxedit.edit.difficulty import default_distance

    return default_distance(args.distance, args.lpips_weights)


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


def load_inputs(args, config):
    """(EditData, input Gaussians) from --data and --scene, read as ``config`` (an
    EditRunConfig) says, with one-line errors."""
    import numpy as np

    from jaxedit import DataError
    from jaxedit.edit import EditData
    from jaxedit.io import load_nerfstudio, load_ply

    if args.data is None:
        raise DataError("--data", "required (a nerfstudio dataset folder)")
    if args.scene is None:
        raise DataError("--scene", "required (the input 3DGS .ply)")
    from jaxedit.pipelines.reconstruct import check_image_size

    dataset = load_nerfstudio(args.data, downscale=config.downscale)
    check_image_size(dataset, args.data)
    scene = load_ply(args.scene)
    if not np.asarray(scene.alive).any():
        raise DataError(args.scene, "has no Gaussians (zero vertices): nothing to edit")
    data = EditData.from_dataset(dataset)
    if config.test_views is not None and len(data.test_images) > config.test_views:
        keep = np.linspace(0, len(data.test_images) - 1, config.test_views).round().astype(int)
        data = EditData.create(data.train_images, data.train_cameras, data.test_images[keep],
                               data.test_cameras[keep])
    return data, scene


def run_config(args):
    """The :class:`jaxedit.pipelines.edit.EditRunConfig` of ``args``: the flags given over
    ``--mode``'s defaults (DataErrors name its fields)."""
    from jaxedit.edit import ProEditConfig

    return FLAGS[0].build(args, bases={"plan": ProEditConfig.for_mode(args.mode)})


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
                bars["root"].update(1)
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


def check_counts(args) -> None:
    """The editor's counts in range (the config tree's are checked as it is built)."""
    from .cli import check_minimums

    check_minimums(args, {"ip2p_size": 8, "ip2p_steps": 1, "ip2p_batch": 1})


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


def run(args) -> dict:
    from jaxedit import DataError
    from jaxedit.parallel.distributed import split_edits
    from jaxedit.pipelines import run_edit, select_snapshot

    from .cli import writes

    if args.out is None:
        raise DataError("--out", "required (the run directory)")
    if args.select_only and not writes(args):
        return {}
    if args.select_only:
        if args.select is None:
            raise DataError("--select", "required with --select-only")
        path = select_snapshot(args.out, args.select)
        return {"selected": str(path)}
    check_counts(args)
    run_cfg = run_config(args)
    if args.resume and args.resume_from is not None:
        raise DataError("--resume", "use either --resume (same run) or --resume-from (a snapshot)")
    if args.ip2p_weights is not None and not args.editor.startswith("ip2p"):
        raise DataError("--ip2p-weights", f"used only with --editor ip2p or ip2p-torch (the "
                                          f"editor is {args.editor})")
    if args.clip_weights is not None and not (args.caption_orig and args.caption_edit):
        raise DataError("--clip-weights", "needs --caption-orig and --caption-edit")
    check_processes(args, run_cfg)
    editor = split_edits(make_editor(args))  # views due at once: split over the processes
    distance = make_distance(args)
    if not args.prompt and args.mode != "in2n":
        raise DataError("--prompt", "required (the editing instruction)")
    data, scene = load_inputs(args, run_cfg)
    from .local_flags import local_spec

    local = local_spec(args, run_cfg, data)
    config, settings = run_cfg.plan, run_cfg.train
    watcher = None
    if args.view:
        from .view import check_port, watch_edit

        watcher = watch_edit(args.out, port=check_port(args.view_port, "--view-port"))
    progress = progress_callback(args.quiet)
    log = (lambda m: None) if args.quiet else (lambda m: print(m, flush=True))
    try:
        out = run_edit(editor, args.prompt or "", data, scene, config=config, settings=settings,
                       seed=args.seed, run_dir=args.out if writes(args) else None,
                       resume=args.resume, resume_from=args.resume_from,
                       select=args.select if writes(args) else None, progress=progress,
                       report=not args.no_report, log=log, distance=distance, local=local)
    finally:
        progress.close()
        if watcher is not None:
            watcher.stop()
    m = out["metrics"]
    if not writes(args):
        return {}
    clip = add_clip_metrics(args)
    if clip is not None:
        m = m | {"clip_direction_similarity": clip.get("direction_similarity"),
                 "clip_direction_consistency": clip.get("direction_consistency")}
    keys = ("psnr_vs_target", "ssim_vs_target", "multiview_consistency", "edit_fit_psnr",
            "num_gaussians", "wall_time_s", "subtasks", "all_converged",
            "clip_direction_similarity", "clip_direction_consistency")
    if watcher is not None:
        print(f"edit finished; the viewer keeps serving {watcher.viewer.url} (Ctrl-C to stop)",
              flush=True)
        watcher.viewer.serve_forever()
        watcher.viewer.close()
    return {k: m.get(k) for k in keys} | {"run_dir": str(args.out)}
