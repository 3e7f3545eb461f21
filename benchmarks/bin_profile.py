"""Where a frame's time goes, stage by stage: binning and its sorts, the kernels, the reduction.

    python benchmarks/bin_profile.py [--smoke] [--out DIR] [--repeats R] [--rows WxHxN,...]

For each scene of ``benchmarks/raster.py`` (512 px / 200k and 1080p / 1M by default)
this times, each jitted and compiled on its own (median ms, device synced):

* ``bin_current``: :func:`jaxedit.raster.binning.bin_gaussians` at the Pallas tile
  size, the binning the renderer runs (after projection, which is not counted);
* the sorts it could be built on, over the same number of keys as the buffer:
  ``sort_keys_i32`` (one int32 key array), ``argsort_stable_u32`` / ``_i32``
  (stable argsort, GPU radix), ``sort_pairs_u32_unstable`` (key + payload) and
  ``sort_twokey`` (two-key lexicographic sort);
* ``enumerate_cummax``: the pair-owner scan of the enumeration (a scatter of run
  starts and a running maximum over the buffer), ``enumerate_searchsorted``: the
  same from a binary search per slot;
* ``kernel_fwd`` / ``kernel_bwd``: the Pallas forward and backward kernels on the
  binned pairs (given their inputs), ``reduce_pallas``: the fixed-order per-Gaussian
  sum of the backward's rows, ``reduce_segment_sum``: the same with XLA's
  scatter-add (``reduce_bitwise_deterministic``: whether two of those agree bit for bit);
* ``pairs_used_frac``: pairs used / buffer size, ``cap``: the buffer size.

The results behind ``benchmarks/results/h100/bin_profile.json`` came from an earlier,
one-off version of this script that also timed binning prototypes no longer in the
tree (scan-based enumerations, the stable variants of ``bin``); the stages that
still exist keep their names. Off a GPU the kernels run in the Pallas interpreter
(``--smoke``: 64 px / 2k, CPU, seconds). Writes DIR/bin_profile.json.
"""

from __future__ import annotations

import time

import numpy as np

from common import parse_args, write_json  # noqa: E402  (sets sys.path)
from raster import scene  # noqa: E402

ROWS = [(512, 512, 200_000), (1920, 1080, 1_000_000)]
SMOKE_ROWS = [(64, 64, 2_000)]


def timed(fn, *args, repeats: int) -> float:
    """Median ms of ``repeats`` synced calls of ``fn`` (jitted, compiled first)."""
    import jax

    compiled = jax.jit(fn).lower(*args).compile()
    jax.block_until_ready(compiled(*args))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - t0)
    return round(1e3 * float(np.median(times)), 3)


