"""A whole progressive edit (paper 3.2-3.3): its plan, its run over the subtasks, its records.

    s_in --r_0 (refine, e(0))--> s_0 --r_1--> ... --r_n--> s_n --consolidate (e(1))--> s_out

Each arrow is a seeded, resumable subtask (:mod:`jaxedit.edit.subtask`): an opacity reset
and warm-up (3.3 (1)), the iterative dataset update with HiFA-annealed timesteps, budgeted
density control under a hard cap (3.3 (2)), until the loss plateaus or a guard fires. Modes:
``proedit`` (difficulty-aware schedule), ``nd`` (one edit subtask 0 -> 1, the paper's
ablation), ``in2n`` (Instruct-NeRF2NeRF on 3DGS). Every random draw folds (subtask,
purpose, step) into one key, so a resumed run ends with the same bits. Nothing here writes
a file: :func:`jaxedit.pipelines.edit_run.run_edit` passes callbacks to :func:`run_plan`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

import jax
import numpy as np

from ..editors.base import editor_guidance
from ..editors.keys import quantize_ratio
from ..train import scene_extent
from . import schedule as sched
from .context import EditContext, EditData
from .difficulty import DifficultyOracle, difficulty_view_subset, ms_ssim_distance
from .identity import (IdentityFloor, LowIdentityError, identity_line, identity_problem,
                       measure_identity)
from .outputs import image_scores, scene_metrics
from .plan import ProEditConfig, SubtaskSpec, plan_subtasks, step_guard, subtask_limits
from .state import EditState, finish_subtask
from .subtask import run_subtask
from .trainer import SubtaskTrainer, EditTrainConfig

#: Default threshold = d(0, 1) / 4 (paper: ~4 subtasks for texture edits).
DEFAULT_SUBTASKS = 4


def make_trainer(config: ProEditConfig, settings: EditTrainConfig, data: EditData,
                 gaussians, editable=None) -> SubtaskTrainer:
    """The editing trainer of a run: ``settings`` as given, completed by the plan (warm-up
    W, background) and the scene (extent from the training cameras when unset); ``editable``:
    a local edit's bool [C0] (:class:`SubtaskTrainer`; None: every Gaussian trains)."""
    if settings.scene_extent is None:
        # rounded: a static field, so equal rigs read from files share one compiled step
        extent = float(f"{scene_extent(data.train_cameras):.4g}")
        settings = dataclasses.replace(settings, scene_extent=extent)
    return SubtaskTrainer(settings, int(gaussians.num_alive()), background=config.background,
                          warmup=config.warmup, editable=editable)


def difficulty_oracle(ctx: EditContext, originals: np.ndarray, seed: int, distance=None):
    """The memoised d(r_a, r_b), a mean over the difficulty views' renders ``originals``
    [N, H, W, 3] of the input scene; ``distance`` e.g. :func:`jaxedit.lpips.lpips_distance`
    (None: multi-scale SSIM). It edits with the editor's single edits
    (:func:`jaxedit.editors.compose.measuring_editor`), so its e(0) edits measure the editor."""
    from ..editors.compose import measuring_editor

    views = difficulty_view_subset(len(originals), ctx.config.difficulty_views,
                                   jax.random.key(seed))
    return DifficultyOracle(measuring_editor(ctx.editor), originals, ctx.prompt, views=views,
                            distance=distance, guidance=ctx.config.guidance, seed=seed,
                            embeddings=(ctx.e_prompt, ctx.e_null))


def scene_oracle(ctx: EditContext, gaussians, seed: int, distance=None, renders=None):
    """:func:`difficulty_oracle` of the renders of ``gaussians`` at the training views
    (``renders``: them, made already; None in IN2N mode, which has no schedule)."""
    if ctx.config.mode == "in2n":
        return None
    if renders is None:
        renders = ctx.renderer.views(gaussians, ctx.data.train_cameras)[0]
    return difficulty_oracle(ctx, renders, seed, distance)


def distance_name(distance) -> str:
    """What schedule.json and the log call a difficulty distance."""
    distance = ms_ssim_distance if distance is None else distance
    return getattr(distance, "name", getattr(distance, "__name__", type(distance).__name__))


