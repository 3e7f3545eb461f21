"""``process-data``: photos or a video -> a posed nerfstudio dataset, by COLMAP (pycolmap).

    python -m experiments process-data --images DIR --out DATA [--matching exhaustive]
    python -m experiments process-data --video FILE --out DATA [--num-frames 300]
    python -m experiments process-data --images DIR --out DATA --focal-px 1200 [--refine-intrinsics]

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

Needs the optional extra: ``pip install -e ".[capture]"`` (pycolmap, imageio-ffmpeg).
"""

from __future__ import annotations

from pathlib import Path

HELP = "photos or a video -> nerfstudio dataset by structure from motion (COLMAP via pycolmap)"
# The dataset folder must be empty when the run starts: record config.json after it.
RECORD_CONFIG_AFTER_RUN = True


#: Library arguments named unlike their flags (for error messages).
FIELD_FLAGS = {"min_fraction": "--min-registered"}

def add_arguments(p) -> None:
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--images", type=Path, help="folder of photos (png, jpg, tif)")
    source.add_argument("--video", type=Path, help="video file (anything ffmpeg reads)")
    p.add_argument("--num-frames", type=int, default=300,
                   help="video: frames to keep, the sharpest of each of this many windows")
    p.add_argument("--matching", choices=["auto", "exhaustive", "sequential"], default="auto",
                   help="image pairs to match (auto: exhaustive for photos, sequential for video)")
    p.add_argument("--overlap", type=int, default=10,
                   help="sequential matching: successors matched to each frame")
    p.add_argument("--camera-model", default="SIMPLE_RADIAL",
                   choices=["SIMPLE_RADIAL", "OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "RADIAL"],
                   help="COLMAP camera model shared by all images")
    p.add_argument("--max-features", type=int, default=8192, help="SIFT features per image")
    p.add_argument("--max-image-size", type=int, default=3200,
                   help="longer image side for SIFT (larger images are downscaled for it)")
    p.add_argument("--min-registered", type=float, default=0.5,
                   help="fail when SfM registers fewer than this fraction of the images")
    p.add_argument("--threads", type=int, default=-1, help="COLMAP threads (-1: all cores)")
    known = p.add_mutually_exclusive_group()
    known.add_argument("--focal-px", type=float, default=None,
                       help="known focal length in pixels (principal point at the centre); "
                            "held fixed unless --refine-intrinsics")
    known.add_argument("--camera-params", default=None, metavar="FX,FY,CX,CY[,K1,K2,P1,P2]",
                       help="known intrinsics in pixels (nerfstudio's fl_x,fl_y,cx,cy,k1,...), "
                            "in --camera-model's terms; held fixed unless --refine-intrinsics")
    p.add_argument("--refine-intrinsics", action="store_true",
                   help="refine --focal-px / --camera-params in bundle adjustment (a start only)")


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
    from jaxedit.capture.sfm import SfmOptions, parse_camera_params, quiet_colmap

    from experiments.progress import Progress, configure

    if args.out is None:
        raise DataError("--out", "process-data needs a dataset folder (--out DATA)")
    try:
        import pycolmap  # noqa: F401
    except ImportError:
        raise DataError("pycolmap", 'not installed; pip install -e ".[capture]"') from None
    configure(quiet=args.quiet)
    quiet_colmap(True)
    matching = args.matching
    if matching == "auto":
        matching = "sequential" if args.video is not None else "exhaustive"
    options = SfmOptions(camera_model=args.camera_model, matching=matching, overlap=args.overlap,
                         max_features=args.max_features, max_image_size=args.max_image_size,
                         num_threads=args.threads, seed=args.seed, focal_px=args.focal_px,
                         camera_params=(None if args.camera_params is None
                                        else parse_camera_params(args.camera_params)),
                         refine_intrinsics=args.refine_intrinsics).check()
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
        sampled, index, scores = frames.sample_video(args.video, args.num_frames)
        sources = list(sampled)
        extra = {"video_frames": index.tolist(), "blur_scores": [round(float(s), 6) for s in scores]}
    with Progress(4, "process-data") as root:
        report = stage_reporter(root)
        summary = process_capture(args.out, sources, options=options,
                                  min_fraction=args.min_registered, report=report)
        report.close()
    return summary | {"matching": matching} | extra
