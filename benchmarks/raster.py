"""Tile splatter speed: forward, forward+backward, compile time, memory, vs the dense oracle.

Scene (fixed for comparability, see issue 3): means ~ N(0, 0.5^2) per axis,
scales uniform in [0.01, 0.05], random quaternions, opacity sigmoid(N(0, 1)),
SH degree 3 (DC ~ N(0, 1), rest ~ N(0, 0.1)), camera 3 units from the origin
looking at it, focal = width.

    python benchmarks/raster.py [--smoke] [--out DIR] [--repeats R] [--sizes 128:10000,...]

Writes DIR/raster.json: per size the intersection statistics (at the 16 px tiles
of INRIA and at the splatter's compositing tiles), forward and forward+backward
times (median/min of R runs after compiling), compile times, a stage profile
(project, binning, chunk layout, compositing), XLA's temp-buffer size, the
process's peak RSS, and the oracle's times where it fits.
"""

from __future__ import annotations

import importlib
import time

import numpy as np

from common import parse_args, peak_rss_mb, time_fn, write_json  # noqa: E402  (sets sys.path)

SIZES = [(128, 10_000), (256, 50_000), (512, 200_000)]
SMOKE = [(64, 2_000)]
#: Oracle limits in pixel x Gaussian evaluations (forward; forward+backward keeps residuals).
ORACLE_FWD_MAX = 2e8
ORACLE_BWD_MAX = 3e7


def scene(n: int, size: int, seed: int = 0, height: int | None = None):
    """``n`` Gaussians and a camera of ``size`` x ``height`` (default square) pixels, focal = width."""
    import jax.numpy as jnp

    from jaxedit import camera as cam_lib
    from jaxedit.gaussians import Gaussians

    rng = np.random.default_rng(seed)
    sh = np.zeros((n, 16, 3), np.float32)
    sh[:, 0] = rng.normal(0.0, 1.0, (n, 3))
    sh[:, 1:] = rng.normal(0.0, 0.1, (n, 15, 3))
    g = Gaussians(means=jnp.asarray(rng.normal(0.0, 0.5, (n, 3)), jnp.float32),
                  log_scales=jnp.asarray(np.log(rng.uniform(0.01, 0.05, (n, 3))), jnp.float32),
                  quats=jnp.asarray(rng.normal(size=(n, 4)), jnp.float32),
                  opacity_logits=jnp.asarray(rng.normal(0.0, 1.0, n), jnp.float32),
                  sh=jnp.asarray(sh), alive=jnp.ones(n, bool))
    cam = cam_lib.make_camera(cam_lib.look_at((3.0, 0.0, 0.0), (0.0, 0.0, 0.0)), width=size,
                              height=height or size, focal=float(size))
    return g, cam


def tile_stats(proj, size: int, tile: int) -> dict:
    from jaxedit.raster import binning as B

    x0, y0, nx, ny = (np.asarray(a) for a in B.tile_rects(proj, size, size, tile))
    tiles_x, _ = B.grid_shape(size, size, tile)
    counts = np.zeros(tiles_x * tiles_x, np.int64)
    for i in np.nonzero(nx * ny)[0]:
        rows = np.arange(y0[i], y0[i] + ny[i])[:, None] * tiles_x
        counts[(rows + np.arange(x0[i], x0[i] + nx[i])[None]).ravel()] += 1
    return {"tile": tile, "intersections": int(counts.sum()), "busiest_tile": int(counts.max()),
            "median_tile": float(np.median(counts)), "empty_tiles": int((counts == 0).sum())}


def compile_and_time(jitted, *args, repeats: int) -> dict:
    """Compile ahead of time (timed), then time the compiled call; XLA temp buffer size."""
    import jax

    t0 = time.perf_counter()
    compiled = jitted.lower(*args).compile()
    compile_ms = 1e3 * (time.perf_counter() - t0)
    rec = time_fn(compiled, *args, repeats=repeats)
    rec["compile_ms"] = compile_ms
    # CPU time of the process per call: steadier than wall time on a shared machine
    # (XLA's CPU runtime ran these programs on one thread in our measurements).
    cpu = []
    for _ in range(repeats):
        c0 = time.process_time()
        jax.block_until_ready(compiled(*args))
        cpu.append(time.process_time() - c0)
    rec["cpu_median_ms"] = 1e3 * float(np.median(cpu))
    try:
        rec["xla_temp_mb"] = round(compiled.memory_analysis().temp_size_in_bytes / 2**20, 1)
    except Exception:  # memory_analysis is best-effort on some backends
        rec["xla_temp_mb"] = None
    return rec


