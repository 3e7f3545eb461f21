"""Outputs people look at: depth maps, turntables, image grids, camera paths (atomic writes)."""

from __future__ import annotations

import io
import warnings
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from .errors import DataError
from .io.files import atomic_path, atomic_write_bytes

# Pixels with less accumulated opacity than this have no meaningful depth.
MIN_ALPHA = 1e-3


def depth_range(depth, alpha, *, percentiles: tuple[float, float] = (2.0, 98.0),
                coverage: float = 0.5) -> tuple[float, float]:
    """Robust (near, far): the (low, high) ``percentiles`` of ``depth`` over pixels whose
    ``alpha`` exceeds ``coverage`` (both float [..., H, W]); (0, 1) when none does."""
    depth, alpha = np.asarray(depth, np.float64), np.asarray(alpha, np.float64)
    if depth.shape != alpha.shape:
        raise DataError("depth", f"shape {depth.shape} differs from alpha's {alpha.shape}")
    lo, hi = percentiles
    if not 0.0 <= lo < hi <= 100.0:
        raise DataError("percentiles", f"need 0 <= low < high <= 100, got {percentiles}")
    covered = (alpha > coverage) & np.isfinite(depth)
    if not covered.any():
        covered = (alpha > MIN_ALPHA) & np.isfinite(depth)
    if not covered.any():
        return 0.0, 1.0
    near, far = np.percentile(depth[covered], [lo, hi])
    if not far > near:  # a flat depth map: widen around it so the division stays finite
        span = max(abs(near) * 1e-3, 1e-6)
        near, far = near - span, far + span
    return float(near), float(far)


def colorize_depth(depth, alpha, *, near: float | None = None, far: float | None = None,
                   cmap: str = "turbo", background=(1.0, 1.0, 1.0),
                   percentiles: tuple[float, float] = (2.0, 98.0)) -> np.ndarray:
    """Depth float [H, W] as RGB float32 [H, W, 3] in [0, 1] in ``cmap`` from ``near`` to
    ``far`` (default :func:`depth_range`), over ``background`` [3] by ``alpha`` [H, W]."""
    import matplotlib

    depth, alpha = np.asarray(depth, np.float64), np.asarray(alpha, np.float64)
    if depth.ndim != 2 or depth.shape != alpha.shape:
        raise DataError("depth", f"need depth and alpha of one shape [H, W], got {depth.shape} "
                                 f"and {alpha.shape}")
    if near is None or far is None:
        auto_near, auto_far = depth_range(depth, alpha, percentiles=percentiles)
        near = auto_near if near is None else near
        far = auto_far if far is None else far
    if not far > near:
        raise DataError("depth range", f"far ({far}) must exceed near ({near})")
    try:
        colormap = matplotlib.colormaps[cmap]
    except KeyError:
        raise DataError("cmap", f"unknown matplotlib colormap {cmap!r}") from None
    t = np.clip((far - np.nan_to_num(depth, nan=far)) / (far - near), 0.0, 1.0)
    rgb = colormap(t)[..., :3]
    a = np.where(alpha > MIN_ALPHA, np.clip(alpha, 0.0, 1.0), 0.0)[..., None]
    bg = np.asarray(background, np.float64).reshape(1, 1, 3)
    return (a * rgb + (1.0 - a) * bg).astype(np.float32)


def to_uint8(image) -> np.ndarray:
    """float [..., 3] in [0, 1] (or uint8) -> uint8, rounded and clipped."""
    image = np.asarray(image)
    if image.dtype == np.uint8:
        return image
    return np.clip(np.rint(np.nan_to_num(image.astype(np.float64)) * 255.0), 0, 255).astype(np.uint8)