def make_schedule(ctx: EditContext, oracle, *, start_ratio: float = 0.0):
    """(Schedule, plan ratios from ``start_ratio``, their difficulties) per the config."""
    cfg = ctx.config
    if cfg.mode == "nd":
        s = sched.uniform(1, oracle)
    elif cfg.mode == "in2n":
        s = sched.uniform(1, None)
    elif ctx.hooks.schedule is not None and start_ratio == 0.0:
        s = ctx.hooks.schedule(oracle)
    elif cfg.subtasks is not None:
        s = sched.uniform(cfg.subtasks, oracle)
    elif cfg.threshold is None and cfg.target_subtasks is not None:
        method = sched.decompose_root if cfg.schedule_method == "root" else sched.decompose
        kwargs = {} if cfg.schedule_method == "root" else {"max_depth": cfg.max_depth}
        s = sched.for_target_subtasks(oracle, cfg.target_subtasks, method=method, **kwargs)
    else:
        # no threshold: a quarter of d(0, 1)
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


def edit_fit(ctx: EditContext, st: EditState) -> float:
    """PSNR (dB) of the final renders against the last edited training images: low when
    the edits disagree across views."""
    g = ctx.trainer.gaussians(st.train)
    rgb = np.stack([ctx.renderer.rgb(g, ctx.data.train_cameras[i])
                    for i in range(len(st.edited))])
    return image_scores(rgb, np.asarray(jax.device_get(st.images)))["psnr"]


def cap_warning(name: str, density: dict, cap: int, alive: int) -> str | None:
    """The warning of a subtask whose Gaussian creation the hard cap limited (None: it did not)."""
    if not density["cap_limited"]:
        return None
    return (f"WARNING: subtask {name}: the Gaussian cap ({cap}) limited creation in "
            f"{density['cap_limited']} of {density['refinements']} maintenance steps: "
            f"{density['shortfall']} Gaussians the budget t(n) wanted were not created "
            f"({density['created']} were; {alive} alive at the end). Raise the cap (max_gaussians) "
            f"to let the edit grow geometry")


def check_identity(ctx: EditContext, gaussians, floor: IdentityFloor, *, seed: int,
                   oracle=None, log=lambda msg: None) -> dict | None:
    """The editor's identity on the input scene (schedule.json's ``"identity"``; None in
    IN2N mode): :func:`jaxedit.edit.identity.measure_identity` of the difficulty oracle's
    e(0) edits, logged; ``oracle`` (None: :func:`scene_oracle` of ``gaussians``) keeps
    them for the schedule. Raises :class:`LowIdentityError` under ``floor`` unless
    ``floor.accept_low`` (then a warning)."""
    if ctx.config.mode == "in2n":
        return None
    oracle = scene_oracle(ctx, gaussians, seed) if oracle is None else oracle
    figures = measure_identity(oracle, ctx.data.train_images)
    log(identity_line(figures))
    problem = identity_problem(figures, floor)
    figures = dict(figures, min_psnr=floor.min_psnr, max_lpips=floor.max_lpips,
                   passed=problem is None, accepted_low=problem is not None and floor.accept_low)
    if problem is None:
        return figures
    if not floor.accept_low:
        raise LowIdentityError(
            "editor identity", f"the editor does not reproduce this scene's views at e(0) "
            f"({problem}): refinement would blur the scene before the instruction begins; "
            f"stopped before training. Use InstructPix2Pix weights made for such views "
            f"(--ip2p-weights DIR), or --accept-low-identity to edit anyway", figures)
    log(f"WARNING: editor identity under the floor ({problem}); going on "
        f"(--accept-low-identity)")
    return figures


def plan_steps(ratios, difficulties, *, consolidate: bool) -> tuple[SubtaskSpec, ...]:
    """The subtasks of a branch's steps ``ratios[0] < ... < ratios[-1]`` (any interval of
    the path, past r = 1 too): one edit per step, then (``consolidate``) one at the last."""
    specs = [SubtaskSpec(i, f"r{i + 1}", float(r), None if d is None else float(d), "edit")
             for i, (r, d) in enumerate(zip(ratios[1:], difficulties))]
    if consolidate:
        specs.append(SubtaskSpec(len(specs), "rn", float(ratios[-1]), None, "consolidate"))
    return tuple(specs)