def bench_size(size: int, n: int, repeats: int, profile: bool = True) -> dict:
    import jax
    import jax.numpy as jnp

    R = importlib.import_module("jaxedit.raster.render")
    from jaxedit.raster import binning as B, project as P
    from jaxedit.raster.reference import render_reference

    g, cam = scene(n, size)
    proj = jax.jit(lambda g: P.project(g, cam))(g)
    needed = int(B.count_intersections(proj, size, size, R.TILE))
    cap = R.next_capacity(needed * R.HEADROOM)
    rec = {"size": size, "gaussians": n, "visible": int(np.asarray(proj.visible).sum()),
           "capacity": cap, "compositing_tile": R.TILE,
           "stats_tile16": tile_stats(proj, size, 16), "stats_compositing": tile_stats(proj, size, R.TILE)}
    w = jnp.asarray(np.random.default_rng(1).normal(size=(size, size, 3)), jnp.float32)

    fwd = jax.jit(lambda g: R.render_tiles(g, cam, capacity=cap).rgb)
    out = R.render_tiles(g, cam, capacity=cap)
    assert not bool(out.overflow)

    def loss(g, w):  # w is an argument, not a constant XLA would fold at compile time
        return jnp.sum(R.render_tiles(g, cam, capacity=cap).rgb * w)

    fwd_bwd = jax.jit(jax.value_and_grad(loss, allow_int=True))
    rec["forward"] = compile_and_time(fwd, g, repeats=repeats)
    rec["forward_backward"] = compile_and_time(fwd_bwd, g, w, repeats=repeats)
    if profile:
        rec["stages_ms"] = stage_profile(g, cam, proj, size, cap, w, max(2, repeats // 2))

    evals = size * size * n
    if evals <= ORACLE_FWD_MAX:
        ref = jax.jit(lambda g: render_reference(g, cam).rgb)
        rec["oracle_forward"] = compile_and_time(ref, g, repeats=max(1, repeats // 3))
        rec["max_abs_diff_vs_oracle"] = float(jnp.max(jnp.abs(ref(g) - fwd(g))))
        rec["speedup_forward"] = rec["oracle_forward"]["median_ms"] / rec["forward"]["median_ms"]
    else:
        rec["oracle_forward"] = f"skipped: {evals:.1e} pixel x Gaussian evaluations"
    if profile and evals <= ORACLE_BWD_MAX:
        ref_bwd = jax.jit(jax.value_and_grad(
            lambda g, w: jnp.sum(render_reference(g, cam).rgb * w), allow_int=True))
        rec["oracle_forward_backward"] = compile_and_time(ref_bwd, g, w,
                                                          repeats=max(1, repeats // 3))
        rec["speedup_forward_backward"] = (rec["oracle_forward_backward"]["median_ms"]
                                           / rec["forward_backward"]["median_ms"])
    else:
        rec["oracle_forward_backward"] = f"skipped: {evals:.1e} evaluations (residual memory)"
    rec["peak_rss_mb_so_far"] = round(peak_rss_mb(), 1)
    return rec


def stage_profile(g, cam, proj, size, cap, w, reps) -> dict:
    """Median ms of each stage, jitted on its own (their sum exceeds the fused whole)."""
    import jax
    import jax.numpy as jnp

    R = importlib.import_module("jaxedit.raster.render")
    from jaxedit.raster import binning as B, composite as CP, project as P

    # Stage profile (each stage jitted on its own; sums exceed the fused whole slightly).
    tiles_x, tiles_y = B.grid_shape(size, size, R.TILE)
    bins_fn = jax.jit(lambda p: B.bin_gaussians(p, size, size, cap, R.TILE))
    bins = bins_fn(proj)
    chunk_fn = jax.jit(lambda b: CP.make_chunks(b, tiles_x * tiles_y, cap, R.TILE))
    gids, tile_of, first = chunk_fn(bins)
    feats = jnp.concatenate([proj.colors, proj.depths[:, None]], -1)
    # Layout arrays and weights are arguments: as closed-over constants XLA would
    # spend the compile constant-folding them.
    comp_fn = jax.jit(lambda m, c, o, f, gids, tile_of, first: CP.composite(
        m, c, o, f, gids, tile_of, first, size, size, R.TILE))

    def comp_loss(m, c, o, f, gids, tile_of, first, w):
        img, trans = CP.composite(m, c, o, f, gids, tile_of, first, size, size, R.TILE)
        return jnp.sum(img[..., :3] * w) + jnp.sum(trans)

    comp_grad = jax.jit(jax.grad(comp_loss, argnums=(0, 1, 2, 3)))
    comp_args = (proj.means2d, proj.conics, proj.opacities, feats, gids, tile_of, first)
    return {
        "project": time_fn(jax.jit(lambda g: P.project(g, cam)), g, repeats=reps)["median_ms"],
        "binning": time_fn(bins_fn, proj, repeats=reps)["median_ms"],
        "chunk_layout": time_fn(chunk_fn, bins, repeats=reps)["median_ms"],
        "composite_forward": time_fn(comp_fn, *comp_args, repeats=reps)["median_ms"],
        "composite_forward_backward": time_fn(comp_grad, *comp_args, w, repeats=reps)["median_ms"],
    }


def main(argv=None):
    def extra(p):
        p.add_argument("--sizes", default=None, help="e.g. 128:10000,256:50000")

    args = parse_args(__doc__.splitlines()[0], argv, extra)
    if args.sizes:
        sizes = [tuple(int(v) for v in s.split(":")) for s in args.sizes.split(",")]
    else:
        sizes = SMOKE if args.smoke else SIZES
    repeats = args.repeats or (2 if args.smoke else 7)
    results = []
    for size, n in sizes:
        t0 = time.perf_counter()
        rec = bench_size(size, n, repeats, profile=not args.smoke)
        rec["wall_s"] = round(time.perf_counter() - t0, 1)
        print(f"{size}px {n} Gaussians: fwd {rec['forward']['median_ms']:.1f} ms "
              f"(cpu {rec['forward']['cpu_median_ms']:.1f}), "
              f"fwd+bwd {rec['forward_backward']['median_ms']:.1f} ms "
              f"(cpu {rec['forward_backward']['cpu_median_ms']:.1f}), "
              f"pairs {rec['stats_compositing']['intersections']} (16px tiles: "
              f"{rec['stats_tile16']['intersections']}), stages {rec.get('stages_ms')}", flush=True)
        results.append(rec)
    write_json(args.out, "raster", {
        "smoke": bool(args.smoke), "results": results,
        "goals_ms": {"128px_10k_forward": 20, "128px_10k_forward_backward": 60,
                     "256px_50k_forward_backward": 600},
        "note": "CPU timings on a shared machine are noisy; medians after one compile call.",
    })


if __name__ == "__main__":
    main()