def image_grid(images: Sequence, ncols: int | None = None, *, pad: int = 2,
               pad_value: float = 1.0) -> np.ndarray:
    """Images float [H_i, W_i, 3] in [0, 1] (or uint8) tiled row-major into one float32 image
    of ``ncols`` columns (default one row), ``pad`` pixels of grey ``pad_value`` around cells."""
    imgs = [np.asarray(im) for im in images]
    if not imgs:
        raise DataError("images", "need at least one image for a grid")
    imgs = [im.astype(np.float32) / 255.0 if im.dtype == np.uint8 else im.astype(np.float32)
            for im in imgs]
    for i, im in enumerate(imgs):
        if im.ndim == 2:
            imgs[i] = np.repeat(im[..., None], 3, axis=-1)
        elif im.ndim != 3 or im.shape[-1] != 3:
            raise DataError(f"images[{i}]", f"need [H, W, 3] or [H, W], got shape {im.shape}")
    ncols = len(imgs) if ncols is None else int(ncols)
    if ncols < 1:
        raise DataError("ncols", f"must be >= 1, got {ncols}")
    nrows = -(-len(imgs) // ncols)
    h = max(im.shape[0] for im in imgs)
    w = max(im.shape[1] for im in imgs)
    out = np.full((nrows * (h + pad) + pad, ncols * (w + pad) + pad, 3), pad_value, np.float32)
    for i, im in enumerate(imgs):
        r, c = divmod(i, ncols)
        y, x = pad + r * (h + pad), pad + c * (w + pad)
        out[y:y + im.shape[0], x:x + im.shape[1]] = im
    return out


def _default_render():
    from .raster import render

    return render


def render_views(gaussians, cameras, *, background=(1.0, 1.0, 1.0), sh_degree: int | None = None,
                 render_fn: Callable | None = None):
    """(rgb float32 [N, H, W, 3], alpha, depth float32 [N, H, W]) of ``cameras`` [N], one at a
    time by ``render_fn(gaussians, camera, *, background, sh_degree)`` (:func:`jaxedit.render`)."""
    import jax.numpy as jnp

    render_fn = _default_render() if render_fn is None else render_fn
    cams = [cameras] if not cameras.batch_shape else [cameras[i] for i in range(len(cameras))]
    kwargs = {"background": jnp.asarray(background, jnp.float32)}
    if sh_degree is not None:
        kwargs["sh_degree"] = sh_degree
    rgbs, alphas, depths = [], [], []
    for cam in cams:
        out = render_fn(gaussians, cam, **kwargs)
        rgbs.append(np.asarray(out.rgb, np.float32))
        alphas.append(np.asarray(out.alpha, np.float32))
        depths.append(np.asarray(out.depth, np.float32))
    return np.stack(rgbs), np.stack(alphas), np.stack(depths)


def frame_cameras(cameras) -> tuple[np.ndarray, float, float, float]:
    """(target float [3], radius, elevation_deg, horizontal fov_deg) of ``cameras`` [N]' orbit."""
    w2c = np.asarray(cameras.world_to_camera, np.float64).reshape(-1, 4, 4)
    rot, trans = w2c[:, :3, :3], w2c[:, :3, 3]
    centres = -np.einsum("nji,nj->ni", rot, trans)
    axes = rot[:, 2, :]  # camera +z (viewing direction) in world coordinates
    # sum_k (I - a a^T) (x - c_k) = 0: least-squares intersection of the axes.
    proj = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    lhs, rhs = proj.sum(0), np.einsum("nij,nj->i", proj, centres)
    if len(centres) >= 2 and np.linalg.cond(lhs) < 1e8:
        target = np.linalg.solve(lhs, rhs)
    else:  # parallel axes or a single camera: a point ahead of the mean camera
        target = centres.mean(0) + axes.mean(0) * np.linalg.norm(centres.mean(0))
    offsets = centres - target
    dist = np.linalg.norm(offsets, axis=-1)
    elevation = np.degrees(np.arcsin(np.clip(offsets[:, 2] / np.maximum(dist, 1e-12), -1, 1)))
    fx = np.asarray(cameras.fx, np.float64).reshape(-1)
    fov = np.degrees(2 * np.arctan(0.5 * cameras.width / np.median(fx)))
    return target, float(np.median(dist)), float(np.median(elevation)), float(fov)


def frame_gaussians(gaussians, *, fov_deg: float = 40.0) -> tuple[np.ndarray, float]:
    """(target float [3], radius) framing the live Gaussians in a ``fov_deg`` view."""
    alive = np.asarray(gaussians.alive, bool)
    if not alive.any():
        raise DataError("gaussians", "no live Gaussians to frame")
    means = np.asarray(gaussians.means, np.float64)[alive]
    sigma = np.exp(np.asarray(gaussians.log_scales, np.float64)[alive]).max(axis=-1)
    target = np.median(means, axis=0)
    reach = np.linalg.norm(means - target, axis=-1) + 3.0 * np.minimum(sigma, 1e6)
    extent = float(np.percentile(reach, 95))
    radius = 1.05 * max(extent, 1e-6) / np.sin(np.radians(fov_deg) / 2)
    return target, float(radius)


def turntable(gaussians, *, n_frames: int = 36, radius: float | None = None,
              elevation: float | None = None, target=None, size: int | None = None,
              fov_deg: float | None = None, cameras=None, background=(1.0, 1.0, 1.0),
              sh_degree: int | None = None, render_fn: Callable | None = None) -> np.ndarray:
    """A full orbit around the scene (+z up): uint8 [n_frames, size, size, 3]; unset orbit
    parameters from ``cameras`` (:func:`frame_cameras`), else :func:`frame_gaussians`."""
    from . import camera as camlib

    if n_frames < 1:
        raise DataError("n_frames", f"must be >= 1, got {n_frames}")
    if cameras is not None:
        c_target, c_radius, c_elev, c_fov = frame_cameras(cameras)
        default_size = cameras.width
    else:
        fov0 = 40.0 if fov_deg is None else fov_deg
        c_target, c_radius = frame_gaussians(gaussians, fov_deg=fov0)
        c_elev, c_fov, default_size = 20.0, fov0, 128
    target = c_target if target is None else np.asarray(target, np.float64)
    radius = c_radius if radius is None else float(radius)
    elevation = c_elev if elevation is None else float(elevation)
    fov_deg = c_fov if fov_deg is None else float(fov_deg)
    size = default_size if size is None else int(size)
    if not radius > 0 or size < 1:
        raise DataError("turntable", f"need radius > 0 and size >= 1, got {radius}, {size}")
    cams = camlib.orbit(n_frames, radius=radius, elevation_deg=elevation, target=target,
                        width=size, height=size, fov_deg=fov_deg)
    rgb, _, _ = render_views(gaussians, cams, background=background, sh_degree=sh_degree,
                             render_fn=render_fn)
    return to_uint8(rgb)


def load_camera_path(path) -> tuple:
    """(Camera [N], fps or None) of a nerfstudio viewer ``camera_path.json`` (perspective;
    ``camera_to_world`` 16 floats row-major OpenGL, ``fov`` vertical degrees)."""
    import json

    from . import camera as camlib

    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except OSError as e:
        raise DataError(path, f"cannot read camera path ({e.strerror or e})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DataError(path, f"malformed JSON ({e})") from None
    if not isinstance(data, dict):
        raise DataError(path, "a camera path must be a JSON object")
    kind = data.get("camera_type", "perspective")
    if kind != "perspective":
        raise DataError(path, f"camera_type {kind!r} is not supported (perspective only)")
    try:
        width, height = int(data["render_width"]), int(data["render_height"])
        frames = data["camera_path"]
    except KeyError as e:
        raise DataError(path, f"missing key {e.args[0]!r}") from None
    except (TypeError, ValueError):
        raise DataError(path, "render_width/render_height must be integers") from None
    if width < 1 or height < 1:
        raise DataError(path, f"bad render size {width}x{height}")
    if not isinstance(frames, list) or not frames:
        raise DataError(path, "'camera_path' must be a non-empty list")
    cams = []
    for i, f in enumerate(frames):
        try:
            c2w = np.asarray(f["camera_to_world"], np.float64).reshape(4, 4)
            fov = float(f["fov"])
        except (KeyError, TypeError, ValueError):
            raise DataError(path, f"camera_path[{i}] needs camera_to_world (16 numbers) and fov") from None
        if not (np.all(np.isfinite(c2w)) and 0.0 < fov < 180.0):
            raise DataError(path, f"camera_path[{i}]: non-finite pose or fov outside (0, 180)")
        rot = c2w[:3, :3]
        if np.abs(rot.T @ rot - np.eye(3)).max() > 1e-3 or np.linalg.det(rot) < 0:
            raise DataError(path, f"camera_path[{i}]: camera_to_world is not a rigid transform")
        focal = 0.5 * height / np.tan(np.radians(fov) / 2)  # three.js: fov is vertical
        cams.append(camlib.make_camera(camlib.opengl_c2w_to_opencv_w2c(c2w), width=width,
                                       height=height, focal=focal))
    fps = data.get("fps")
    return camlib.stack(cams), (float(fps) if isinstance(fps, (int, float)) and fps > 0 else None)


def save_camera_path(path, cameras, *, fps: float = 12.0) -> None:
    """Write cameras [N] as a nerfstudio camera path (vertical fov from ``fy``)."""
    import json

    from . import camera as camlib

    w2c = np.asarray(cameras.world_to_camera, np.float64).reshape(-1, 4, 4)
    fy = np.broadcast_to(np.asarray(cameras.fy, np.float64).reshape(-1), (len(w2c),))
    frames = []
    for m, f in zip(w2c, fy):
        c2w = camlib.opencv_w2c_to_opengl_c2w(m)
        fov = float(np.degrees(2 * np.arctan(0.5 * cameras.height / f)))
        frames.append({"camera_to_world": [float(v) for v in c2w.reshape(-1)], "fov": fov,
                       "aspect": cameras.width / cameras.height})
    data = {"camera_type": "perspective", "render_width": cameras.width,
            "render_height": cameras.height, "fps": fps, "seconds": len(frames) / fps,
            "camera_path": frames}
    atomic_write_bytes(Path(path), (json.dumps(data, indent=1) + "\n").encode())


def mp4_available() -> bool:
    """Whether MP4 turntables can be written (``imageio-ffmpeg`` installed)."""
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        return False
    return True


def encode_webp(frames, fps: float = 12.0, *, quality: int = 85) -> bytes:
    """Animated WebP bytes of uint8/float frames [F, H, W, 3] (looping)."""
    from PIL import Image

    frames = to_uint8(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or len(frames) == 0:
        raise DataError("frames", f"need [F, H, W, 3] with F >= 1, got shape {frames.shape}")
    if not fps > 0:
        raise DataError("fps", f"must be > 0, got {fps}")
    images = [Image.fromarray(f) for f in frames]
    buf = io.BytesIO()
    images[0].save(buf, format="WEBP", save_all=True, append_images=images[1:],
                   duration=int(round(1000.0 / fps)), loop=0, quality=quality, method=4)
    return buf.getvalue()


def _write_mp4(path: Path, frames: np.ndarray, fps: float) -> None:
    import imageio_ffmpeg

    # H.264 wants even sizes and yuv420p for players (browsers, QuickTime) to accept it.
    h, w = frames.shape[1:3]
    pad_h, pad_w = h % 2, w % 2
    if pad_h or pad_w:
        frames = np.pad(frames, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)), mode="edge")
    with atomic_path(path) as tmp, warnings.catch_warnings():
        # ffmpeg runs in a subprocess; JAX warns about any fork, but fork+exec is safe.
        warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
        writer = imageio_ffmpeg.write_frames(str(tmp), (frames.shape[2], frames.shape[1]),
                                             fps=fps, codec="libx264", pix_fmt_out="yuv420p",
                                             quality=8, macro_block_size=1,
                                             ffmpeg_log_level="error")
        writer.send(None)
        for f in frames:
            writer.send(np.ascontiguousarray(f))
        writer.close()


def write_turntable(path, frames, fps: float = 12.0, *, mp4: bool | None = None) -> list[Path]:
    """Write ``frames`` uint8 or float [F, H, W, 3] as animated WebP at ``path`` and, with
    ``mp4`` (default: whether ``imageio-ffmpeg`` is installed; DataError if True without it),
    MP4 beside it -> the paths written."""
    path = Path(path)
    if path.suffix.lower() != ".webp":
        raise DataError(path, "turntables are written as .webp (plus .mp4 when available)")
    frames = to_uint8(frames)
    atomic_write_bytes(path, encode_webp(frames, fps))
    written = [path]
    if mp4 is None:
        mp4 = mp4_available()
    if mp4:
        if not mp4_available():
            raise DataError(path.with_suffix(".mp4"), "MP4 needs the imageio-ffmpeg package")
        _write_mp4(path.with_suffix(".mp4"), frames, fps)
        written.append(path.with_suffix(".mp4"))
    return written


def read_webp(path) -> tuple[np.ndarray, np.ndarray]:
    """Frames uint8 [F, H, W, 3] and their durations in ms int [F] of a WebP file."""
    from PIL import Image, ImageSequence

    path = Path(path)
    try:
        frames, durations = [], []
        with Image.open(path) as im:
            for f in ImageSequence.Iterator(im):
                f.load()  # Pillow fills in the frame's duration when it decodes it
                frames.append(np.asarray(f.convert("RGB")))
                durations.append(int(f.info.get("duration") or 0))
        return np.stack(frames), np.asarray(durations)
    except (OSError, ValueError) as e:
        raise DataError(path, f"cannot read WebP ({e})") from None


def read_webp_frames(path) -> np.ndarray:
    """uint8 [F, H, W, 3], the frames of an (animated) WebP file."""
    return read_webp(path)[0]


__all__ = ["colorize_depth", "depth_range", "encode_webp", "frame_cameras", "frame_gaussians",
           "image_grid", "load_camera_path", "mp4_available", "read_webp", "read_webp_frames",
           "render_views", "save_camera_path", "to_uint8", "turntable",
           "write_turntable"]

