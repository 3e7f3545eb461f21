"""A reconstruction run: fit 3D Gaussians to a nerfstudio dataset and write its run directory.

The library half of ``python -m experiments reconstruct``, whose flags are generated from
:class:`ReconstructConfig`. :func:`reconstruct` writes ``scene.ply`` (INRIA 3DGS PLY),
``test/NNN_<name>.png`` and ``test_compare.png``, ``metrics.json``, ``train_log.jsonl``,
``checkpoints/ckpt_<step>.npz`` (resuming ends with the same Gaussians) and, with
``camera_opt``, ``dataset/`` (the images as trained with the learned pose corrections).

Initial points (``init``): "auto" takes the dataset's ``ply_file_path``, else SIFT features
triangulated at the known poses (:mod:`jaxedit.capture.triangulate`) topped up with points on
the surfaces they mark (:mod:`jaxedit.capture.dense`), else (logged) photo-consistent random
points (:mod:`jaxedit.capture.points`); "triangulate" and "random" take those alone.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path
from typing import Callable

import jax
import numpy as np

from .. import gaussians as G
from ..compilation import compile_stats
from ..train.background import background_rgb
from ..errors import DataError, check_ranges, ranged
from ..capture.triangulate import TriangulateOptions
from ..train import TrainConfig
from .rundir import JsonlLog, RollingCheckpoints, latest_checkpoint

log = logging.getLogger("jaxedit.reconstruct")

#: How the poses may be normalised when the dataset is read.
NORMALIZE = ("none", "nerfstudio")
#: Where the initial points come from (see the module docstring).
INITS = ("auto", "triangulate", "random")


@dataclasses.dataclass(frozen=True)
class ReconstructConfig:
    """A reconstruction run's settings: training, reading the dataset, recording the run.

    Attributes:
      train: training hyper-parameters (:class:`jaxedit.train.TrainConfig`).
      downscale: integer image downscale factor (1: full size; unset: long side <= 1600 px).
      skip_missing_images: drop the frames whose image file is missing instead of stopping.
      normalize: re-centre and scale the poses as nerfstudio does ("nerfstudio") or not ("none").
      init: initial points: "auto" (dataset, else triangulated + dense), "triangulate" or "random".
      triangulation: how "triangulate" and "auto" triangulate the training views.
      random_points: initial points of the random start (photo-consistent random points).
      checkpoint_every: checkpoint period in steps (0: only at the end).
      log_every: train_log.jsonl period in steps.
    """

    train: TrainConfig = TrainConfig()
    downscale: int | None = ranged(None, low=1)
    skip_missing_images: bool = False
    normalize: str = "none"
    init: str = "auto"
    triangulation: TriangulateOptions = TriangulateOptions()
    random_points: int = ranged(20_000, low=1)
    checkpoint_every: int = ranged(1000, low=0)
    log_every: int = ranged(10, low=1)

    def __post_init__(self):
        check_ranges(self)
        if self.normalize not in NORMALIZE:
            raise DataError("normalize", f"must be one of {', '.join(NORMALIZE)}, got "
                            f"{self.normalize!r}")
        if self.init not in INITS:
            raise DataError("init", f"must be one of {', '.join(INITS)}, got {self.init!r}")


def composite_background(name: str) -> tuple[float, float, float]:
    """The solid colour renders are scored on and RGBA photos composited over for a
    training background ``name``: its own colour, white for "random"."""
    return background_rgb(name) or background_rgb("white")


def resolve_downscale(path, config: ReconstructConfig) -> int:
    """``config.downscale``, or when unset (None) the factor :func:`jaxedit.io.nerfstudio.auto_downscale`
    picks for the dataset at ``path`` (from transforms.json alone; logged)."""
    from ..io.nerfstudio import dataset_downscale

    return dataset_downscale(path, config.downscale)


def require_dataset_memory(path, downscale: int, max_gaussians: int, *, extra: float = 0.0,
                           extra_what: str = "") -> None:
    """DataError naming ``--downscale`` when ``max_gaussians`` Gaussians on the views at ``path``
    plus ``extra`` bytes (``extra_what``) would not fit in free memory; decodes no photo."""
    from ..io.nerfstudio import nerfstudio_frame_count, nerfstudio_view_size
    from ..memory import require_memory, working_set

    height, width = nerfstudio_view_size(path, downscale=downscale)
    count, channel_bytes = nerfstudio_frame_count(path)
    require_memory("--downscale", working_set(count, height, width, channel_bytes,
                                              max_gaussians) + extra,
                   f"{count} views of {width}x{height} and up to {max_gaussians} Gaussians "
                   f"(--max-gaussians){extra_what}")


def load_dataset(path, config: ReconstructConfig):
    """The nerfstudio dataset at ``path`` as ``config`` reads it; DataError if its images are
    too small or the run would not fit in memory."""
    from ..io import load_nerfstudio

    downscale = resolve_downscale(path, config)
    require_dataset_memory(path, downscale, config.train.densify.max_gaussians)
    data = load_nerfstudio(path, downscale=downscale, normalize=config.normalize,
                           background=composite_background(config.train.background),
                           skip_missing=config.skip_missing_images)
    check_image_size(data, path)
    return data


def run(data_path, out, config: ReconstructConfig, *, seed: int = 0, resume: bool = False,
        progress: Callable | None = None) -> dict:
    """Read the dataset at ``data_path`` and reconstruct it into ``out`` (see
    :func:`reconstruct`); returns the metrics."""
    return run_loaded(load_dataset(data_path, config), out, config, seed=seed, resume=resume,
                      progress=progress)


def run_loaded(data, out, config: ReconstructConfig, *, seed: int = 0, resume: bool = False,
               progress: Callable | None = None) -> dict:
    """:func:`run` of a dataset already read by :func:`load_dataset` with ``config``."""
    return reconstruct(data, out, config.train, seed=seed, resume=resume,
                       checkpoint_every=config.checkpoint_every, log_every=config.log_every,
                       random_points=config.random_points, init=config.init,
                       triangulation=config.triangulation, progress=progress)


#: Smallest image side that training and evaluation accept: SSIM's 11-pixel window.
MIN_IMAGE_SIZE = 11


def check_image_size(data, where) -> None:
    """DataError when ``data``'s images (after downscaling) are smaller than SSIM's window."""

    h, w = data.image_size
    if min(h, w) < MIN_IMAGE_SIZE:
        raise DataError(where, f"images are {w}x{h} px (after downscaling); training needs at "
                        f"least {MIN_IMAGE_SIZE}x{MIN_IMAGE_SIZE} (the SSIM window)")


#: Border pixels of the training images that must show the background for carving.
CARVE_BORDER_FRACTION = 0.5


def initial_points(data, n_random: int, seed: int, background=None, *, init: str = "auto",
                   triangulation: TriangulateOptions = TriangulateOptions()):
    """(points [P, 3], colours [P, 3], source) by ``init``; source is "dataset",
    "triangulated", "triangulated+dense" (up to ``n_random`` points; "+random" when the
    surfaces gave too few) or "random". Random and dense candidates are carved by
    ``background`` (RGB) when :data:`CARVE_BORDER_FRACTION` of the borders show it.
    """

    if init not in INITS:
        raise DataError("init", f"must be one of {', '.join(INITS)}, got {init!r}")
    if init == "auto" and data.points is not None and len(data.points) >= 4:
        colors = data.point_colors if data.point_colors is not None else np.full(
            (len(data.points), 3), 0.5, np.float32)
        return np.asarray(data.points, np.float32), np.asarray(colors, np.float32), "dataset"
    if init in ("auto", "triangulate"):
        found = _triangulated(data, triangulation, required=init == "triangulate",
                              background=background)
        if found is not None and (init == "triangulate" or len(found[0]) >= n_random):
            return (*found, "triangulated")
        if found is not None:
            return _dense_start(data, found, n_random, seed, background)
    return (*_random_start(data, n_random, seed, background), "random")


def _random_start(data, n_random: int, seed: int, background):
    """(points, colours): ``n_random`` photo-consistent random points, carved by ``background``."""
    from ..capture.points import random_points

    images, cameras = data.train()
    background = _carving(images, background)
    points, colors = random_points(images, cameras, n_random, jax.random.key(seed),
                                   background=background)
    if background is not None:
        log.info("initial points: %d random points carved by the background %s",
                 len(points), tuple(float(c) for c in background))
    return points, colors


def _carving(images, background):
    """``background`` where :data:`CARVE_BORDER_FRACTION` of the images' borders show it."""
    from ..capture.points import background_fraction

    if background is not None and background_fraction(images, background) < CARVE_BORDER_FRACTION:
        return None  # a scene photo, not an object on a background: no carving
    return background


