"""``render``: render any snapshot (.ply) along any camera path.

    python -m experiments render --scene PLY --out DIR [--data DIR [--split test]]
    python -m experiments render --scene PLY --out DIR --orbit 36 --radius 3 --elevation 20
    python -m experiments render --scene PLY --out DIR --camera-path camera_path.json

Writes ``DIR/frames/frame_000.png ...``, coloured depth maps ``DIR/depth/``, the
frames as a turntable/flythrough ``DIR/turntable.webp`` (+ ``.mp4`` when
imageio-ffmpeg is installed), the path itself as ``DIR/camera_path.json`` (the
nerfstudio viewer's format, so it can be edited there and rendered again) and
``DIR/metrics.json`` (frame count, timing). The path: the cameras of a nerfstudio
dataset (``--data``, ``--split``), a nerfstudio camera path (``--camera-path``),
or an orbit whose unset radius/elevation/target are fitted to the scene.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

HELP = "render a snapshot (.ply) along a dataset's cameras or an orbit (PNG frames + turntable)"


def add_arguments(p) -> None:
    p.add_argument("--scene", type=Path, required=True, help="3DGS .ply file to render")
    path = p.add_mutually_exclusive_group()
    path.add_argument("--data", type=Path, default=None,
                      help="nerfstudio dataset (folder or transforms.json) whose cameras to use")
    path.add_argument("--orbit", type=int, default=None, metavar="N",
                      help="an orbit of N frames around the scene (the default path: 36 frames)")
    path.add_argument("--camera-path", type=Path, default=None,
                      help="nerfstudio viewer camera path JSON (camera_path.json) to follow")
    p.add_argument("--split", choices=["all", "train", "test"], default="all",
                   help="with --data: which cameras")
    p.add_argument("--normalize", choices=["none", "nerfstudio"], default="none",
                   help="with --data: the world normalisation the scene was reconstructed in")
    p.add_argument("--radius", type=float, default=None, help="orbit radius (default: fit the scene)")
    p.add_argument("--elevation", type=float, default=None, help="orbit elevation in degrees (default 20)")
    p.add_argument("--target", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                   help="orbit centre (default: the scene's robust centre)")
    p.add_argument("--fov", type=float, default=None, help="orbit horizontal field of view, degrees")
    p.add_argument("--size", type=int, default=None,
                   help="frame width in pixels (orbit: square frames, default 256; data: rescales)")
    p.add_argument("--fps", type=float, default=None,
                   help="frames per second of the video (default: the camera path's, else 12)")
    p.add_argument("--background", type=float, nargs=3, default=(1.0, 1.0, 1.0),
                   metavar=("R", "G", "B"), help="background colour in [0, 1]")
    p.add_argument("--sh-degree", type=int, default=None, help="SH degree to render (default: all)")
    p.add_argument("--no-depth", action="store_true", help="skip the depth maps")


def _check(args) -> None:
    from jaxedit import DataError

    if args.out is None:
        raise DataError("--out", "an output directory is required")
    if not args.scene.is_file():
        raise DataError(args.scene, "is a folder, expected a scene .ply file (given as --scene)"
                        if args.scene.is_dir() else "scene file does not exist")
    if args.orbit is not None and args.orbit < 1:
        raise DataError("--orbit", f"needs at least 1 frame, got {args.orbit}")
    if args.size is not None and not 8 <= args.size <= 4096:
        raise DataError("--size", f"must be in [8, 4096], got {args.size}")
    if args.radius is not None and not args.radius > 0:
        raise DataError("--radius", f"must be > 0, got {args.radius}")
    if args.fps is not None and not args.fps > 0:
        raise DataError("--fps", f"must be > 0, got {args.fps}")
    if not all(0.0 <= c <= 1.0 for c in args.background):
        raise DataError("--background", f"colour components must be in [0, 1], got {args.background}")
    if args.fov is not None and not 0.0 < args.fov < 180.0:
        raise DataError("--fov", f"must be in (0, 180) degrees, got {args.fov}")
    if args.elevation is not None and not abs(args.elevation) <= 90.0:
        raise DataError("--elevation", f"must be in [-90, 90] degrees, got {args.elevation}")
    if args.target is not None and not np.isfinite(args.target).all():
        raise DataError("--target", f"must be finite, got {args.target}")
    if args.data is None and args.split != "all":
        raise DataError("--split", "only applies with --data")
    if args.orbit is not None:  # before the orbit's cameras are even made
        size = 256 if args.size is None else args.size
        check_memory(args.orbit, size, size)


def check_memory(n: int, width: int, height: int) -> None:
    """Refuse a camera path whose frames would not fit in memory (they are kept for the video)."""
    from experiments.cli import require_memory

    # float32 RGB, alpha and depth per pixel per frame, kept until the turntable is written.
    per_frame = width * height * 4 * 5
    require_memory("--orbit/--size", n * per_frame, f"{n} frames of {width}x{height} px")


def cameras_for(args, gaussians):
    """(cameras [N], fps or None): a dataset's cameras, a camera path file, or an orbit."""
    from jaxedit import DataError, camera as camlib, viz

    if args.camera_path is not None:
        cams, fps = viz.load_camera_path(args.camera_path)
        if args.size is not None and args.size != cams.width:
            cams = cams.scaled(args.size / cams.width)
        return cams, fps
    if args.data is not None:
        from jaxedit.io import load_nerfstudio

        ds = load_nerfstudio(args.data, normalize=args.normalize)
        if args.split == "train":
            cams = ds.cameras[np.asarray(ds.train_indices)]
        elif args.split == "test":
            cams = ds.cameras[np.asarray(ds.test_indices)]
        else:
            cams = ds.cameras
        if not cams.batch_shape or len(cams) == 0:
            raise DataError(args.data, f"no cameras in split {args.split!r}")
        if args.size is not None and args.size != cams.width:
            cams = cams.scaled(args.size / cams.width)
        return cams, None
    fov = 40.0 if args.fov is None else args.fov
    if args.radius is None or args.target is None:
        if not np.asarray(gaussians.alive).any():
            raise DataError(args.scene, "has no Gaussians to frame an orbit around; give --radius "
                            "and --target (or --data / --camera-path) to render its background")
        target, radius = viz.frame_gaussians(gaussians, fov_deg=fov)
    else:
        radius = args.radius
    if args.target is not None:
        target = np.asarray(args.target, np.float64)
    size = 256 if args.size is None else args.size
    return camlib.orbit(args.orbit or 36, radius=args.radius or radius,
                        elevation_deg=20.0 if args.elevation is None else args.elevation,
                        target=target, width=size, height=size, fov_deg=fov), None