def _schedule_fields(schedule) -> dict:
    return {"threshold": schedule.threshold, "target_subtasks": schedule.target_subtasks,
            "schedule_method": schedule.method, "depth_limit_hit": schedule.depth_limit_hit,
            "difficulty_evaluations": schedule.evaluations}


def plan_edit(ctx: EditContext, gaussians, *, seed: int, distance=None, start_ratio: float = 0.0,
              resumed_from: str | None = None, identity: dict | None = None,
              oracle=None, steps: Callable | None = None,
              log=lambda msg: None) -> tuple[tuple[SubtaskSpec, ...], dict]:
    """(the subtasks, schedule.json's header) of an edit of the input scene ``gaussians``.

    Args:
      seed: seeds the difficulty oracle's edits.
      distance: the difficulty's distance (None: the oracle's default).
      start_ratio: where the schedule starts; a run continued from the snapshot
        ``resumed_from`` has no refine subtask.
      identity: :func:`check_identity`'s figures for the header (None: not checked).
      oracle: the difficulty oracle (None: :func:`scene_oracle` of ``gaussians``).
      steps: ``steps(oracle) -> (fields, ratios, difficulties)``, a branch's own steps
        (:mod:`jaxedit.edit.steer`) instead of the config's schedule; ``fields`` gives the
        header's threshold, target_subtasks, schedule_method, depth_limit_hit and
        difficulty_evaluations.
      log: receives the scheduler's warnings.
    """
    config, data = ctx.config, ctx.data
    if oracle is None:
        oracle = scene_oracle(ctx, gaussians, seed, distance)
    if oracle is not None:
        log(f"difficulty distance: {distance_name(distance)}")
    if steps is not None:
        fields, ratios, diffs = steps(oracle)
        plan = plan_steps(ratios, diffs, consolidate=config.consolidate)
    else:
        schedule, ratios, diffs = make_schedule(ctx, oracle, start_ratio=start_ratio)
        fields = _schedule_fields(schedule)
        if start_ratio >= 1.0 - 1e-9:
            ratios, diffs = [1.0], []
        plan = (plan_subtasks(config.mode, ratios, diffs, start_ratio=start_ratio,
                              refine_first=config.refine_first and resumed_from is None,
                              consolidate=config.consolidate)
                if len(ratios) > 1 or config.mode == "in2n" else
                plan_subtasks("proedit", [0.0, 1.0], [None], refine_first=False,
                              consolidate=config.consolidate)[-1:])
        if start_ratio == 0.0:
            plan = ctx.hooks.planned(plan)
        if schedule.depth_limit_hit:
            log(f"WARNING: the scheduler hit its depth limit (max_depth {config.max_depth}, at "
                f"most {2 ** config.max_depth} subtasks): some subtask is harder than the "
                f"threshold {schedule.threshold:.4g}")
        if schedule.target_subtasks is not None:
            log(f"threshold {schedule.threshold:.4g} gives {schedule.num_subtasks} subtasks "
                f"(target {schedule.target_subtasks})")
    curve = [] if oracle is None else difficulty_curve(oracle, ratios)
    header = {"prompt": ctx.prompt,
              "editor": getattr(ctx.editor, "name", type(ctx.editor).__name__),
              "mode": config.mode, "threshold": fields["threshold"],
              "target_subtasks": fields["target_subtasks"],
              "difficulty": None if oracle is None else {
                  "distance": distance_name(distance),
                  "reduction": "mean over views (paper eq. 3's sum / |V|; the threshold "
                               "is per view)",
                  "views": list(oracle.views), "num_views": len(oracle.views),
                  "of_training_views": len(data.train_images)},
              "schedule_method": fields["schedule_method"],
              "depth_limit_hit": fields["depth_limit_hit"],
              "difficulty_evaluations": fields["difficulty_evaluations"],
              "editor_calls_for_schedule": getattr(oracle, "editor_calls", 0),
              "difficulty_curve": curve, "seed": seed,
              "distance": None if oracle is None else distance_name(distance),
              "resumed_from": resumed_from, "start_ratio": start_ratio, "asynchronous": config.asynchronous,
              "config": dataclasses.asdict(config),
              # the scales every edit of the run used: the config's, or the editor's own
              "guidance": list(editor_guidance(ctx.editor, config.guidance)),
              "guard": {"max_steps": step_guard(config, data.train_images.shape),
                        "max_steps_scaled": config.max_steps is None,
                        "max_seconds": config.max_seconds},
              "max_gaussians": ctx.trainer.settings.densify.max_gaussians,
              "input_gaussians": int(gaussians.num_alive()), "identity": identity}
    return plan, header


