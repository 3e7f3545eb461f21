"""Built-in scenes and the photometric loss: ray-casting time and SSIM loss cost.

* ray caster: wall and CPU time to render ``views + test_views`` views of each built-in
  scene (default 72 views of 128 x 128, 2 x 2 supersampling), time for the point cloud,
  and the whole ``make_scene`` (PNG + PLY writing included);
* loss: jitted value-and-grad of ``photometric_loss`` (0.8 L1 + 0.2 D-SSIM) per image
  size, plus the SSIM agreement with scikit-image on a rendered view.

    python benchmarks/scenes.py [--smoke] [--out DIR]
"""

from __future__ import annotations

import tempfile
import time

import numpy as np
from common import parse_args, peak_rss_mb, time_fn, write_json

import jax
import jax.numpy as jnp

from jaxedit import losses, metrics, scenes


def timed(fn, *args, **kw):
    w0, c0 = time.perf_counter(), time.process_time()
    out = fn(*args, **kw)
    return out, time.perf_counter() - w0, time.process_time() - c0


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv)
    size, views, test_views = (32, 6, 2) if args.smoke else (128, 64, 8)
    names = ["face"] if args.smoke else ["face", "tabletop", "fence"]
    num_points = 500 if args.smoke else 4000
    rows = []
    for name in names:
        scene = scenes.get_scene(name)
        cams, train, test = scenes.scene_cameras(scene, views=views, test_views=test_views, size=size)
        images, wall, cpu = timed(scenes.render_scene, scene, cams)
        _, pwall, pcpu = timed(scenes.sample_points, scene, cams[train], num_points,
                               np.random.default_rng(0))
        with tempfile.TemporaryDirectory() as tmp:
            _, mwall, mcpu = timed(scenes.make_scene, name, tmp, size=size, views=views,
                                   test_views=test_views, num_points=num_points)
        row = {"scene": name, "views": views + test_views, "size": size, "supersample": 2,
               "render_wall_s": wall, "render_cpu_s": cpu,
               "render_ms_per_view": 1e3 * wall / len(images),
               "points_wall_s": pwall, "points_cpu_s": pcpu,
               "make_scene_wall_s": mwall, "make_scene_cpu_s": mcpu}
        rows.append(row)
        print(f"{name}: render {wall:.2f} s wall / {cpu:.2f} s CPU for {len(images)} views, "
              f"points {pwall:.2f} s wall / {pcpu:.2f} s CPU, make_scene {mwall:.2f} s")

    # SSIM agreement on a real target: a view against a slightly shifted one.
    ref = images[0]
    other = np.roll(ref, 1, axis=1)
    ssim_err = abs(float(losses.ssim(ref, other)) - metrics.ssim_skimage(ref, other))

    loss_rows = []
    for s in ([32] if args.smoke else [64, 128, 256, 512]):
        rng = np.random.default_rng(0)
        a = jnp.asarray(rng.uniform(size=(s, s, 3)), jnp.float32)
        b = jnp.asarray(rng.uniform(size=(s, s, 3)), jnp.float32)
        fn = jax.jit(jax.value_and_grad(losses.photometric_loss))
        timing = time_fn(fn, a, b, repeats=args.repeats or (3 if args.smoke else 10))
        loss_rows.append({"size": s, **timing})
        print(f"photometric loss value+grad {s}x{s}: {timing['median_ms']:.2f} ms "
              f"(compile {timing['compile_ms']:.0f} ms)")
    write_json(args.out, "scenes", {"smoke": args.smoke, "raycast": rows, "loss": loss_rows,
                                    "ssim_abs_error_vs_skimage": ssim_err,
                                    "peak_rss_mb": peak_rss_mb(),
                                    "note": "CPU timings on a shared machine are noisy"})


if __name__ == "__main__":
    main()