def _dense_start(data, found, n_random: int, seed: int, background):
    """(points, colours, source): the triangulated ``found`` points, then points on the
    surfaces they mark up to ``n_random`` (:mod:`jaxedit.capture.dense`), then random
    ones if those fall short."""
    from ..capture.dense import surface_points

    images, cameras = data.train()
    dense = surface_points(found[0], images, cameras, n_random - len(found[0]),
                           jax.random.fold_in(jax.random.key(seed), 2),
                           background=_carving(images, background))
    parts, source = [found, dense], "triangulated+dense"
    short = n_random - len(found[0]) - len(dense[0])
    if short > 0:
        parts.append(_random_start(data, short, seed, background))
        source += "+random"
    log.info("initial points: %d triangulated, %d on the surfaces they mark%s", len(found[0]),
             len(dense[0]), f", {short} random" if short > 0 else "")
    return (np.concatenate([p[0] for p in parts]).astype(np.float32),
            np.concatenate([p[1] for p in parts]).astype(np.float32), source)


def _triangulated(data, options: TriangulateOptions, *, required: bool, background=None):
    """(points, colours) triangulated at the training views' poses, their features found on
    the photos read at ``options.feature_side`` when the views were loaded smaller
    (:func:`jaxedit.capture.triangulate.feature_views`); when not ``required``, None (logged)
    where pycolmap is missing or finds too few points."""
    from ..capture.triangulate import feature_views, triangulate

    try:
        import pycolmap  # noqa: F401
    except ImportError:
        if required:
            raise DataError("init", 'triangulate needs pycolmap: pip install -e ".[capture]", '
                                    'or use --init random') from None
        log.warning("initial points: the dataset has none and pycolmap is not installed "
                    "to triangulate them; starting from random points")
        return None
    images, cameras = feature_views(data, options.feature_side,
                                    (1.0, 1.0, 1.0) if background is None else background)
    try:
        points, colors = triangulate(images, cameras, options=options,
                                     where=getattr(data, "path", "dataset"))
    except DataError as e:
        if required:
            raise
        log.warning("initial points: %s; starting from random points", e)
        return None
    log.info("initial points: %d triangulated at the known poses of %d training views "
             "(features at %dx%d px)", len(points), len(images), images.shape[2],
             images.shape[1])
    return points, colors