def curve_grid(config: ProEditConfig) -> list[float]:
    """The ratios of the reported d(0, r) curve: ``config.curve_points`` evenly in [0, 1]."""
    return [float(r) for r in np.linspace(0.0, 1.0, max(config.curve_points, 2))]


def difficulty_curve(oracle, ratios=()) -> list[list[float]]:
    """[[r, d(0, r)], ...] at 0, ``ratios`` and every ratio the oracle has edited already: no
    editor call (:func:`complete_curve` adds the grid's other points later)."""
    chosen = {quantize_ratio(r): float(r) for r in oracle.edited_ratios()}
    chosen.update({quantize_ratio(r): float(r) for r in (0.0, *ratios)})
    return [[r, d] for r, d in oracle.curve(sorted(chosen.values()))]


def complete_curve(header: dict, oracle, config: ProEditConfig) -> dict:
    """``header`` with its curve at :func:`curve_grid` too (their editor calls made now, after
    the first snapshot rather than before it); ``header`` itself when nothing is missing."""
    have = [r for r, _ in header.get("difficulty_curve") or []]
    known = {quantize_ratio(r) for r in have}
    if oracle is None or all(quantize_ratio(r) in known for r in curve_grid(config)):
        return header
    return dict(header, difficulty_curve=difficulty_curve(oracle, have + curve_grid(config)))


def schedule_json(header: dict, plan, records) -> dict:
    """schedule.json: the header, the finished subtasks' records, then the pending ones."""
    done = {r["index"] for r in records}
    pending = [{"index": p.index, "name": p.name, "ratio": p.ratio, "difficulty": p.difficulty,
                "kind": p.kind, "steps": None, "seconds": None, "converged": None,
                "snapshot": None} for p in plan if p.index not in done]
    return {**header, "subtasks": list(records) + pending}


def subtask_record(spec: SubtaskSpec, info: dict, num_gaussians: int) -> dict:
    """schedule.json's record of a finished subtask (``snapshot`` / ``metrics`` still None)."""
    return {"index": spec.index, "name": spec.name, "kind": spec.kind, "ratio": spec.ratio,
            "difficulty": spec.difficulty, "steps": info["steps"],
            "edits_complete_at": info["edits_complete_at"],
            "anneal_horizon": info["anneal_horizon"], "annealed_at": info["annealed_at"],
            "seconds": info["seconds"], "converged": info["converged"],
            "guard": info["guard"], "density": info["density"],
            "num_gaussians": int(num_gaussians), "snapshot": None, "metrics": None}


def moved_line(name: str, metrics: dict) -> str:
    """The log's line of how far a subtask's snapshot moved from the input scene."""
    return (f"subtask {name}: snapshot {metrics['psnr_vs_input']:.2f} dB from the input scene "
            f"(SSIM {metrics['ssim_vs_input']:.3f}, LPIPS {metrics['lpips_vs_input']:.3f}), "
            f"{metrics['num_gaussians']} Gaussians of the input's {metrics['input_gaussians']}")


