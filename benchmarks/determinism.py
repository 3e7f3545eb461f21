"""Are the splatter's outputs and gradients bit-identical from one run to the next?

    python benchmarks/determinism.py [--smoke] [--out DIR] [--rows WxHxN,...]
                                     [--backends pallas,xla]

For each scene of ``benchmarks/raster.py`` and each backend, the forward image and
the gradient of ``sum(image * w)`` with respect to every Gaussian parameter are
computed twice by the same compiled program and compared bit for bit (NumPy
``array_equal``). The Pallas backend sums each Gaussian's gradient rows in a fixed
order (``reduce_pair_rows``); the XLA path's scatter-add is free to reorder its
additions on a GPU. Writes DIR/determinism.json with ``{WxH}_{backend}_bitwise_identical``
(and the largest difference where they differ), the record behind
``benchmarks/results/h100/determinism.json``. ``--smoke``: 64 px / 2k on the CPU.
"""

from __future__ import annotations

import numpy as np

from common import parse_args, write_json  # noqa: E402  (sets sys.path)
from raster import scene  # noqa: E402

ROWS = [(512, 512, 200_000), (1920, 1080, 1_000_000)]
SMOKE_ROWS = [(64, 64, 2_000)]


def twice(g, cam, backend: str):
    """Two (image, gradients) results of one compiled fwd+bwd, as NumPy leaves."""
    import jax
    import jax.numpy as jnp

    from jaxedit.raster import render_tiles
    from jaxedit.raster.render import HEADROOM, count_pairs, next_capacity

    cap = next_capacity(count_pairs(g, cam, backend=backend) * HEADROOM)
    w = jnp.asarray(np.random.default_rng(1).normal(size=(cam.height, cam.width, 3)), jnp.float32)

    def loss(g):
        rgb = render_tiles(g, cam, capacity=cap, backend=backend).rgb
        return jnp.sum(rgb * w), rgb

    fn = jax.jit(jax.value_and_grad(loss, has_aux=True, allow_int=True))
    return [[np.asarray(x) for x in jax.tree_util.tree_leaves(fn(g))] for _ in range(2)]


def compare(g, cam, backend: str) -> dict:
    a, b = twice(g, cam, backend)
    same = all(np.array_equal(x, y) for x, y in zip(a, b))
    diff = max((float(np.max(np.abs(x.astype(np.float64) - y.astype(np.float64))))
                for x, y in zip(a, b) if x.dtype.kind == "f" and x.size), default=0.0)
    return {"bitwise_identical": same, "max_abs_difference": diff}


def main(argv=None):
    def extra(p):
        p.add_argument("--rows", default=None, help="scenes, e.g. 512x512x200000 (default: all)")
        p.add_argument("--backends", default="pallas,xla")

    args = parse_args(__doc__.splitlines()[0], argv, extra)
    import jax

    rows = SMOKE_ROWS if args.smoke else ROWS
    if args.rows:
        rows = [tuple(int(v) for v in r.split("x")) for r in args.rows.split(",")]
    out = {"platform": jax.default_backend(), "smoke": bool(args.smoke)}
    for width, height, n in rows:
        g, cam = scene(n, width, height=height)
        for backend in [b for b in args.backends.split(",") if b]:
            try:
                rec = compare(g, cam, backend)
            except Exception as e:  # noqa: BLE001  (e.g. out of memory: recorded, go on)
                out[f"{width}x{height}_{backend}_error"] = f"{type(e).__name__}: {e}"[:300]
                continue
            out[f"{width}x{height}_{backend}_bitwise_identical"] = rec["bitwise_identical"]
            out[f"{width}x{height}_{backend}_max_abs_difference"] = rec["max_abs_difference"]
            print(f"{width}x{height} / {n} {backend}: {rec}", flush=True)
        write_json(args.out, "determinism", out)


if __name__ == "__main__":
    main()
