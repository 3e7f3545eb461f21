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

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from jaxedit.errors import check_ranges, ranged

HELP = "render a snapshot (.ply) along a dataset's cameras or an orbit (PNG frames + turntable)"


@dataclasses.dataclass(frozen=True)
class RenderConfig:
    """What is rendered, along which cameras, and how.

    Attributes:
      scene: splat file to render (.ply, .compressed.ply, .spz, .sog, meta.json, .splat).
      data: nerfstudio dataset (folder or transforms.json) whose cameras to use.
      orbit: an orbit of N frames around the scene (the default path: 36 frames).
      camera_path: nerfstudio viewer camera path JSON (camera_path.json) to follow.
      split: with --data: which cameras.
      normalize: with --data: the world normalisation the scene was reconstructed in.
      radius: orbit radius (None: fit the scene).
      elevation: orbit elevation in degrees (None: 20).
      target: orbit centre (None: the scene's robust centre).
      fov: orbit horizontal field of view, degrees (None: 40).
      size: frame width in pixels (orbit: square frames, None: 256; data: rescales).
      fps: frames per second of the video (None: the camera path's, else 12).
      background: background colour.
      sh_degree: SH degree to render (None: all).
      no_depth: skip the depth maps.
    """

    scene: Path | None = None
    data: Path | None = None
    orbit: int | None = ranged(None, low=1)
    camera_path: Path | None = None
    split: str = "all"
    normalize: str = "none"
    radius: float | None = ranged(None, low=0, open=True)
    elevation: float | None = ranged(None, low=-90, high=90)
    target: tuple[float, float, float] | None = None
    fov: float | None = ranged(None, low=0, high=180, open=True)
    size: int | None = ranged(None, low=8, high=4096)
    fps: float | None = ranged(None, low=0, open=True)
    background: tuple[float, float, float] = ranged((1.0, 1.0, 1.0), low=0, high=1)
    sh_degree: int | None = None
    no_depth: bool = False

    def __post_init__(self):
        check_ranges(self)


def _config_flags():
    from experiments.flags import Flag, FlagSet

    return FlagSet(RenderConfig, (
        Flag("scene", required=True), Flag("data", exclusive="path"),
        Flag("orbit", exclusive="path", metavar="N"), Flag("camera_path", exclusive="path"),
        Flag("split", choices=("all", "train", "test")),
        Flag("normalize", choices=("none", "nerfstudio")), Flag("radius"), Flag("elevation"),
        Flag("target", metavar=("X", "Y", "Z")), Flag("fov"), Flag("size"), Flag("fps"),
        Flag("background", metavar=("R", "G", "B")), Flag("sh_degree"), Flag("no_depth"))).complete()


#: The command's flags, generated from :class:`RenderConfig`.
FLAGS = (_config_flags(),)


def add_arguments(p) -> None:
    FLAGS[0].add_to(p)


def run_config(args) -> RenderConfig:
    """The :class:`RenderConfig` of ``args`` (range errors name the flag)."""
    return FLAGS[0].build(args)


def _check(args) -> None:
    from jaxedit import DataError

    if args.out is None:
        raise DataError("--out", "an output directory is required")
    if not args.scene.is_file():
        raise DataError(args.scene, "is a folder, expected a scene file (given as --scene)"
                        if args.scene.is_dir() else "scene file does not exist")
    run_config(args)  # the ranges
    if args.data is None and args.split != "all":
        raise DataError("--split", "only applies with --data")
    if args.orbit is not None:  # before the orbit's cameras are even made
        size = 256 if args.size is None else args.size
        check_memory(args.orbit, size, size)


def check_memory(n: int, width: int, height: int) -> None:
    """Refuse a camera path whose frames would not fit in memory (they are kept for the video)."""
    from jaxedit.memory import require_memory

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
        from jaxedit.io import load_nerfstudio_cameras

        # transforms.json alone: the photos are neither decoded nor needed.
        cams, train, test = load_nerfstudio_cameras(args.data, normalize=args.normalize)
        if args.split == "train":
            cams = cams[train]
        elif args.split == "test":
            cams = cams[test]
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
    from jaxedit.io import load_scene, write_image
    from jaxedit.io.files import atomic_write_text

    _check(args)
    configure(quiet=args.quiet)
    t0 = time.perf_counter()
    gaussians = load_scene(args.scene)
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
