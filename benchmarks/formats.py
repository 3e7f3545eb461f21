"""Splat file formats: each format's round trip both ways, sizes against splat-transform's, speed.

    python benchmarks/formats.py [--smoke] [--out DIR] [--scene FILE --data DATASET]
                                 [--splat-transform DIR] [--parts quality,viewer,speed]
                                 [--formats ply,spz,...] [--repeats R]

Quality, on a scene (``--scene``, e.g. the demo's edited snapshot, with its dataset ``--data`` for
the test cameras; without them a random scene seen from an orbit):
  * ours: save_scene -> load_scene -> our render of the test views, PSNR against our render of
    the scene itself (white background), and the file size;
  * ours read by splat-transform 3.7.0: its conversion of our file back to a .ply, rendered;
  * theirs: splat-transform's file from the scene's .ply (compressed .ply, .spz, .sog) read by
    load_scene and rendered, its size and the ratio of ours to it.
Viewer (with splat-transform and chromium): our .spz of the scene in splat-transform's .html
(the SuperSplat viewer), screenshot in headless Chromium (software WebGL) from a camera looking
at the scene's centre, against our render of that camera: PSNR, and the two side by side as
DIR/formats_viewer.png.
Speed: save_scene and load_scene of N random Gaussians at SH degree 3 (1 M for every format),
Gaussians per second by wall time and by this process's CPU time (time.process_time, all its
threads), each the best of R repeats (default 3; SOG once, its k-means dominates), with the
1-minute load average before and after each format: on a shared machine the wall time says how
busy it was, the CPU time what the work costs.

``--parts``: which of quality, viewer and speed to run (default all); the parts not run are kept
from an existing DIR/formats.json. ``--formats``: the formats the speed part times (with
``--parts``, the others keep their figures).
``--splat-transform DIR``: the npm prefix holding @playcanvas/splat-transform (default
$SPLAT_TRANSFORM_DIR, then PATH); its parts are skipped, and say so, without it.
Writes DIR/formats.json.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
from common import parse_args, peak_rss_mb, write_json  # noqa: E402  (sets sys.path)

SUFFIX = {"ply": ".ply", "compressed-ply": ".compressed.ply", "spz": ".spz", "sog": ".sog",
          "splat": ".splat"}
THEIRS = ("compressed-ply", "spz", "sog")  # the formats splat-transform writes
SPEED_FORMATS = ("ply", "compressed-ply", "spz", "splat", "sog")
PARTS = ("quality", "viewer", "speed")


def _extra(parser):
    parser.add_argument("--scene", type=Path, default=None, help="a splat file to measure on")
    parser.add_argument("--data", type=Path, default=None, help="its nerfstudio dataset (cameras)")
    parser.add_argument("--splat-transform", type=Path, default=None,
                        help="npm prefix with @playcanvas/splat-transform installed")
    parser.add_argument("--parts", default="quality,viewer,speed",
                        help="comma list of quality, viewer, speed (the others are kept)")
    parser.add_argument("--formats", default=",".join(SPEED_FORMATS),
                        help="comma list of the formats the speed part times")


def find_splat_transform(prefix: Path | None) -> list[str] | None:
    prefix = prefix or (Path(os.environ["SPLAT_TRANSFORM_DIR"]) if os.environ.get("SPLAT_TRANSFORM_DIR")
                        else None)
    candidates = [prefix / "node_modules" / ".bin" / "splat-transform"] if prefix else []
    candidates.append(Path(shutil.which("splat-transform") or "/nonexistent"))
    found = next((c for c in candidates if c.exists()), None)
    return [str(found)] if found and shutil.which("node") else None


def load_their_ply(path: Path):
    """load_ply of a .ply splat-transform decoded, its infinite opacities clipped to +-20 first.

    splat-transform decodes an 8-bit alpha of 255 (or 0) as an infinite logit, which load_ply
    refuses; the render is the same for any logit past about 10.
    """
    from jaxedit.io import load_ply

    data = bytearray(path.read_bytes())
    end = data.index(b"end_header\n") + len(b"end_header\n")
    names = [ln.split()[-1] for ln in data[:end].decode().splitlines() if ln.startswith("property")]
    assert all(ln.split()[1] == "float" for ln in data[:end].decode().splitlines()
               if ln.startswith("property")), "expected an all-float .ply"
    table = np.frombuffer(data, np.float32, offset=end).reshape(-1, len(names))
    column = names.index("opacity")
    table[:, column] = np.clip(table[:, column], -20, 20)
    fixed = path.with_suffix(".clipped.ply")
    fixed.write_bytes(bytes(data))
    return load_ply(fixed)


def _screenshot(url: str, size: int, tmp: Path, seconds: float = 180.0) -> np.ndarray:
    """float [size, size, 3]: headless Chromium's picture of ``url`` once two frames agree."""
    import base64
    import io
    import json
    import urllib.request

    from PIL import Image
    from websockets.sync.client import connect

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    profile = Path(tempfile.mkdtemp(dir=tmp))
    proc = subprocess.Popen([chromium, "--headless", "--no-sandbox", "--use-angle=swiftshader",
                             "--enable-unsafe-swiftshader", "--hide-scrollbars", "--no-first-run",
                             "--remote-debugging-port=0", f"--user-data-dir={profile}", url],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        port_file, deadline = profile / "DevToolsActivePort", time.monotonic() + 60
        while not (port_file.is_file() and port_file.read_text().count("\n") >= 1):
            if time.monotonic() > deadline:
                raise TimeoutError("chromium did not start")
            time.sleep(0.2)
        port = int(port_file.read_text().split()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=30) as r:
            page = next(p for p in json.load(r) if p["type"] == "page")
        ws, calls = connect(page["webSocketDebuggerUrl"], max_size=None), [0]

        def call(method, **params):
            calls[0] += 1
            ws.send(json.dumps({"id": calls[0], "method": method, "params": params}))
            while True:
                msg = json.loads(ws.recv(timeout=120))
                if msg.get("id") == calls[0]:
                    return msg.get("result", {})

        call("Emulation.setDeviceMetricsOverride", width=size, height=size, deviceScaleFactor=1,
             mobile=False)
        deadline, last = time.monotonic() + seconds, None
        while True:
            time.sleep(2)
            data = base64.b64decode(call("Page.captureScreenshot")["data"])
            img = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"), np.float32) / 255
            drawn = (img < 0.9).mean() > 0.01
            if (drawn and last is not None and np.abs(img - last).max() < 1 / 255) \
                    or time.monotonic() > deadline:
                ws.close()
                return img
            last = img
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def _viewer(scene, st, tmp: Path, out_dir: Path) -> dict:
    """PSNR of the SuperSplat viewer's picture of our .spz against our render of its camera."""
    import json

    import jax.numpy as jnp
    from PIL import Image

    import jaxedit
    from jaxedit import camera as camlib
    from jaxedit import metrics
    from jaxedit.io import load_scene, save_scene, transform_gaussians, upright

    scene = transform_gaussians(scene, upright("+z"))  # as `export --up +z`: upright in viewers
    means = np.asarray(scene.means)[np.asarray(scene.alive)]
    target = np.median(means, axis=0)
    extent = float(np.percentile(np.linalg.norm(means - target, axis=1), 95))
    # The viewer's camera looks at its target with its world's +y up, the PLY's -y: look along x.
    eye, fov, size = target + np.array([2.2 * extent, 0.0, 0.0]), 50.0, 512
    to_viewer = np.array([-1.0, -1.0, 1.0])  # its world is the PLY's turned 180 degrees about z
    off = {"enabled": False}
    settings = {"version": 2, "tonemapping": "none", "highPrecisionRendering": False,
                "background": {"color": [1, 1, 1]}, "animTracks": [], "annotations": [],
                "startMode": "default",
                "postEffectSettings": {"sharpness": {**off, "amount": 0},
                                       "bloom": {**off, "intensity": 1, "blurLevel": 2},
                                       "grading": {**off, "brightness": 0, "contrast": 1,
                                                   "saturation": 1, "tint": [1, 1, 1]},
                                       "vignette": {**off, "intensity": 0.5, "inner": 0.3,
                                                    "outer": 0.75, "curvature": 1},
                                       "fringing": {**off, "intensity": 0.5}},
                "cameras": [{"initial": {"position": (to_viewer * eye).tolist(),
                                         "target": (to_viewer * target).tolist(), "fov": fov}}]}
    (tmp / "settings.json").write_text(json.dumps(settings))
    ours = save_scene(tmp / "viewer_scene.spz", scene)
    subprocess.run([*st, "-q", "-w", "-g", "cpu", "--viewer-settings", str(tmp / "settings.json"),
                    str(ours), str(tmp / "viewer.html")], check=True, capture_output=True, timeout=600)
    shot = _screenshot((tmp / "viewer.html").as_uri() + "?noui&noanim&webgl", size, tmp)
    cam = camlib.make_camera(camlib.look_at(eye, target, up=(0.0, -1.0, 0.0)), width=size,
                             height=size, focal=size / 2 / np.tan(np.radians(fov / 2)))
    rgb = np.clip(np.asarray(jaxedit.render(load_scene(ours), cam, background=jnp.ones(3)).rgb), 0, 1)
    out_dir.mkdir(parents=True, exist_ok=True)
    Image.fromarray((np.concatenate([shot, rgb], 1) * 255).round().astype(np.uint8)).save(
        out_dir / "formats_viewer.png")
    return {"viewer": "SuperSplat viewer in splat-transform 3.7.0's .html, headless Chromium, SwiftShader",
            "format": "spz", "size": [size, size], "fov_deg": fov, "eye": eye.tolist(),
            "target": target.tolist(), "psnr_db": float(metrics.psnr(shot, rgb)),
            "image": "formats_viewer.png (viewer left, ours right)"}


def _best_seconds(fn, repeats) -> tuple[float, float]:
    """(best wall seconds, best CPU seconds of this process) of ``repeats`` calls of ``fn``."""
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return min(wall), min(cpu)


def _random_gaussians(n, seed=0):
    from jaxedit.io.formats.common import Splats, to_gaussians

    rng = np.random.default_rng(seed)
    sh = np.concatenate([rng.normal(0, 0.8, (n, 1, 3)), rng.normal(0, 0.15, (n, 15, 3))], 1)
    quats = rng.normal(size=(n, 4))
    return to_gaussians(Splats(rng.normal(size=(n, 3)).astype(np.float32),
                               rng.normal(-3.5, 0.5, (n, 3)).astype(np.float32),
                               quats.astype(np.float32), rng.normal(1.0, 1.5, n).astype(np.float32),
                               sh.astype(np.float32)))


def _scene_and_cameras(args):
    from jaxedit import camera as camlib
    from jaxedit import gaussians as G
    from jaxedit.io import load_nerfstudio, load_scene

    if args.scene is not None:
        if args.data is None:
            raise SystemExit("--scene needs --data (the cameras to render)")
        data = load_nerfstudio(args.data)
        views = data.test_indices if len(data.test_indices) else data.train_indices
        return G.compact(load_scene(args.scene)), data.cameras[views], str(args.scene)
    n = 3000 if args.smoke else 20000
    g = _random_gaussians(n, seed=1)
    g = type(g)(**{**g.__dict__, "means": g.means * 0.5, "log_scales": g.log_scales - 0.5})
    return g, camlib.orbit(4 if args.smoke else 8, radius=4.0, width=64, height=64, fov_deg=50), \
        f"random, {n} Gaussians"


def _quality(args, st, tmp: Path) -> dict:
    import jax.numpy as jnp

    import jaxedit
    from jaxedit import gaussians as G
    from jaxedit import metrics
    from jaxedit.io import load_scene, save_ply, save_scene

    scene, cams, label = _scene_and_cameras(args)
    n, degree = scene.capacity, scene.sh_degree

    def render(g):  # one shape for every format: degree-3 SH, the scene's count
        g = G.with_sh_degree(G.compact(g), degree)
        assert g.capacity == n, (g.capacity, n)
        return np.asarray(jaxedit.render(g, cams, background=jnp.ones(3)).rgb)

    reference = render(scene)

    def psnr(g):
        return float(np.mean(metrics.psnr(render(g), reference)))

    def st_run(*a):
        subprocess.run([*st, "-q", "-w", *map(str, a)], check=True, capture_output=True, timeout=600)

    source = save_ply(tmp / "scene.ply", scene)
    out = {"scene": label, "gaussians": n, "sh_degree": degree, "views": int(reference.shape[0]),
           "view_size": list(reference.shape[1:3]), "ply_bytes": source.stat().st_size,
           "splat_transform": st is not None, "formats": {}}
    for fmt in ("compressed-ply", "spz", "sog", "splat"):
        ours = save_scene(tmp / f"ours{SUFFIX[fmt]}", scene)
        row = {"ours_bytes": ours.stat().st_size, "ours_psnr_db": psnr(load_scene(ours))}
        if st is not None:
            st_run(ours, tmp / f"ours_by_st_{fmt}.ply")
            row["ours_read_by_splat_transform_psnr_db"] = psnr(load_their_ply(tmp / f"ours_by_st_{fmt}.ply"))
            if fmt in THEIRS:
                theirs = tmp / f"theirs{SUFFIX[fmt]}"
                st_run(*(["-g", "cpu"] if fmt == "sog" else []), source, theirs)
                row.update(theirs_bytes=theirs.stat().st_size,
                           theirs_psnr_db=psnr(load_scene(theirs)),
                           size_ours_over_theirs=ours.stat().st_size / theirs.stat().st_size)
        out["formats"][fmt] = row
        print(fmt, row, flush=True)
    return out


def _speed(args) -> dict:
    from jaxedit.io import load_scene, save_scene

    repeats = args.repeats or (1 if args.smoke else 3)
    formats = [f.strip() for f in args.formats.split(",") if f.strip()]
    unknown = sorted(set(formats) - set(SPEED_FORMATS))
    if unknown:
        raise SystemExit(f"--formats: unknown {', '.join(unknown)} (of {', '.join(SPEED_FORMATS)})")
    out = {}
    tmp = Path(tempfile.mkdtemp(prefix="jaxedit-formats-speed-"))
    try:
        for fmt in formats:
            n = (2000 if fmt == "sog" else 20_000) if args.smoke else 1_000_000
            g = _random_gaussians(n)
            path = tmp / f"speed{SUFFIX[fmt]}"
            reps = 1 if fmt == "sog" else repeats  # SOG: minutes a write at this size
            load_before = os.getloadavg()[0]
            t_write, c_write = _best_seconds(lambda: save_scene(path, g), reps)
            t_read, c_read = _best_seconds(lambda: load_scene(path), reps)
            out[fmt] = {"gaussians": n, "sh_degree": 3, "bytes": path.stat().st_size,
                        "repeats": reps, "write_s": t_write, "write_cpu_s": c_write,
                        "read_s": t_read, "read_cpu_s": c_read,
                        "write_gaussians_per_s": n / t_write,
                        "write_gaussians_per_cpu_s": n / c_write,
                        "read_gaussians_per_s": n / t_read,
                        "read_gaussians_per_cpu_s": n / c_read,
                        "load_average_1m": [load_before, os.getloadavg()[0]]}
            print(fmt, out[fmt], flush=True)
            path.unlink()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv, extra=_extra)
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    if not parts or set(parts) - set(PARTS):
        raise SystemExit(f"--parts: a comma list of {', '.join(PARTS)}, got {args.parts!r}")
    st = find_splat_transform(args.splat_transform)
    load_at_start = os.getloadavg()[0]
    previous = Path(args.out) / "formats.json"
    results, kept = {}, {}
    if set(parts) != set(PARTS) and previous.is_file():  # the parts not run are kept
        kept = json.loads(previous.read_text())
        results = {k: v for k, v in kept.items() if k in PARTS and k not in parts}
    results["smoke"] = args.smoke
    tmp = Path(tempfile.mkdtemp(prefix="jaxedit-formats-"))
    try:
        if "quality" in parts:
            results["quality"] = _quality(args, st, tmp)
        chromium = shutil.which("chromium") or shutil.which("chromium-browser")
        if "viewer" in parts and st is not None and chromium is not None and not args.smoke:
            from jaxedit import gaussians as G

            results["viewer"] = _viewer(G.compact(_scene_and_cameras(args)[0]), st, tmp, args.out)
        if "speed" in parts:  # the formats not timed keep their figures
            results["speed"] = {**kept.get("speed", {}), **_speed(args)}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if st is None:
        results["note"] = "splat-transform not found: its columns are missing"
    results["parts_run"] = parts
    results["peak_rss_mb"] = peak_rss_mb()
    # other work on the machine slows the timings: the load before and after this run
    results["load_average_1m"] = {"start": load_at_start, "end": os.getloadavg()[0]}
    write_json(args.out, "formats", results)


if __name__ == "__main__":
    main()
