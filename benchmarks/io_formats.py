"""Throughput of jaxedit.io: 3DGS .ply save/load and nerfstudio dataset loading.

    python benchmarks/io_formats.py [--smoke] [--out DIR]

Measures (median of a few repeats, seconds and items per second):
  * save_ply / load_ply of N Gaussians at SH degree 3 (the INRIA layout),
  * load_nerfstudio of V views (PNG), pinhole and OPENCV (undistortion on load),
    and with downscale 2.
Writes DIR/io_formats.json. Timings on a shared machine are noisy.
"""

from __future__ import annotations

import dataclasses
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from common import parse_args, peak_rss_mb, write_json  # noqa: E402  (sets sys.path)


def _median_seconds(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv)
    import jax.numpy as jnp

    from jaxedit import camera as camlib
    from jaxedit import gaussians as G
    from jaxedit.io import load_nerfstudio, load_ply, save_nerfstudio, save_ply

    n_gauss = 20_000 if args.smoke else 1_000_000
    views, size = (4, (64, 48)) if args.smoke else (40, (640, 480))
    repeats = args.repeats or (1 if args.smoke else 3)
    rng = np.random.default_rng(0)
    tmp = Path(tempfile.mkdtemp(prefix="jaxedit-io-bench-"))
    results = {"smoke": args.smoke}
    try:
        g = G.empty(n_gauss, 3)
        g = dataclasses.replace(
            g, means=jnp.asarray(rng.normal(size=(n_gauss, 3)).astype(np.float32)),
            sh=jnp.asarray(rng.normal(size=(n_gauss, 16, 3)).astype(np.float32)),
            alive=jnp.ones((n_gauss,), bool))
        path = tmp / "scene.ply"
        t_save = _median_seconds(lambda: save_ply(path, g), repeats)
        t_load = _median_seconds(lambda: load_ply(path), repeats)
        mb = path.stat().st_size / 2**20
        results["ply"] = {"gaussians": n_gauss, "sh_degree": 3, "file_mb": round(mb, 1),
                          "save_s": t_save, "load_s": t_load,
                          "save_mb_per_s": mb / t_save, "load_mb_per_s": mb / t_load}

        w, h = size
        cams = camlib.orbit(views, radius=3.0, width=w, height=h, fov_deg=50)
        images = rng.uniform(size=(views, h, w, 3)).astype(np.float32)
        ds_path = save_nerfstudio(tmp / "ds", images, cams)
        t_pin = _median_seconds(lambda: load_nerfstudio(ds_path), repeats)
        # cache=False: every repeat decodes (the view cache would read the first one's back)
        t_down = _median_seconds(lambda: load_nerfstudio(ds_path, downscale=2, cache=False),
                                 repeats)
        import json

        meta = json.loads(ds_path.read_text())
        meta.update(camera_model="OPENCV", k1=-0.1, k2=0.02, p1=0.001, p2=-0.001)
        ds_path.write_text(json.dumps(meta))
        t_dist = _median_seconds(lambda: load_nerfstudio(ds_path, cache=False), repeats)
        results["nerfstudio"] = {
            "views": views, "width": w, "height": h,
            "pinhole_s": t_pin, "pinhole_views_per_s": views / t_pin,
            "downscale2_s": t_down,
            "opencv_undistort_s": t_dist, "opencv_views_per_s": views / t_dist,
        }
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    results["peak_rss_mb"] = peak_rss_mb()
    for k, v in results.items():
        print(k, v)
    write_json(args.out, "io_formats", results)


if __name__ == "__main__":
    main()
