"""The ProEdit driver: progressive editing through a schedule of subtasks.

Paper sections 3.2-3.3 and appendices B, D. The scene goes through

    s_in --r_0 (refine, e(0))--> s_0 --r_1--> s_1 ... --r_n--> s_n --consolidate (e(1))--> s_out

where every arrow is one *subtask*: a seeded, resumable transformation of the
training state. A subtask with ratio r:

1. sets every Gaussian's opacity to the cull threshold and trains ``warmup``
   steps without densify/cull, so Gaussians on the right surface earn opacity
   and wrong ones are culled at the next maintenance (paper 3.3 (1));
2. runs the iterative dataset update: edited views of the *current* renders
   (``image`` = current render, ``original`` = original photo, embedding
   e(r) = r E(p) + (1 - r) E("")) replace the training images as they arrive
   from an edit source (:mod:`jaxedit.edit.buffer`: deterministic inline or a
   producer thread); the SDEdit timestep follows HiFA's annealing
   t(i) = t_max - (t_max - t_min) sqrt(i / N) within the subtask, N half the
   room under the step guard (:func:`plan.anneal_horizon`);
3. trains with the budgeted adaptive density control (paper 3.3 (2), app. D)
   under a hard cap (default twice the input's Gaussians; a warning with
   figures whenever the cap, not t(n), limited creation);
4. ends when the running mean of the training loss has not decreased for
   ``patience`` steps after every view was edited at least once and after an
   edit at t_min arrived, or when a guard fires (``max_steps``, scaled with the
   scene by :func:`plan.subtask_guard`, or ``max_seconds``; recorded as
   ``converged: False`` and the guard's name).

Modes (rows of the paper's tables): ``proedit`` (difficulty-aware schedule),
``nd`` (no decomposition: one edit subtask 0 -> 1, with the same r_0 / r_n and
adaptive 3DGS, the paper's ablation), ``in2n`` (Instruct-NeRF2NeRF on 3DGS: one
subtask at r = 1, no opacity reset, classic densify thresholds, one view edited
every 10 steps with timesteps drawn from 0.02-0.98, a fixed number of steps).

Everything random is derived from one key with ``fold_in`` of (subtask index,
purpose, step), so the deterministic mode reproduces bits, and a run resumed
from the checkpoint written inside any subtask ends with the same bits as an
uninterrupted run.

Modules, one per concept: :mod:`.plan` (configuration and subtasks),
:mod:`.schedule` (the difficulty-aware scheduler, 3.2), :mod:`.driver` (one
subtask as a state machine of pure parts, 3.3), :mod:`.trainer` (the editing
trainer's settings), :mod:`.checkpoint` (the resumable state on disk) and
:mod:`.outputs` (snapshots, metrics, the selection). This module runs a whole
edit with its run directory: the side effects (files, threads, progress) stay here
and in the driver's edge.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from pathlib import Path
from typing import Callable

import jax
import numpy as np

from ..errors import DataError
from ..io.files import atomic_write_text
from .buffer import pick_devices
# Re-exported: the names the CLI, the tests and users import from here.
from .checkpoint import CHECKPOINT_NAME, load_checkpoint, save_checkpoint  # noqa: F401
from .difficulty import DIFFICULTY_VIEWS, difficulty_view_subset  # noqa: F401
from .driver import (CHUNK, DriverState, EditContext, EditData, LossTracker,  # noqa: F401
                     apply_edits, begin_subtask, finish_subtask, init_state, make_edit_fn,
                     run_subtask, step_chunk, track_loss, train_view)
from .outputs import (Renderer, image_scores, reprojection_consistency,  # noqa: F401
                      scene_metrics, select_snapshot, snapshot_ratio, write_scene_snapshot)
from .plan import MODES, ProEditConfig, SubtaskSpec, anneal_timestep, plan_subtasks  # noqa: F401
from .trainer import (CAP_MIN_ROOM, SubtaskTrainer, TrainSettings,  # noqa: F401
                      default_max_gaussians, resolve_max_gaussians)


# ---------------------------------------------------------------------------
# Schedules
# ---------------------------------------------------------------------------
DEFAULT_SUBTASKS = 4  # default threshold = d(0, 1) / 4 (paper: ~4 subtasks for texture edits)
DIFFICULTY_VIEWS_DEFAULT_MAX = DIFFICULTY_VIEWS  # the earlier name


def difficulty_oracle(ctx: EditContext, originals: np.ndarray, seed: int, distance=None):
    """The memoised d(r_a, r_b) over the difficulty views' renders of the input scene.

    ``distance``: the perceptual distance (e.g. :func:`jaxedit.lpips.lpips_distance`);
    None is the oracle's default (multi-scale SSIM). The reduction over views is the
    oracle's default, the mean (eq. 3's sum / |V|), so thresholds are per view.
    """
    from .difficulty import DifficultyOracle

    views = difficulty_view_subset(len(originals), ctx.config.difficulty_views, ctx.key)
    return DifficultyOracle(ctx.editor, originals, ctx.prompt, views=views, distance=distance,
                            guidance=tuple(ctx.config.guidance), seed=seed)


def distance_name(distance) -> str:
    """What schedule.json and the log call a difficulty distance."""
    from .difficulty import ms_ssim_distance

    distance = ms_ssim_distance if distance is None else distance
    return getattr(distance, "name", getattr(distance, "__name__", type(distance).__name__))


def make_schedule(ctx: EditContext, oracle, *, start_ratio: float = 0.0):
    """(Schedule, plan ratios from ``start_ratio``, their difficulties) per the config."""
    from . import schedule as sched

    cfg = ctx.config
    if cfg.mode == "nd":
        s = sched.uniform(1, oracle)
        if cfg.nd_subtasks > 1 and start_ratio == 0.0:  # ND-k: the same edit k times
            return s, [0.0] + [1.0] * cfg.nd_subtasks, [s.difficulties[0]] + [0.0] * (
                cfg.nd_subtasks - 1)
    elif cfg.mode == "in2n":
        s = sched.uniform(1, None)
    elif cfg.subtasks is not None:
        s = sched.uniform(cfg.subtasks, oracle)
    elif cfg.threshold is None and cfg.target_subtasks is not None:
        method = sched.decompose_root if cfg.schedule_method == "root" else sched.decompose
        kwargs = {} if cfg.schedule_method == "root" else {"max_depth": cfg.max_depth}
        s = sched.for_target_subtasks(oracle, cfg.target_subtasks, method=method, **kwargs)
    else:
        # No threshold given: a quarter of the whole task's difficulty, i.e. about the
        # paper's ~4 subtasks for texture edits (more where d(0, r) is uneven).
        threshold = (cfg.threshold if cfg.threshold is not None
                     else max(oracle(0.0, 1.0) / DEFAULT_SUBTASKS, 1e-6))
        method = sched.decompose_root if cfg.schedule_method == "root" else sched.decompose
        kwargs = {} if cfg.schedule_method == "root" else {"max_depth": cfg.max_depth}
        s = method(oracle, threshold=threshold, **kwargs)
    ratios = [start_ratio] + [r for r in s.ratios if r > start_ratio + 1e-9]
    if start_ratio > 0.0:
        diffs = [oracle(a, b) if oracle is not None else None for a, b in zip(ratios, ratios[1:])]
    else:
        diffs = [None if math.isnan(d) else float(d) for d in s.difficulties]
    return s, ratios, diffs


def edit_fit(ctx: EditContext, st: DriverState) -> float:
    """PSNR (dB) of the final renders against the last edited training images.

    How well one 3D scene explains all the edited views: low when the edits
    disagree across views (the multi-view inconsistency the scene had to average).
    """
    g = ctx.trainer.gaussians(st.train)
    rgb = np.stack([ctx.renderer.rgb(g, ctx.data.train_cameras[i])
                    for i in range(len(st.edited))])
    return image_scores(rgb, np.asarray(jax.device_get(st.images)))["psnr"]


# ---------------------------------------------------------------------------
# A whole run, with its run directory
# ---------------------------------------------------------------------------
def _plan_to_json(plan) -> list:
    return [dataclasses.asdict(p) for p in plan]


def _plan_from_json(items) -> tuple[SubtaskSpec, ...]:
    return tuple(SubtaskSpec(**p) for p in items)


def cap_warning(name: str, density: dict, cap: int, alive: int) -> str | None:
    """The warning of a subtask whose Gaussian creation the hard cap limited (None: it did not)."""
    if not density["cap_limited"]:
        return None
    return (f"WARNING: subtask {name}: the Gaussian cap ({cap}) limited creation in "
            f"{density['cap_limited']} of {density['refinements']} maintenance steps: "
            f"{density['shortfall']} Gaussians the budget t(n) wanted were not created "
            f"({density['created']} were; {alive} alive at the end). Raise the cap (max_gaussians) "
            f"to let the edit grow geometry")


def run_edit(editor, prompt: str, data: EditData, gaussians, *, config: ProEditConfig,
             settings: TrainSettings | None = None, seed: int = 0,
             run_dir: str | os.PathLike | None = None, resume: bool = False,
             resume_from: str | os.PathLike | None = None, select=None,
             callback: Callable | None = None, progress: Callable | None = None,
             report: bool = True, log: Callable[[str], None] | None = None,
             distance: Callable | None = None) -> dict:
    """Edit ``gaussians`` progressively (see the module docstring); returns the run summary.

    Args:
      editor, prompt: the 2D editor and the instruction.
      data: original photos and cameras (train views edited, test views held out).
      gaussians: the input scene (a reconstruction of ``data``).
      config / settings: driver and trainer knobs.
      seed: the run seed (every random draw derives from it).
      run_dir: where schedule.json, metrics.json, snapshots and the checkpoint go
        (None: in memory only, no files).
      resume: continue the run in ``run_dir`` from its checkpoint (exactly, in
        the deterministic mode).
      resume_from: a snapshot directory (``subtasks/NN_rX.XXX``) to continue from
        with this config's schedule (the ratios above the snapshot's).
      select: ratio (float) or subtask index (int) whose snapshot becomes
        ``run_dir/selected.ply``.
      callback: ``callback(spec, step, loss)`` after every training step.
      progress: ``progress(spec, step, loss, state)`` after every training step.
      distance: perceptual distance of the difficulty (default multi-scale SSIM; pass
        :func:`jaxedit.lpips.lpips_distance` for the paper's LPIPS).
    Returns:
      {"schedule": schedule.json contents, "metrics": metrics.json contents, "gaussians": final}.
    """
    log = log or (lambda msg: None)
    if not str(prompt).strip() and config.mode != "in2n":
        raise DataError("prompt", "empty instruction")
    run_dir = None if run_dir is None else Path(run_dir)
    from ..train import scene_extent

    settings = settings or TrainSettings()
    if settings.scene_extent is None:
        # Rounded: the extent is a static field of the train state, and cameras that went
        # through a file differ in the last bits; equal rigs should share one compiled step.
        extent = float(f"{scene_extent(data.train_cameras):.4g}")
        settings = dataclasses.replace(settings, scene_extent=extent)
    # The plan owns W, the mode and the background; the trainer runs with them.
    settings = dataclasses.replace(settings, adaptive=config.mode != "in2n"
                                   ).replace_densify(warmup=config.warmup)
    settings = resolve_max_gaussians(settings, int(gaussians.num_alive()))
    trainer = SubtaskTrainer(settings, background=config.background)
    trainer_device, editor_device = pick_devices()
    ctx = EditContext(editor, prompt, data, config, trainer, Renderer(config.background),
                      jax.random.key(seed), editor_device)
    wall0 = time.perf_counter()
    ckpt = None if run_dir is None else run_dir / CHECKPOINT_NAME
    if resume and (ckpt is None or not ckpt.exists()):
        raise DataError(ckpt or "run_dir", "no checkpoint to resume from")

    if resume:
        st, meta = load_checkpoint(ckpt, trainer.init(gaussians))
        plan = _plan_from_json(meta["plan"])
        header = meta["header"]
        wall0 -= meta.get("wall_time_s", 0.0)
        log(f"resuming subtask {st.subtask} at step {st.step} from {ckpt}")
    else:
        start_ratio, start_scene, images = 0.0, gaussians, None
        if resume_from is not None:
            from ..io import load_ply

            snap = Path(resume_from)
            start_ratio = snapshot_ratio(snap)
            start_scene = load_ply(snap / "scene.ply")
            # The dataset the snapshot was trained on is best approximated by its renders.
            images = np.stack([ctx.renderer.rgb(start_scene, data.train_cameras[i])
                               for i in range(len(data.train_images))])
            log(f"continuing from {snap} (r = {start_ratio:.3f})")
        originals = np.stack([ctx.renderer.rgb(gaussians, data.train_cameras[i])
                              for i in range(len(data.train_images))])
        oracle = (None if config.mode == "in2n"
                  else difficulty_oracle(ctx, originals, seed, distance))
        if oracle is not None:
            log(f"difficulty distance: {distance_name(distance)}")
        schedule, ratios, diffs = make_schedule(ctx, oracle, start_ratio=start_ratio)
        resumed = resume_from is not None
        if start_ratio >= 1.0 - 1e-9:
            ratios, diffs = [1.0], []
        plan = (plan_subtasks(config.mode, ratios, diffs, start_ratio=start_ratio,
                              refine_first=config.refine_first and not resumed,
                              consolidate=config.consolidate)
                if len(ratios) > 1 or config.mode == "in2n" else
                plan_subtasks("proedit", [0.0, 1.0], [None], refine_first=False,
                              consolidate=config.consolidate)[-1:])
        curve = []
        if oracle is not None:
            grid = np.linspace(0.0, 1.0, max(config.curve_points, 2))
            curve = [[r, d] for r, d in oracle.curve(sorted(set(map(float, grid)) | set(ratios)))]
        if schedule.depth_limit_hit:
            log(f"WARNING: the scheduler hit its depth limit (max_depth {config.max_depth}, at "
                f"most {2 ** config.max_depth} subtasks): some subtask is harder than the "
                f"threshold {schedule.threshold:.4g}")
        if schedule.target_subtasks is not None:
            log(f"threshold {schedule.threshold:.4g} gives {schedule.num_subtasks} subtasks "
                f"(target {schedule.target_subtasks})")
        header = {"prompt": prompt, "editor": getattr(editor, "name", type(editor).__name__),
                  "mode": config.mode, "threshold": schedule.threshold,
                  "target_subtasks": schedule.target_subtasks,
                  "difficulty": None if oracle is None else {
                      "distance": distance_name(distance),
                      "reduction": "mean over views (paper eq. 3's sum / |V|; the threshold "
                                   "is per view)",
                      "views": list(oracle.views), "num_views": len(oracle.views),
                      "of_training_views": len(data.train_images)},
                  "schedule_method": schedule.method, "depth_limit_hit": schedule.depth_limit_hit,
                  "difficulty_evaluations": schedule.evaluations,
                  "editor_calls_for_schedule": getattr(oracle, "editor_calls", 0),
                  "difficulty_curve": curve, "seed": seed,
                  "distance": None if oracle is None else distance_name(distance),
                  "resumed_from": None if resume_from is None else str(resume_from),
                  "start_ratio": start_ratio, "asynchronous": config.asynchronous,
                  "config": dataclasses.asdict(ctx.config),
                  "guard": {"max_steps": ctx.config.max_steps,
                            "max_steps_scaled": config.max_steps is None,
                            "max_seconds": ctx.config.max_seconds},
                  "max_gaussians": settings.densify.max_gaussians,
                  "input_gaussians": int(gaussians.num_alive())}
        st = init_state(ctx, start_scene, images)
        if run_dir is not None:
            write_scene_snapshot(ctx, run_dir / "original", gaussians, ratio=0.0)

    def schedule_json(records) -> dict:
        done = {r["index"] for r in records}
        pending = [{"index": p.index, "name": p.name, "ratio": p.ratio, "difficulty": p.difficulty,
                    "kind": p.kind, "steps": None, "seconds": None, "converged": None,
                    "snapshot": None} for p in plan if p.index not in done]
        return {**header, "subtasks": list(records) + pending}

    def meta() -> dict:
        return {"plan": _plan_to_json(plan), "header": header,
                "wall_time_s": time.perf_counter() - wall0}

    def save(state):
        if ckpt is not None:
            save_checkpoint(ckpt, state, meta())

    if run_dir is not None:
        atomic_write_text(run_dir / "schedule.json", json.dumps(schedule_json(st.records), indent=2) + "\n")
        save(st)

    if config.subtask_steps is not None and len(config.subtask_steps) != len(plan):
        raise DataError("subtask_steps", f"{len(config.subtask_steps)} lengths for a plan of "
                                         f"{len(plan)} subtasks")

    def context_of(spec):
        """The context a subtask runs in (a fixed length: its own step budget, no plateau)."""
        if config.subtask_steps is None:
            return ctx
        return dataclasses.replace(ctx, config=dataclasses.replace(
            ctx.config, max_steps=int(config.subtask_steps[spec.index]), stop_on_plateau=False))

    for spec in plan[st.subtask:]:
        log(f"subtask {spec.index} {spec.name} ({spec.kind}) r = {spec.ratio:.3f}")
        st, info = run_subtask(context_of(spec), st, spec, callback=callback, checkpoint=save,
                               progress=progress)
        g = trainer.gaussians(st.train)
        record = {"index": spec.index, "name": spec.name, "kind": spec.kind, "ratio": spec.ratio,
                  "difficulty": spec.difficulty, "steps": info["steps"],
                  "edits_complete_at": info["edits_complete_at"],
                  "anneal_horizon": info["anneal_horizon"], "annealed_at": info["annealed_at"],
                  "seconds": info["seconds"], "converged": info["converged"],
                  "guard": info["guard"], "density": info["density"],
                  "num_gaussians": int(g.num_alive()), "snapshot": None, "metrics": None}
        if info["guard"] == "steps":
            log(f"subtask {spec.name}: max_steps guard ({ctx.config.max_steps}) fired before "
                f"the loss plateaued")
        elif info["guard"] == "seconds":
            log(f"subtask {spec.name}: max_seconds guard ({ctx.config.max_seconds:g} s) fired "
                f"before the loss plateaued, at step {info['steps']}")
        warning = cap_warning(spec.name, info["density"], settings.densify.max_gaussians,
                              int(g.num_alive()))
        if warning:
            log(warning)
        if run_dir is not None:
            rel = Path("subtasks") / spec.dirname
            record["metrics"] = write_scene_snapshot(ctx, run_dir / rel, g, ratio=spec.ratio)
            record["snapshot"] = str(rel / "scene.ply")
        st = finish_subtask(st, record)
        if run_dir is not None:
            atomic_write_text(run_dir / "schedule.json",
                              json.dumps(schedule_json(st.records), indent=2) + "\n")
            save(st)

    final = trainer.gaussians(st.train)
    metrics = scene_metrics(ctx, final, 1.0 if plan else 0.0)
    metrics.update(edit_fit_psnr=edit_fit(ctx, st), wall_time_s=time.perf_counter() - wall0,
                   total_steps=int(sum(r["steps"] for r in st.records)),
                   subtasks=len(st.records),
                   # a fixed budget's subtasks (converged None) were not cut short
                   all_converged=bool(all(r["converged"] is not False for r in st.records)),
                   utilisation=st.utilisation.as_dict(), mode=config.mode,
                   asynchronous=config.asynchronous)
    sched_json = schedule_json(st.records)
    if run_dir is not None:
        atomic_write_text(run_dir / "metrics.json", json.dumps(metrics, indent=2) + "\n")
        if select is not None:
            select_snapshot(run_dir, select)
        if report:
            try:
                from ..pipelines.report import write_report
            except ImportError:
                log("jaxedit.pipelines.report unavailable: no report.html")
            else:
                write_report(run_dir)
    return {"schedule": sched_json, "metrics": metrics, "gaussians": final}
