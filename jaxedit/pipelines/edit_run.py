"""An edit run: its config tree, and :func:`run_edit`, which runs it with a run directory.

``python -m experiments edit`` generates its flags from :class:`EditRunConfig`.
:func:`run_edit` is :func:`prepare_edit` then :func:`jaxedit.edit.progressive.run_plan`, with a
:class:`jaxedit.pipelines.rundir.RunDir` at the edge. The run directory::

    RUN/schedule.json        the plan and every finished subtask's record
    RUN/metrics.json         the final scene's numbers
    RUN/checkpoint.npz       the edit state, rewritten every checkpoint_every steps
    RUN/identity.json        only in a run the editor identity check stopped: its figures
    RUN/original/            snapshot of the input scene (:mod:`.snapshots`)
    RUN/subtasks/NN_rX.XXX/  snapshot of each finished subtask
    RUN/selected.ply         the chosen snapshot (``select``)
    RUN/report.html          (``report``)
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import threading
import time
from pathlib import Path
from typing import Callable, NamedTuple

import jax
import numpy as np

from ..compilation import compile_stats
from ..edit import local as local_lib
from ..edit import progressive
from ..edit.buffer import pick_devices
from ..edit.context import EditContext, EditData, encode_prompt
from ..edit.difficulty import default_distance
from ..edit.hooks import NO_HOOKS, EditHooks
from ..edit.identity import IdentityFloor, LowIdentityError
from ..edit.outputs import Renderer
from ..edit.state import EditState, begin_subtask, init_state
from ..edit.subtask import compile_chunk
from ..edit.plan import ProEditConfig
from ..edit.trainer import EditTrainConfig, resolve_max_gaussians
from ..errors import DataError, check_ranges, ranged
from ..editors.diffusion import DDIM_STEPS
from ..io import load_nerfstudio, load_ply, load_scene
from .rundir import RunDir, read_oracle_memo
# the run directory's names, importable from here too (steer, the viewer)
from .rundir import (CHECKPOINT_NAME, IDENTITY_NAME, LOCAL_DIR, ORACLE_NAME,  # noqa: F401
                     write_oracle_memo)
from .snapshots import snapshot_ratio


@dataclasses.dataclass(frozen=True)
class EditStart:
    """Where a branch of an edit run begins (:mod:`jaxedit.pipelines.steer_run` builds it).

    Attributes:
      scene: the Gaussians of the parent's snapshot.
      ratio: that snapshot's ratio on the branch's embedding path.
      label: the parent node, recorded as schedule.json's ``resumed_from``.
      embeddings: (E_to, E_from) of the branch's path, e(r) = r E_to + (1 - r) E_from.
      steps: the branch's ``steps(oracle)`` (:func:`jaxedit.edit.progressive.plan_edit`).
      path_scene: the scene whose renders the path's difficulty oracle edits.
      path_seed: the seed of the path's oracle.
      memo: the path's oracle memo file (:data:`ORACLE_NAME` of the branch that began it).
      shapes: the parent's ``capacity`` and ``max_intersections`` there (None: sized anew).
      notes: fields added to schedule.json's header (an extension's ``experimental``).
      images: float [N, H, W, 3], ``scene`` rendered at the training views (None: rendered
        when the edit starts).
    """

    scene: object
    ratio: float
    label: str
    embeddings: tuple
    steps: Callable
    path_scene: object
    path_seed: int
    memo: Path
    shapes: dict | None = None
    notes: dict | None = None
    images: np.ndarray | None = None


#: The 2D editors the library builds (:func:`make_editor`).
EDITORS = ("ip2p", "ip2p-torch")


@dataclasses.dataclass(frozen=True)
class EditorConfig:
    """The 2D editor of an edit run (:func:`make_editor`).

    Attributes:
      kind: 2D editor (ip2p: InstructPix2Pix in JAX; ip2p-torch: diffusers; simulated).
      weights: diffusers folder of InstructPix2Pix weights (None: the bundled small 64 px model).
      device: torch device of ip2p-torch (None: cuda:0, else cpu).
      dtype: networks' dtype (None: float32 on the CPU, bfloat16/float16 on accelerators).
      size: IP2P working resolution in px (None: 64 for the bundled editor, else 512).
      steps: DDIM steps per IP2P edit.
      batch: ip2p: most views per editor call (None: 8 per accelerator, 1 on the CPU).
      targets: ip2p: a larger view's target: render + e(r)'s edit minus e(0)'s of the photo
        plus the photo (anchored, two edits per view), minus e(0)'s of the render (delta, two
        edits), render + edit change (detail), the render at e(0) and detail after (hybrid),
        or the edit enlarged (stretch). Views at the editor's size: the editor's own edit.
    """

    kind: str = "ip2p"
    weights: Path | None = None
    device: str | None = None
    dtype: str | None = None
    size: int | None = ranged(None, low=8)
    steps: int = ranged(DDIM_STEPS, low=1)
    batch: int | None = ranged(None, low=1)
    targets: str = "anchored"

    def __post_init__(self):
        from ..editors.compose import TARGETS

        if self.targets not in TARGETS:
            raise DataError("targets", f"unknown targets {self.targets!r}; choose from "
                                       f"{', '.join(TARGETS)}")
        check_ranges(self)
        if self.weights is not None and not self.kind.startswith("ip2p"):
            raise DataError("weights", f"used only with the ip2p or ip2p-torch editor (the "
                                       f"editor is {self.kind})")


def make_editor(config: EditorConfig):
    """The InstructPix2Pix editor ``config`` describes (the bundled one without ``weights``);
    the simulated editor is built by the commands, not here."""
    if config.kind == "simulated":
        raise DataError("kind", "the simulated editor is the lab's test instrument: pass "
                                "jaxedit_lab.simulated.SimulatedEditor() as the editor")
    if config.kind not in EDITORS:
        raise DataError("kind", f"unknown editor {config.kind!r}; choose from "
                                f"{', '.join(EDITORS)}")
    from ..editors import bundled_editor, native_size

    weights = config.weights or bundled_editor()
    size = config.size or native_size(weights)
    if config.kind == "ip2p":
        from ..editors.jax_ip2p import load_editor

        from ..editors.compose import with_targets

        # The editor's device of pick_devices, the one run_edit gives the editor.
        return with_targets(load_editor(weights, devices=[pick_devices()[1]],
                                        dtype=config.dtype, size=size, steps=config.steps,
                                        batch=config.batch), config.targets)
    try:
        from ..editors.ip2p import load_editor as load_torch_editor
    except ImportError as e:  # torch / diffusers are optional extras
        raise DataError("kind", f"ip2p-torch is unavailable ({e})") from None
    return load_torch_editor(weights, device=config.device, dtype=config.dtype, size=size,
                             steps=config.steps)


@dataclasses.dataclass(frozen=True)
class EditRunConfig:
    """An edit run's settings.

    Attributes:
      plan: the edit's plan (:class:`jaxedit.edit.plan.ProEditConfig`).
      train: the editing trainer (:class:`jaxedit.edit.trainer.EditTrainConfig`).
      editor: the 2D editor (:class:`EditorConfig`).
      distance: difficulty distance (auto or lpips: LPIPS as in the paper; ms-ssim).
      lpips_weights: LPIPS weights written by convert-lpips (None: the bundled LPIPS-AlexNet).
      downscale: image downscale factor (unset: a power of two, long side <= 1600 px).
      skip_missing_images: drop the frames whose image file is missing instead of stopping.
      test_views: at most this many held-out views in snapshots and metrics (None: all).
      identity: the floor the editor's identity must clear before training.
    """

    plan: ProEditConfig = ProEditConfig()
    train: EditTrainConfig = EditTrainConfig()
    editor: EditorConfig = EditorConfig()
    identity: IdentityFloor = IdentityFloor()
    distance: str = "auto"
    lpips_weights: Path | None = None
    downscale: int | None = ranged(None, low=1)
    skip_missing_images: bool = False
    test_views: int | None = ranged(None, low=1)

    def __post_init__(self):
        check_ranges(self)


def require_edit_memory(config: EditRunConfig, data_path, num_input: int, *,
                        editor_loaded: bool = True) -> None:
    """Refuse (naming ``--downscale``) an edit whose views, Gaussians at the cap and, unless
    ``editor_loaded``, editor weights would not fit in free memory, before any photo is decoded."""
    from ..edit.trainer import default_max_gaussians
    from ..editors import bundled_editor
    from ..io.nerfstudio import auto_downscale, nerfstudio_photo_size
    from ..memory import weight_file_bytes
    from .reconstruct import require_dataset_memory

    # only the library's InstructPix2Pix editors have weight files it knows of
    editor = 0 if editor_loaded or config.editor.kind not in EDITORS else weight_file_bytes(
        config.editor.weights or bundled_editor())
    cap = config.train.densify.max_gaussians or default_max_gaussians(num_input)
    downscale = config.downscale or auto_downscale(*nerfstudio_photo_size(data_path))
    require_dataset_memory(data_path, downscale, cap, extra=editor,
                           extra_what=" and the editor's weights" if editor else "")


def load_inputs(config: EditRunConfig, data_path, scene_path, *,
                editor_loaded: bool = True) -> tuple[EditData, object]:
    """(EditData, input Gaussians) of the nerfstudio dataset ``data_path`` and the splat file
    ``scene_path``, read as ``config`` says once :func:`require_edit_memory` lets it."""
    from .reconstruct import check_image_size

    from ..io.nerfstudio import dataset_downscale

    scene = load_scene(scene_path)
    if not np.asarray(scene.alive).any():
        raise DataError(scene_path, "has no Gaussians (zero vertices): nothing to edit")
    require_edit_memory(config, data_path, int(np.asarray(scene.alive).sum()),
                        editor_loaded=editor_loaded)
    dataset = load_nerfstudio(data_path, downscale=dataset_downscale(data_path, config.downscale),
                              skip_missing=config.skip_missing_images)
    check_image_size(dataset, data_path)
    data = EditData.from_dataset(dataset)
    if config.test_views is not None and len(data.test_images) > config.test_views:
        keep = np.linspace(0, len(data.test_images) - 1, config.test_views).round().astype(int)
        data = EditData.create(data.train_images, data.train_cameras, data.test_images[keep],
                               data.test_cameras[keep])
    return data, scene


def edit_files(config: EditRunConfig, prompt: str, data_path, scene_path, *, editor=None,
               local=None, **kwargs) -> dict:
    """:func:`run_edit` of the scene and dataset on disk, with ``config``'s editor and
    difficulty distance: what ``python -m experiments edit`` runs, as one call.

    Args:
      config: the run's settings.
      prompt: the instruction.
      data_path, scene_path: nerfstudio dataset folder and the input 3DGS .ply.
      editor: the editor to use instead of ``make_editor(config.editor)`` (a wrapped one).
      local: None, a :class:`jaxedit.edit.local.LocalSpec`, or a function of the loaded
        :class:`EditData` returning one (masks matched to its views).
      **kwargs: :func:`run_edit`'s (``seed``, ``run_dir``, ``resume``, ``progress``, ...).
    """
    editor = make_editor(config.editor) if editor is None else editor
    distance = default_distance(config.distance, config.lpips_weights)
    data, scene = load_inputs(config, data_path, scene_path)
    if callable(local):
        local = local(data)
    return run_edit(editor, prompt, data, scene, config=config.plan, settings=config.train,
                    distance=distance, local=local, identity=config.identity, **kwargs)


@contextlib.contextmanager
def on_a_thread(fn: Callable, *args):
    """``fn(*args)`` on a thread while the block runs, joined (and its error raised) at its end."""
    errors: list[BaseException] = []

    def work():
        try:
            fn(*args)
        except BaseException as e:  # raised in the caller's thread below
            errors.append(e)

    thread = threading.Thread(target=work, name=getattr(fn, "__name__", "work"), daemon=True)
    thread.start()
    try:
        yield
    finally:
        thread.join()
    if errors:
        raise errors[0]


def edit_context(editor, prompt: str, data: EditData, gaussians, *, config: ProEditConfig,
                 settings: EditTrainConfig | None = None, seed: int = 0, local=None,
                 hooks: EditHooks = NO_HOOKS, resume_from=None, start: EditStart | None = None,
                 log: Callable[[str], None] = lambda msg: None) -> tuple[EditContext, object]:
    """(the run's :class:`EditContext`, its local plan or None): the prompt and the local
    edit checked, the local plan made, the trainer built with its editable set."""
    if not str(prompt).strip() and config.mode != "in2n":
        raise DataError("prompt", "empty instruction")
    # the cap is checked before the local plan's work, whose editable set the trainer takes
    settings = resolve_max_gaussians(settings or EditTrainConfig.for_mode(config.mode),
                                     int(gaussians.num_alive()))
    _, editor_device = pick_devices()
    # The prompt is encoded once per run: here if the local plan needs it, else by EditContext.
    embeddings = None if start is None else start.embeddings
    local_plan = None
    if local is not None and local.active and (resume_from is not None or start is not None):
        raise DataError("--local", "a local edit starts from the input scene, not --resume-from")
    if local is not None and local.active:
        if local.mode == "auto":
            embeddings = encode_prompt(editor, prompt)
        local_plan = local_lib.plan_local(
            local, gaussians, data.train_cameras, data.train_images, editor=editor,
            embedding=None if embeddings is None else embeddings[0],
            key=jax.random.fold_in(jax.random.key(seed), 35))
        figures = local_plan.figures
        log(f"local edit: {figures['editable']} Gaussians editable, {figures['frozen']} "
            f"frozen, {100 * figures['mask_fraction']:.1f}% of the pixels inside "
            f"({figures['seconds']:.1f} s)")
    trainer = progressive.make_trainer(config, settings, data, gaussians,
                                       None if local_plan is None else local_plan.editable)
    ctx = EditContext.create(editor, prompt, data, config, trainer, Renderer(config.background),
                             jax.random.key(seed), editor_device,
                             masks=None if local_plan is None else local_plan.masks,
                             embeddings=embeddings, hooks=hooks)
    return ctx, local_plan


class EditSetup(NamedTuple):
    """What :func:`prepare_edit` makes: context, start state, plan, schedule.json's header,
    local plan, ready time, difficulty oracle (None in IN2N) and whether the memo served it."""

    ctx: EditContext
    state: EditState
    plan: tuple
    header: dict
    local: object
    started: float
    oracle: object
    memo_restored: bool


def prepare_edit(editor, prompt: str, data: EditData, gaussians, *, config: ProEditConfig,
                 settings: EditTrainConfig | None = None, seed: int = 0, resume_from=None,
                 distance: Callable | None = None, local=None, hooks: EditHooks = NO_HOOKS,
                 identity: IdentityFloor | None = IdentityFloor(),
                 start: EditStart | None = None, memo: Path | None = None,
                 log: Callable[[str], None] = lambda msg: None) -> EditSetup:
    """A new edit, ready for :func:`jaxedit.edit.progressive.run_plan`; writes nothing.

    The context, the identity check (raises :class:`LowIdentityError`), the start state and
    the plan. Arguments as :func:`run_edit`'s.
    """
    ctx, local_plan = edit_context(editor, prompt, data, gaussians, config=config,
                                   settings=settings, seed=seed, local=local, hooks=hooks,
                                   resume_from=resume_from, start=start, log=log)
    started = time.perf_counter()
    start_ratio, start_scene, images = 0.0, gaussians, None
    origin = None if resume_from is None else str(resume_from)
    if start is not None:
        start_ratio, start_scene, origin = start.ratio, start.scene, start.label
        images = (start.images if start.images is not None else
                  ctx.renderer.views(start_scene, data.train_cameras)[0])
    elif resume_from is not None:
        snap = Path(resume_from)
        start_ratio = snapshot_ratio(snap)
        start_scene = load_ply(snap / "scene.ply")
        # The dataset the snapshot was trained on is best approximated by its renders.
        images = np.stack([ctx.renderer.rgb(start_scene, data.train_cameras[i])
                           for i in range(len(data.train_images))])
        log(f"continuing from {snap} (r = {start_ratio:.3f})")
    figures = oracle = None
    if identity is not None and start_ratio == 0.0 and start is None:
        # before anything is compiled for training; its e(0) edits stay in the oracle, and
        # the schedule reuses them
        oracle = progressive.scene_oracle(ctx, gaussians, seed, distance)
        figures = progressive.check_identity(ctx, gaussians, identity, seed=seed,
                                             oracle=oracle, log=log)
    shapes = {} if start is None else start.shapes or {}
    st = init_state(ctx, start_scene, images, **shapes)
    # The training chunks' program is built (or read back) while the schedule edits.
    with on_a_thread(compile_chunk, ctx, begin_subtask(ctx, st)):
        if oracle is None and start is not None:  # the start's renders when they are the path's
            oracle = progressive.scene_oracle(
                ctx, start.path_scene, start.path_seed, distance,
                renders=images if start.path_scene is start.scene else None)
        elif oracle is None:
            oracle = progressive.scene_oracle(ctx, gaussians, seed, distance)
        restored = oracle is not None and memo is not None and read_oracle_memo(oracle, memo)
        plan, header = progressive.plan_edit(
            ctx, gaussians, seed=seed, distance=distance, start_ratio=start_ratio,
            log=log, resumed_from=origin, identity=figures, oracle=oracle,
            steps=None if start is None else start.steps)
        log(f"schedule: {len(plan)} subtasks, {header['editor_calls_for_schedule']} editor "
            f"calls")
    if local_plan is not None:
        header = dict(header, local=local_plan.figures)
    if start is not None and start.notes:
        header = dict(header, **start.notes)
    return EditSetup(ctx, st, plan, header, local_plan, started, oracle, restored)


def run_edit(editor, prompt: str, data: EditData, gaussians, *, config: ProEditConfig,
             settings: EditTrainConfig | None = None, seed: int = 0,
             run_dir: str | os.PathLike | None = None, resume: bool = False,
             resume_from: str | os.PathLike | None = None, select=None,
             callback: Callable | None = None, progress: Callable | None = None,
             report: bool = True, log: Callable[[str], None] | None = None,
             distance: Callable | None = None, local=None, hooks: EditHooks = NO_HOOKS,
             identity: IdentityFloor | None = IdentityFloor(), start: EditStart | None = None,
             stop: Callable[[], bool] | None = None) -> dict:
    """Edit ``gaussians`` progressively (:mod:`jaxedit.edit.progressive`); returns the run summary.

    Args:
      editor, prompt: the 2D editor and the instruction.
      data: original photos and cameras (train views edited, test views held out).
      gaussians: the input scene (a reconstruction of ``data``).
      config / settings: plan and trainer knobs (settings None: the mode's).
      seed: the run seed (every random draw derives from it).
      run_dir: the run directory (None: in memory only, no files).
      resume: continue the run in ``run_dir`` from its checkpoint.
      resume_from: a snapshot directory (``subtasks/NN_rX.XXX``) to continue from.
      select: ratio (float) or subtask index (int) whose snapshot becomes ``selected.ply``.
      callback: ``callback(spec, step, loss)`` after every training step.
      progress: ``progress(spec, step, loss, state)`` after every training step.
      report: write ``run_dir/report.html`` at the end.
      log: ``log(message)`` for what a person should read (warnings, resumption).
      distance: perceptual distance of the difficulty (default multi-scale SSIM).
      local: a :class:`jaxedit.edit.local.LocalSpec` (None or inactive: a global edit).
      hooks: a study's changes (:class:`jaxedit.edit.hooks.EditHooks`).
      identity: the editor identity floor (None: not checked); under it raises
        :class:`LowIdentityError`, having written only ``run_dir/identity.json``.
      start: a branch's beginning (:class:`EditStart`; None: the input scene at r = 0).
      stop: ``stop() -> bool``, asked between subtasks: True ends the run (``resume`` goes on).
    Returns:
      {"schedule": schedule.json contents, "metrics": metrics.json contents (None when
      stopped), "gaussians": final, "stopped": whether ``stop`` ended it}.
    """
    log = log or (lambda msg: None)
    compiles_before = compile_stats()
    run = RunDir.at(run_dir)
    setup, memo_owner = None, False
    if resume:
        ctx, local_plan = edit_context(editor, prompt, data, gaussians, config=config,
                                       settings=settings, seed=seed, local=local, hooks=hooks,
                                       resume_from=resume_from, start=start, log=log)
        wall0 = time.perf_counter()
        st, plan, header, wall_s = run.resume(ctx, gaussians, log)
        wall0 -= wall_s
    else:
        try:
            setup = prepare_edit(editor, prompt, data, gaussians, config=config,
                                 settings=settings, seed=seed, resume_from=resume_from,
                                 distance=distance, local=local, hooks=hooks, identity=identity,
                                 start=start, memo=run.memo(start), log=log)
        except LowIdentityError as e:  # the check's record, and nothing else
            run.write_identity(e)
            raise
        ctx, st, plan, header, local_plan = setup[:5]
        wall0 = setup.started
        memo_owner = run.write_memo(setup.oracle, setup.memo_restored, start)
    # The input scene's renders of the held-out views: every snapshot says how far it moved.
    reference = None if run.path is None else (
        ctx.renderer.views(gaussians, data.test_cameras)[0], int(gaussians.num_alive()))
    refine_floor = (identity or IdentityFloor()).refine_min_psnr
    if not resume and start is None:
        run.write_original(ctx, gaussians, local_plan)

    def save(state):
        run.save(state, plan, header, time.perf_counter() - wall0)

    def finish_curve(state) -> bool:
        """After the first snapshot: the difficulty curve's other points (and their edits in
        the memo); whether the header changed."""
        nonlocal header
        if setup is None or state.records:
            return False
        before, header = header, progressive.complete_curve(header, setup.oracle, ctx.config)
        if memo_owner and header is not before:
            write_oracle_memo(setup.oracle, run.memo(start))
        return header is not before

    def on_subtask(state, spec, record):
        """A finished subtask's snapshot, and schedule.json with its record."""
        if run.path is None:
            finish_curve(state)
            return record
        shapes = {"capacity": int(state.train.gaussians.capacity),
                  "max_intersections": int(state.train.max_intersections)}
        record = run.write_snapshot(ctx, spec, ctx.trainer.gaussians(state.train), record,
                                    reference, shapes)
        log(progressive.moved_line(spec.name, record["metrics"]))
        warning = (progressive.refine_warning(spec.name, record["metrics"], refine_floor)
                   if spec.kind == "refine" else None)
        if warning:
            log(warning)
        records = tuple(state.records) + (record,)
        run.write_schedule(progressive.schedule_json(header, plan, records))
        if finish_curve(state):
            run.write_schedule(progressive.schedule_json(header, plan, records))
        return record

    run.write_schedule(progressive.schedule_json(header, plan, st.records))
    save(st)
    compiled = compile_stats(since=compiles_before)
    log(f"training starts: {compiled['count']} programs compiled, {compiled['cache_hits']} "
        f"read from the compile cache ({compiled['seconds']:.1f} s)")
    st = progressive.run_plan(ctx, st, plan, on_subtask=on_subtask, checkpoint=save,
                              progress=progress, callback=callback, stop=stop, log=log)
    final = ctx.trainer.gaussians(st.train)
    if st.subtask < len(plan):  # stopped between subtasks: the checkpoint resumes it
        return {"schedule": progressive.schedule_json(header, plan, st.records), "metrics": None,
                "gaussians": final, "stopped": True}
    metrics = {**progressive.final_metrics(ctx, st, plan, time.perf_counter() - wall0),
               "compiles": compile_stats(since=compiles_before)}
    run.finish(metrics, select, report)
    return {"schedule": progressive.schedule_json(header, plan, st.records), "metrics": metrics,
            "gaussians": final, "stopped": False}