def refine_warning(name: str, metrics: dict, min_psnr: float) -> str | None:
    """The warning of a refinement (r_0) snapshot that moved the scene more than
    ``min_psnr`` allows (its test renders against the input scene's; None: it did not)."""
    psnr = metrics.get("psnr_vs_input")
    if psnr is None or psnr >= min_psnr:
        return None
    return (f"WARNING: subtask {name} (refinement, e(0)) moved the scene: its renders are "
            f"{psnr:.1f} dB from the input scene's (floor {min_psnr:g} dB), LPIPS "
            f"{metrics['lpips_vs_input']:.3f}, {metrics['num_gaussians']} Gaussians of "
            f"{metrics['input_gaussians']}: the editor does not reproduce these views")


def subtask_warnings(ctx: EditContext, spec: SubtaskSpec, info: dict,
                     num_gaussians: int) -> list[str]:
    """What the log should say of a finished subtask: a guard that fired, a cap that bit."""
    out = []
    if info["guard"] == "steps":
        guard = ctx.hooks.limits_of(
            spec, subtask_limits(ctx.config, ctx.data.train_images.shape)).max_steps
        out.append(f"subtask {spec.name}: max_steps guard ({guard}) fired "
                   f"before the loss plateaued")
    elif info["guard"] == "seconds":
        out.append(f"subtask {spec.name}: max_seconds guard ({ctx.config.max_seconds:g} s) "
                   f"fired before the loss plateaued, at step {info['steps']}")
    warning = cap_warning(spec.name, info["density"], ctx.trainer.settings.densify.max_gaussians,
                          num_gaussians)
    if warning:
        out.append(warning)
    return out


def run_plan(ctx: EditContext, st: EditState, plan: tuple[SubtaskSpec, ...], *,
             on_subtask: Callable | None = None, checkpoint: Callable | None = None,
             progress: Callable | None = None, callback: Callable | None = None,
             stop: Callable[[], bool] | None = None,
             log: Callable[[str], None] = lambda msg: None) -> EditState:
    """Run the subtasks of ``plan`` from the ``st.subtask``-th on (possibly resumed mid-way);
    returns the state after the last one.

    Args:
      on_subtask: ``on_subtask(st, spec, record) -> record`` when a subtask ends: the
        :func:`subtask_record` to keep (a run directory adds its snapshot).
      checkpoint: ``checkpoint(st)`` every ``checkpoint_every`` steps and after each subtask.
      progress, callback: as :func:`jaxedit.edit.subtask.run_subtask`'s.
      stop: ``stop() -> bool``, asked between subtasks: True ends the run there (the state
        is that of a finished subtask: a checkpoint of it resumes the plan).
      log: ``log(message)``: each subtask's start and its warnings.
    """
    for spec in plan[st.subtask:]:
        if stop is not None and st.subtask > 0 and stop():
            log(f"stopped before subtask {spec.index} {spec.name} (resume to go on)")
            break
        log(f"subtask {spec.index} {spec.name} ({spec.kind}) r = {spec.ratio:.3f}")
        st, info = run_subtask(ctx, st, spec, callback=callback, checkpoint=checkpoint,
                               progress=progress)
        alive = int(ctx.trainer.gaussians(st.train).num_alive())
        record = subtask_record(spec, info, alive)
        for warning in subtask_warnings(ctx, spec, info, alive):
            log(warning)
        if on_subtask is not None:
            record = on_subtask(st, spec, record)
        st = finish_subtask(st, record)
        if checkpoint is not None:
            checkpoint(st)
    return st


def final_metrics(ctx: EditContext, st: EditState, plan, wall_time_s: float) -> dict:
    """metrics.json: the final scene's scores, the edit fit, steps, convergence, utilisation."""
    final = ctx.trainer.gaussians(st.train)
    metrics = scene_metrics(ctx, final, 1.0 if plan else 0.0)
    metrics.update(edit_fit_psnr=edit_fit(ctx, st), wall_time_s=wall_time_s,
                   total_steps=int(sum(r["steps"] for r in st.records)),
                   subtasks=len(st.records),
                   # a fixed budget's subtasks (converged None) were not cut short
                   all_converged=bool(all(r["converged"] is not False for r in st.records)),
                   utilisation=st.utilisation.as_dict(), mode=ctx.config.mode,
                   asynchronous=ctx.config.asynchronous)
    return metrics