def profile(width: int, height: int, n: int, repeats: int) -> dict:
    import jax
    import jax.numpy as jnp

    from jaxedit.raster import binning as B
    from jaxedit.raster import pallas as PK
    from jaxedit.raster import project as P
    from jaxedit.raster.render import HEADROOM, PALLAS_TILE, next_capacity

    interpret = PK.use_interpreter()
    g, cam = scene(n, width, height=height)
    proj = jax.jit(lambda g: P.project(g, cam, sh_degree=3))(g)
    tile = PALLAS_TILE
    needed = int(B.count_intersections(proj, width, height, tile))
    cap = next_capacity(needed * HEADROOM)
    tag = f"{width}x{height}"
    rec = {f"{tag}_cap": cap, f"{tag}_pairs_used_frac": needed / cap}
    rec[f"{tag}_bin_current"] = timed(lambda p: B.bin_gaussians(p, width, height, cap, tile),
                                      proj, repeats=repeats)
    bins = jax.jit(lambda p: B.bin_gaussians(p, width, height, cap, tile))(proj)

    rng = np.random.default_rng(0)
    num_tiles = int(np.prod(B.grid_shape(width, height, tile)))
    keys = jnp.asarray(rng.integers(0, num_tiles, cap), jnp.int32)
    payload = jnp.arange(cap, dtype=jnp.int32)
    sorts = {
        "sort_keys_i32": (lambda k: jax.lax.sort(k), keys),
        "argsort_stable_u32": (lambda k: jnp.argsort(k.astype(jnp.uint32), stable=True), keys),
        "argsort_stable_i32": (lambda k: jnp.argsort(k, stable=True), keys),
        "sort_pairs_u32_unstable": (lambda k: jax.lax.sort((k.astype(jnp.uint32), payload),
                                                           num_keys=1, is_stable=False), keys),
        "sort_twokey": (lambda k: jax.lax.sort((k, payload), num_keys=2), keys),
    }
    for name, (fn, arg) in sorts.items():
        rec[f"{tag}_{name}"] = timed(fn, arg, repeats=repeats)

    counts = jnp.asarray(np.diff(np.asarray(bins.run_ends), prepend=0), jnp.int32)
    starts = jnp.cumsum(counts) - counts
    slots = jnp.arange(cap, dtype=jnp.int32)
    rec[f"{tag}_enumerate_cummax"] = timed(lambda c: B._pair_owners(c, cap), counts,
                                           repeats=repeats)
    rec[f"{tag}_enumerate_searchsorted"] = timed(
        lambda s: jnp.searchsorted(s, slots, side="right") - 1, starts, repeats=repeats)

    feats = jnp.concatenate([proj.colors, proj.depths[:, None]], -1)
    args = (proj.means2d, proj.conics, proj.opacities, feats, bins.gids, bins.tile_start)
    rec[f"{tag}_kernel_fwd"] = timed(lambda *a: PK.tiles_forward(
        *a, width, height, tile, interpret=interpret), *args, repeats=repeats)
    _, trans, last = PK.tiles_forward(*args, width, height, tile, interpret=interpret)
    g_feat = jnp.ones((num_tiles, feats.shape[-1], tile * tile), jnp.float32)
    g_trans = jnp.ones((num_tiles, tile * tile), jnp.float32)
    rec[f"{tag}_kernel_bwd"] = timed(lambda *a: PK.tiles_backward(
        *a, bins.enum_slots, trans, last, g_feat, g_trans, width, height, tile,
        interpret=interpret), *args, repeats=repeats)
    rows = PK.tiles_backward(*args, bins.enum_slots, trans, last, g_feat, g_trans, width, height,
                             tile, interpret=interpret)
    rec[f"{tag}_reduce_pallas"] = timed(lambda r: PK.reduce_pair_rows(
        r, bins.depth_order, bins.run_ends, interpret=interpret), rows, repeats=repeats)
    owner = jnp.full(rows.shape[0], n, jnp.int32).at[bins.enum_slots].set(bins.gids, mode="drop")

    def segment_sum(r):
        return jax.ops.segment_sum(r, owner, num_segments=n + 1)[:n]

    rec[f"{tag}_reduce_segment_sum"] = timed(segment_sum, rows, repeats=repeats)
    shuffled = jax.jit(segment_sum)
    a, b = np.asarray(shuffled(rows)), np.asarray(shuffled(rows))
    rec[f"{tag}_reduce_bitwise_deterministic"] = bool(np.array_equal(a, b))
    return rec


def main(argv=None):
    def extra(p):
        p.add_argument("--rows", default=None, help="scenes, e.g. 512x512x200000 (default: all)")

    args = parse_args(__doc__.splitlines()[0], argv, extra)
    import jax

    rows = SMOKE_ROWS if args.smoke else ROWS
    if args.rows:
        rows = [tuple(int(v) for v in r.split("x")) for r in args.rows.split(",")]
    repeats = args.repeats or (2 if args.smoke else 10)
    out = {"platform": jax.default_backend(), "smoke": bool(args.smoke), "repeats": repeats}
    for width, height, n in rows:
        rec = profile(width, height, n, repeats)
        out.update(rec)
        print(", ".join(f"{k}={v}" for k, v in rec.items()), flush=True)
        write_json(args.out, "bin_profile", out)


if __name__ == "__main__":
    main()
