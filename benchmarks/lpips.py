"""LPIPS (JAX) speed: jitted distance of one pair and of a batch of views, VGG and AlexNet.

The real converted weights are used where they are (``~/.cache/jaxedit/weights``, see the
README); otherwise a random trunk and heads of exactly LPIPS-vgg / LPIPS-alex's shapes, since
the cost does not depend on the weight values (the JSON records which). The difficulty of
ProEdit evaluates one LPIPS per (view, ratio pair), so the per-pair time at the training
resolution is the figure that matters.

    python benchmarks/lpips.py [--smoke] [--out DIR]
"""

from __future__ import annotations

import numpy as np
from common import parse_args, peak_rss_mb, time_fn, write_json

import jax
import jax.numpy as jnp

from jaxedit.io.weights import default_lpips_weights
from jaxedit.lpips import ARCHITECTURES, LPIPS, LPIPSParams, Conv, load_lpips


def random_lpips(net: str, seed: int = 0) -> LPIPS:
    rng = np.random.default_rng(seed)
    convs = [op for stage in ARCHITECTURES[net] for op in stage if isinstance(op, Conv)]
    w = tuple(jnp.asarray(rng.normal(0, (2 / (c.cin * c.kernel ** 2)) ** 0.5,
                                     (c.kernel, c.kernel, c.cin, c.cout)), jnp.float32)
              for c in convs)
    b = tuple(jnp.zeros((c.cout,), jnp.float32) for c in convs)
    taps = [[op for op in st if isinstance(op, Conv)][-1].cout for st in ARCHITECTURES[net]]
    heads = tuple(jnp.asarray(rng.uniform(0, 0.1, (ch,)), jnp.float32) for ch in taps)
    return LPIPS(LPIPSParams(w, b, heads), net)


def lpips_model(net: str) -> tuple[LPIPS, str]:
    """(model, "real" | "random"): the converted weights when present, else random ones."""
    path = default_lpips_weights(net)
    return (load_lpips(path, net), "real") if path.is_file() else (random_lpips(net), "random")


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv)
    repeats = args.repeats or (2 if args.smoke else 5)
    cases = ([("alex", 64, 1)] if args.smoke else
             [(net, size, 1) for net in ("alex", "vgg") for size in (128, 256, 512)]
             + [("alex", 256, 4), ("vgg", 256, 4)])
    results = []
    for net, size, batch in cases:
        fn, weights = lpips_model(net)
        rng = np.random.default_rng(1)
        a = jnp.asarray(rng.uniform(0, 1, (batch, size, size, 3)), jnp.float32)
        b = jnp.asarray(rng.uniform(0, 1, (batch, size, size, 3)), jnp.float32)
        timing = time_fn(fn, a, b, repeats=repeats)
        row = {"net": net, "weights": weights, "size": size, "batch": batch, **timing,
               "ms_per_pair": timing["median_ms"] / batch}
        results.append(row)
        print(f"lpips-{net} {size}x{size} batch {batch}: {timing['median_ms']:.1f} ms "
              f"({row['ms_per_pair']:.1f} ms/pair), compile {timing['compile_ms']:.0f} ms")
    write_json(args.out, "lpips", {"smoke": args.smoke, "results": results,
                                   "peak_rss_mb": peak_rss_mb(), "backend": jax.default_backend()})


if __name__ == "__main__":
    main()
