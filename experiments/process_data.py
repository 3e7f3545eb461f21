"""``process-data``: photos or a video -> a posed nerfstudio dataset, by COLMAP (pycolmap).

    python -m experiments process-data --images DIR --out DATA [--matching exhaustive]
    python -m experiments process-data --video FILE --out DATA [--num-frames 300]
    python -m experiments process-data --images DIR --out DATA --focal-px 1200 [--refine-intrinsics]
    python -m experiments process-data --triangulate DATA      # points for a posed dataset

The analogue of nerfstudio's ``ns-process-data images|video``: SIFT extraction,
matching (exhaustive for photos, sequential for video frames), incremental
mapping, the largest model kept; writes ``DATA/transforms.json`` (OpenGL
camera-to-world, OPENCV or PINHOLE intrinsics, ``applied_transform``),
``images/``, ``images_2/``, ``images_4/``, ``sparse_pc.ply`` and ``colmap/``, all
at once when everything succeeded. A video is cut into ``--num-frames`` windows
and the sharpest frame of each is kept. Known intrinsics (``--focal-px`` or
``--camera-params``) are held fixed in bundle adjustment, or only start it with
``--refine-intrinsics``; photos with an EXIF focal length start COLMAP from it. Each
frame records its photo's name as ``original_file_path``. Then::

    python -m experiments reconstruct --data DATA --out RUN --normalize nerfstudio

``--triangulate DATA`` gives a posed ``transforms.json`` without a point cloud (instant-ngp,
Polycam, Record3D) one: SIFT features matched between neighbouring views and triangulated
at the known poses, written as ``DATA/sparse_pc.ply`` and its ``ply_file_path`` (see
:mod:`jaxedit.capture.triangulate`); ``reconstruct`` does the same in memory by default.

Needs the optional extra: ``pip install -e ".[capture]"`` (pycolmap, imageio-ffmpeg).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

HELP = "photos or a video -> nerfstudio dataset by structure from motion (COLMAP via pycolmap)"
# The dataset folder must be empty when the run starts: record config.json after it.
RECORD_CONFIG_AFTER_RUN = True


#: Library arguments named unlike their flags (for error messages).
FIELD_FLAGS = {"min_fraction": "--min-registered", "camera_params": "--camera-params"}


def _config_flags():
    from jaxedit.capture import CaptureConfig
    from jaxedit.capture.sfm import CAMERA_MODELS

    from .flags import Flag, FlagSet

    # SfmOptions checks its fields in .check(), which run() calls.
    return FlagSet(CaptureConfig, (
        Flag("num_frames"),
        Flag("sfm.overlap"),
        Flag("sfm.camera_model", choices=CAMERA_MODELS),
        Flag("sfm.max_features"),
        Flag("sfm.max_image_size"),
        Flag("min_registered"),
        Flag("sfm.num_threads", "--threads"),
        Flag("sfm.focal_px"),
        Flag("sfm.refine_intrinsics"),
    ), derived=("sfm.camera_params",)).complete()  # from --camera-params


@dataclasses.dataclass(frozen=True)
class ProcessDataCommand:
    """The capture to read and how its pairs and intrinsics are given.

    Attributes:
      images: folder of photos (png, jpg, tif).
      video: video file (anything ffmpeg reads).
      triangulate: a posed nerfstudio dataset (folder or transforms.json) without points:
        triangulate features at its poses and write them as its ply_file_path.
      matching: image pairs to match (auto: exhaustive for photos, sequential for video).
      camera_params: known intrinsics in pixels (nerfstudio's fl_x,fl_y,cx,cy,k1,...), in
        --camera-model's terms; held fixed unless --refine-intrinsics (excludes --focal-px).
      skip_missing_images: with --triangulate: triangulate without the frames whose image
        file is missing (a warning lists them) instead of stopping.
    """

    images: Path | None = None
    video: Path | None = None
    triangulate: Path | None = None
    matching: str = "auto"
    camera_params: str | None = None
    skip_missing_images: bool = False


def _command_flags():
    from .flags import Flag, FlagSet

    return FlagSet(ProcessDataCommand, (
        Flag("images", exclusive="source", required=True),
        Flag("video", exclusive="source", required=True),
        Flag("triangulate", exclusive="source", required=True, metavar="DATA"),
        Flag("matching", choices=("auto", "exhaustive", "sequential")),
        Flag("camera_params", metavar="FX,FY,CX,CY[,K1,K2,P1,P2]"),
        Flag("skip_missing_images"))).complete()


#: The command's flags: its settings', generated from :class:`jaxedit.capture.CaptureConfig`,
#: and its input's (:class:`ProcessDataCommand`).
FLAGS = (_config_flags(), _command_flags())


def add_arguments(p) -> None:
    FLAGS[1].add_to(p)
    FLAGS[0].add_to(p)


def run_config(args):
    """The :class:`jaxedit.capture.CaptureConfig` of ``args`` (DataErrors name its fields);
    ``--matching auto`` picks sequential matching for a video, exhaustive for photos."""
    from jaxedit.capture.sfm import parse_camera_params

    matching = args.matching
    if matching == "auto":
        matching = "sequential" if getattr(args, "video", None) is not None else "exhaustive"
    return FLAGS[0].build(args, derived={
        "sfm.matching": matching, "sfm.seed": args.seed,
        "sfm.camera_params": (None if args.camera_params is None
                              else parse_camera_params(args.camera_params))})


def stage_reporter(root):
    """A ``report(stage, done, total)`` callback drawing one child bar per stage under ``root``."""
    state = {"stage": None, "bar": None}

    def report(stage: str, done: int, total: int) -> None:
        if stage != state["stage"]:
            if state["bar"] is not None:
                state["bar"].close()
                root.update(1)
            state["stage"], state["bar"] = stage, root.child(total, stage)
        bar = state["bar"]
        if done > bar.n:
            bar.update(done - bar.n)

    def close() -> None:
        if state["bar"] is not None:
            state["bar"].close()
            root.update(1)
            state["bar"] = None

    report.close = close
    return report


def run(args) -> dict:
    from jaxedit import DataError
    from jaxedit.capture import frames
    from jaxedit.capture.dataset import check_out_dir, process_capture
    from jaxedit.capture.sfm import quiet_colmap

    from experiments.progress import Progress, configure

    if args.out is None and getattr(args, "triangulate", None) is None:
        raise DataError("--out", "process-data needs a dataset folder (--out DATA)")
    try:
        import pycolmap  # noqa: F401
    except ImportError:
        raise DataError("pycolmap", 'not installed; pip install -e ".[capture]"') from None
    configure(quiet=args.quiet)
    quiet_colmap(True)
    config = run_config(args)
    if getattr(args, "triangulate", None) is not None:
        return triangulate(args, config)
    if getattr(args, "skip_missing_images", False):
        raise DataError("--skip-missing-images", "only applies with --triangulate")
    options = config.sfm.check()
    check_out_dir(args.out)  # before decoding anything
    extra = {}
    if args.images is not None:
        sources = frames.list_images(args.images)
        frames.check_images(sources, args.images)
    else:
        try:
            import imageio_ffmpeg  # noqa: F401
        except ImportError:
            raise DataError("imageio-ffmpeg", 'not installed; pip install -e ".[capture]"') from None
        sampled, index, scores = frames.sample_video(args.video, config.num_frames)
        sources = list(sampled)
        extra = {"video_frames": index.tolist(), "blur_scores": [round(float(s), 6) for s in scores]}
    with Progress(4, "process-data") as root:
        report = stage_reporter(root)
        summary = process_capture(args.out, sources, options=options,
                                  min_fraction=config.min_registered, report=report)
        report.close()
    return summary | {"matching": options.matching} | extra


def triangulate(args, config) -> dict:
    """``--triangulate DATA``: the dataset's points triangulated at its poses, written into it."""
    from jaxedit import DataError
    from jaxedit.capture.triangulate import triangulate_dataset, write_dataset_points
    from jaxedit.io.nerfstudio import _load_meta, _resolve_json

    if args.out is not None:
        raise DataError("--out", "--triangulate writes into the dataset it is given; drop --out")
    json_path = _resolve_json(args.triangulate)
    meta = _load_meta(json_path)
    if meta.get("ply_file_path") is not None:  # before any photo is read
        raise DataError(json_path, f"already has points (ply_file_path: "
                                   f"{meta['ply_file_path']!r}); remove that key to triangulate")
    points, colors, summary = triangulate_dataset(json_path, options=config.triangulation,
                                                  skip_missing=args.skip_missing_images)
    ply = write_dataset_points(json_path, points, colors)
    return summary | {"ply_file_path": str(ply), "transforms": str(json_path)}