def run(args) -> dict:
    from experiments.progress import Progress, configure
    from jaxedit import camera as camlib, viz
    from jaxedit.io import load_ply, write_image
    from jaxedit.io.files import atomic_write_text

    _check(args)
    configure(quiet=args.quiet)
    t0 = time.perf_counter()
    gaussians = load_ply(args.scene)
    cams, path_fps = cameras_for(args, gaussians)
    camlib.check_cameras(cams, args.camera_path or args.data or "--orbit/--radius/--fov/--target")
    fps = args.fps or path_fps or 12.0
    n = len(cams)
    check_memory(n, cams.width, cams.height)
    out = Path(args.out)
    frames, alphas, depths = [], [], []
    t_render = time.perf_counter()
    with Progress(n, "render") as bar:
        for i in range(n):
            rgb, alpha, depth = viz.render_views(gaussians, cams[i], background=args.background,
                                                 sh_degree=args.sh_degree)
            frames.append(rgb[0])
            alphas.append(alpha[0])
            depths.append(depth[0])
            write_image(out / "frames" / f"frame_{i:03d}.png",
                        np.ascontiguousarray(np.clip(rgb[0], 0.0, 1.0)))
            bar.update(1)
    render_s = time.perf_counter() - t_render
    if not args.no_depth:
        near, far = viz.depth_range(np.stack(depths), np.stack(alphas))
        for i in range(n):
            write_image(out / "depth" / f"frame_{i:03d}.png",
                        viz.colorize_depth(depths[i], alphas[i], near=near, far=far,
                                           background=args.background))
    videos = viz.write_turntable(out / "turntable.webp", np.stack(frames), fps=fps)
    viz.save_camera_path(out / "camera_path.json", cams, fps=fps)
    metrics = {
        "scene": str(args.scene), "frames": n, "width": cams.width, "height": cams.height,
        "num_gaussians": int(np.asarray(gaussians.alive).sum()),
        "render_s": round(render_s, 3), "frames_per_s": round(n / max(render_s, 1e-9), 3),
        "wall_time_s": round(time.perf_counter() - t0, 3),
        "fps": fps,
        "outputs": (["frames/"] + ([] if args.no_depth else ["depth/"]) + [p.name for p in videos]
                    + ["camera_path.json"]),
    }
    atomic_write_text(out / "metrics.json", json.dumps(metrics, indent=2) + "\n")
    return metrics