def capped_initial_points(data, n_random: int, cap: int, seed: int, background=None, *,
                          init: str = "auto",
                          triangulation: TriangulateOptions = TriangulateOptions()):
    """:func:`initial_points`, thinned (uniformly, logged) to at most ``cap`` points."""

    points, colors, source = initial_points(data, n_random, seed, background, init=init,
                                            triangulation=triangulation)
    if len(points) > cap:
        log.info("initial points: keeping a random %d of the %d %s points (max_gaussians)",
                 cap, len(points), source)
        points, colors = G.subsample_points(points, colors, cap,
                                            jax.random.fold_in(jax.random.key(seed), 1))
    return points, colors, source


def reconstruct(data, out: Path, config, *, seed: int = 0, resume: bool = False,
                checkpoint_every: int = 1000, log_every: int = 10, random_points: int = 20_000,
                init: str = "auto", triangulation: TriangulateOptions = TriangulateOptions(),
                progress: Callable | None = None) -> dict:
    """Train on ``data``'s training views, evaluate on its test views, write the outputs.

    Args:
      data: a :class:`jaxedit.io.Dataset`.
      out: run directory (None: write nothing, as processes other than 0 do).
      config: :class:`jaxedit.train.TrainConfig`.
      seed, resume, checkpoint_every, log_every, random_points, init, triangulation: as
        :class:`ReconstructConfig` (``resume``: continue from the newest checkpoint).
      progress: :func:`jaxedit.train.fit`'s progress callback (its ``close()`` called at the end).
    Returns:
      the metrics dict (also written to ``out/metrics.json``).
    """
    import contextlib

    from .. import train as T
    from ..io.files import atomic_write_text

    t_start = time.perf_counter()
    compiles_before = compile_stats()
    out = None if out is None else Path(out)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    # The training views stay as loaded (uint8 for photos) on the device, a quarter of float32.
    train_images, train_cams = data.subset_pixels(data.train_indices)
    if len(data.test_indices):
        test_images, test_cams = data.test()
        test_idx, eval_split = data.test_indices, "test"
    else:  # no held-out views: report training-view quality, and say so
        test_images, test_cams = data.train()
        test_idx, eval_split = data.train_indices, "train"
    extent = T.scene_extent(train_cams)
    ckpt_dir = None if out is None else out / "checkpoints"

    state = None
    if resume and ckpt_dir is not None:
        latest = latest_checkpoint(ckpt_dir)
        if latest is not None:
            state = T.load_checkpoint(latest)
            if state.config != config:
                # The flags win (e.g. a larger --iters extends the run); the result then
                # differs from an uninterrupted run with either setting.
                log.warning("resuming %s with changed training settings", latest)
                state = dataclasses.replace(state, config=config)
            log.info("resuming from %s (step %d)", latest, int(state.step))
    points_source, num_points = "checkpoint", None
    if state is None:
        points, colors, points_source = capped_initial_points(
            data, random_points, config.densify.max_gaussians, seed,
            background_rgb(config.background), init=init, triangulation=triangulation)
        num_points = int(len(points))
        log.info("initial points: %d (%s; --init %s)", num_points, points_source, init)
        g = G.from_points(points, colors, sh_degree=config.sh_degree)
        state = T.init_state(g, config, extent, key=jax.random.key(seed), cameras=train_cams)
    start_step = int(state.step)

    chunk_times: list[tuple[float, int]] = []  # (seconds, steps) of every chunk of steps
    last = [time.perf_counter()]

    def timer(_state, metrics):
        now = time.perf_counter()
        chunk_times.append((now - last[0], len(metrics["loss"])))
        last[0] = now

    t_train = time.perf_counter()
    last[0] = t_train
    bar = progress or None  # False: no progress (the earlier boolean)
    try:
        with (contextlib.nullcontext() if out is None
              else JsonlLog(out / "train_log.jsonl")) as log_record:
            state = T.fit(state, train_images, train_cams, log=log_record, log_every=log_every,
                          checkpoint=None if out is None else RollingCheckpoints(ckpt_dir),
                          checkpoint_every=checkpoint_every or None, progress=bar,
                          callback=timer, desc="reconstruct")
    finally:
        if bar is not None and hasattr(bar, "close"):
            bar.close()
    train_s = time.perf_counter() - t_train
    steps = int(state.step) - start_step

    t_eval = time.perf_counter()
    result = T.evaluate(state.gaussians, test_images, test_cams,
                        background=composite_background(config.background))
    eval_s = time.perf_counter() - t_eval

    t_write = time.perf_counter()
    renders = result.pop("renders")
    corrections = None
    if out is not None:
        corrections = write_outputs(out, data, renders, test_images, test_idx, eval_split,
                                    state, config)
    write_s = time.perf_counter() - t_write

    seconds = np.asarray([t for t, _ in chunk_times], np.float64)
    times = seconds / np.maximum([n for _, n in chunk_times], 1) if chunk_times else seconds
    median = float(np.median(times)) if len(times) else float("nan")
    # Chunks far slower per step than the median are the ones that (re)compiled.
    slow = times > 10 * median if len(times) else times.astype(bool)
    metrics = {
        "test_psnr": result["psnr"], "test_ssim": result["ssim"], "eval_split": eval_split,
        "test_psnr_per_view": result["psnr_per_view"],
        "test_ssim_per_view": result["ssim_per_view"],
        "num_gaussians": int(state.gaussians.num_alive()), "capacity": state.capacity,
        "max_gaussians": config.densify.max_gaussians,
        "iterations": int(state.step), "steps_run": steps, "resumed_from": start_step,
        "wall_time_s": round(time.perf_counter() - t_start, 3), "train_time_s": round(train_s, 3),
        "steps_per_s": steps / train_s if train_s > 0 else 0.0,
        "steady_step_ms": 1e3 * median,
        "steady_steps_per_s": 1.0 / median if median > 0 else 0.0,
        "compile_chunks": int(np.sum(slow)),
        "compile_time_s": round(float(np.sum(seconds[slow])), 3),
        "eval_time_s": round(eval_s, 3), "write_time_s": round(write_s, 3),
        "max_intersections": state.max_intersections, "scene_extent": extent,
        "initial_points": points_source, "initial_point_count": num_points, "init": init,
        "train_views": int(len(train_images)),
        "test_views": int(len(test_idx)), "image_size": [int(train_images.shape[2]),
                                                         int(train_images.shape[1])],
        "config": config.to_dict(),
        "compiles": compile_stats(since=compiles_before),
    }
    if corrections is not None:
        metrics["camera_corrections"] = corrections
    if out is not None:
        atomic_write_text(out / "metrics.json", json.dumps(metrics, indent=2) + "\n")
    return metrics


