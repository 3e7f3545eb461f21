"""``reconstruct``: fit 3D Gaussians to a nerfstudio dataset (built-in scenes included).

    python -m experiments reconstruct --data DIR --out RUN_DIR [--iters N --seed S ...]

The edge of :mod:`jaxedit.pipelines.reconstruct`, whose docstring lists what RUN_DIR
receives (scene.ply, test renders, metrics.json, train_log.jsonl, checkpoints/, and
with ``--camera-opt`` the corrected dataset/). The flags are generated from
:class:`jaxedit.pipelines.reconstruct.ReconstructConfig` (experiments/flags.py);
``--resume`` continues from the newest checkpoint and ends with the same Gaussians as
an uninterrupted run.
"""

from __future__ import annotations

from pathlib import Path

from experiments.flags import Flag, FlagSet
# Re-exported: the pipeline is the library's (jaxedit.pipelines.reconstruct); this module is its edge.
from jaxedit.pipelines.reconstruct import capped_initial_points, initial_points, reconstruct  # noqa: F401
from jaxedit.train import BACKGROUNDS

HELP = "reconstruct a nerfstudio dataset with 3DGS: scene.ply, test renders, metrics.json"


def _config_flags() -> FlagSet:
    from jaxedit.pipelines.reconstruct import INITS, NORMALIZE, ReconstructConfig

    return FlagSet(ReconstructConfig, (
        Flag("train.iterations", "--iters"),
        Flag("train.sh_degree"),
        Flag("train.background", choices=BACKGROUNDS),
        Flag("train.densify.max_gaussians"),
        Flag("train.densify.budget", "--densify-budget"),
        Flag("train.densify.refine_every"),
        Flag("train.densify.warmup"),
        Flag("train.densify.stop_at", "--densify-until"),
        Flag("train.densify.reset_every"),
        Flag("train.densify.cull_alpha"),
        Flag("train.camera_opt"),
        Flag("train.lr_camera", "--camera-lr"),
        Flag("train.camera_opt_from"),
        Flag("downscale"),
        Flag("skip_missing_images"),
        Flag("normalize", choices=NORMALIZE),
        Flag("init", choices=INITS),
        Flag("random_points"),
        Flag("checkpoint_every"),
        Flag("log_every"),
    )).complete()


def _flag_sets():
    from experiments.distributed import distributed_flags

    return _config_flags(), distributed_flags()


#: The command's flags, generated from :class:`jaxedit.pipelines.reconstruct.ReconstructConfig`,
#: and the multi-process run's (:class:`jaxedit.parallel.distributed.DistributedConfig`).
FLAGS = _flag_sets()


def add_arguments(p) -> None:
    p.add_argument("--data", type=Path, required=True,
                   help="nerfstudio dataset folder (or its transforms.json)")
    FLAGS[0].add_to(p)
    FLAGS[1].add_to(p.add_argument_group(
        "several processes (jax.distributed; see the README's multi-host section)"))
    p.add_argument("--resume", action="store_true",
                   help="continue from the newest checkpoint in RUN_DIR/checkpoints")


def run_config(args):
    """The :class:`ReconstructConfig` of ``args`` (DataErrors name its fields).

    ``--camera-lr`` scales the final camera rate with it, keeping TrainConfig's decay.
    """
    from jaxedit.train import TrainConfig

    derived = {}
    lr = FLAGS[0].values(args).get("train.lr_camera")
    if lr is not None:  # the decay's ratio stays TrainConfig's
        derived["train.lr_camera_final"] = (lr * TrainConfig.lr_camera_final
                                            / TrainConfig.lr_camera)
    return FLAGS[0].build(args, derived=derived)


def _check(args, config) -> None:
    from jaxedit import DataError

    from jaxedit.memory import require_memory

    if args.out is None:
        raise DataError("--out", "reconstruct needs a run directory (--out RUN_DIR)")
    # A Gaussian of degree-3 SH costs 59 float32 parameters, each with a gradient and two
    # Adam moments, plus densification statistics: about 1 KiB. The random init alone
    # allocates --random-points of them (before the --max-gaussians cap subsamples).
    require_memory("--random-points", config.random_points * 1024,
                   f"{config.random_points} initial Gaussians")


def run(args) -> dict:
    from jaxedit.pipelines import reconstruct as runs

    from experiments.progress import configure, training_bar

    from jaxedit import DataError
    from jaxedit.parallel.distributed import process_count

    from experiments.rundirs import writes

    config = run_config(args)
    _check(args, config)
    if args.resume and process_count() > 1:
        raise DataError("--resume", "not with several processes yet (only process 0 has the "
                                    "checkpoints)")
    configure(quiet=args.quiet)
    if config.init != "random":
        _quiet_colmap()
    # Every process trains the same scene; only process 0 writes the run directory.
    metrics = runs.run(args.data, args.out if writes(args) else None, config, seed=args.seed,
                       resume=args.resume, progress=training_bar())
    if not writes(args):
        return {}
    keys = ("test_psnr", "test_ssim", "num_gaussians", "iterations", "wall_time_s", "steps_per_s",
            "init", "initial_points", "initial_point_count")
    return {k: metrics[k] for k in keys} | {"out": str(args.out)}


def _quiet_colmap() -> None:
    """COLMAP's own log lines off, where it is installed (triangulation reports through ours)."""
    try:
        from jaxedit.capture.sfm import quiet_colmap

        quiet_colmap(True)
    except ImportError:
        pass


__all__ = ["reconstruct", "run_config", "initial_points", "capped_initial_points"]