def write_outputs(out: Path, data, renders, test_images, test_idx, eval_split: str, state,
                  config) -> dict | None:
    """Write a finished reconstruction's files (test renders [V, H, W, 3] and their
    comparison strip, scene.ply, with ``camera_opt`` the corrected dataset) into ``out``;
    returns the camera corrections' summary (None without ``camera_opt``)."""
    from ..io import save_ply, write_image

    for k, (i, r) in enumerate(zip(test_idx, renders)):
        name = Path(data.filenames[int(i)]).stem
        write_image(out / eval_split / f"{k:03d}_{name}.png", r)
    columns = min(len(renders), 8)
    if columns:
        top = np.concatenate(list(np.asarray(test_images[:columns])), axis=1)
        bottom = np.concatenate(list(renders[:columns]), axis=1)
        write_image(out / f"{eval_split}_compare.png", np.concatenate([top, bottom], axis=0))
    save_ply(out / "scene.ply", state.gaussians)
    if config.camera_opt:
        return write_corrected_dataset(out / "dataset", data, state.cameras)
    return None


def write_corrected_dataset(folder: Path, data, corrections) -> dict:
    """Write ``data`` as trained, with its training cameras' learned corrections (test
    cameras keep theirs), to ``folder`` atomically; returns the corrections' summary."""

    from .. import poses
    from ..io import save_nerfstudio

    train = np.asarray(data.train_indices)
    fixed = poses.corrected_cameras(data.cameras[train], corrections)
    w2c = np.array(data.cameras.world_to_camera, np.float32)
    w2c[train] = np.asarray(fixed.world_to_camera)
    cameras = dataclasses.replace(data.cameras, world_to_camera=w2c)
    save_nerfstudio(folder, data.images, cameras, filenames=data.filenames,
                    train_indices=train, test_indices=np.asarray(data.test_indices),
                    points=data.points, point_colors=data.point_colors)
    sizes = poses.correction_sizes(corrections)
    rot, trans = sizes["rotation_deg"], sizes["translation"]
    return {"median_rotation_deg": float(np.median(rot)), "max_rotation_deg": float(rot.max()),
            "median_translation": float(np.median(trans)), "max_translation": float(trans.max()),
            "dataset": str(folder)}


__all__ = ["NORMALIZE", "ReconstructConfig", "capped_initial_points", "check_image_size",
           "composite_background", "initial_points", "load_dataset", "reconstruct", "run",
           "write_corrected_dataset", "write_outputs"]
