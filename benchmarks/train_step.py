"""Time of one 3DGS train step, and of its parts.

    python benchmarks/train_step.py [--smoke] [--out DIR] [--size N] [--gaussians N]

On the built-in ``face`` scene (initial points sampled from its surfaces) this
times, each jitted on its own, with compile time reported separately:

* ``render_forward``: the tile splatter, one view;
* ``loss_and_grad``: render + 0.8 L1 + 0.2 D-SSIM, forward and backward;
* ``train_step``: the whole :func:`jaxedit.train.train_step` (grad, Adam,
  density-control statistics; a step without maintenance);
* ``train_step_refine``: the same at a maintenance step (cull + ranked creation);
* ``densify_update``: the density-control update alone at a maintenance step;
* ``train_chunk``: :func:`jaxedit.train.train_chunk`, ``CHUNK`` steps in one call
  (what :func:`jaxedit.train.fit` runs), and ``train_chunk_per_step`` = that / ``CHUNK``.

Writes ``DIR/train_step.json``. ``--smoke``: 32 x 32, 300 Gaussians, 3 repeats, only
``train_step`` and ``densify_update``.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
from common import parse_args, peak_rss_mb, time_fn, write_json


def extra(p):
    p.add_argument("--size", type=int, default=None, help="image size (default 128)")
    p.add_argument("--gaussians", type=int, default=None, help="Gaussians (default 20000)")


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv, extra)
    import jax
    import jax.numpy as jnp

    from jaxedit import densify as D
    from jaxedit import gaussians as G
    from jaxedit import scenes
    from jaxedit import train as T
    from jaxedit.losses import photometric_loss
    from jaxedit.raster.render import next_capacity, render_tiles

    size = args.size or (32 if args.smoke else 128)
    n = args.gaussians or (300 if args.smoke else 20_000)
    repeats = args.repeats or (3 if args.smoke else 10)

    scene = scenes.get_scene("face")
    cams, train, _ = scenes.scene_cameras(scene, views=8, test_views=0, size=size)
    images = scenes.render_scene(scene, cams, supersample=1)
    points, colors = scenes.sample_points(scene, cams, n, np.random.default_rng(0))
    g = G.from_points(points, colors, sh_degree=3)
    extent = T.scene_extent(cams)
    # Densify at step 1 (refine_every=1, warmup=0) for the maintenance timings.
    refine_cfg = T.TrainConfig(iterations=1000, densify=T.DensifyConfig(
        warmup=0, refine_every=1, stop_at=10**6, reset_every=0))
    plain_cfg = T.TrainConfig(iterations=1000)
    state = T.init_state(g, plain_cfg, extent, key=jax.random.key(0))
    batch, key = T.select_batch(images, cams, state.key, 0)
    # Grow the intersection buffer until one step fits (as fit does), then time from step 0.
    grown, _ = T.step_with_retry(state, batch, key)
    state = dataclasses.replace(state, max_intersections=grown.max_intersections)
    cap = state.max_intersections
    cam, target = batch.camera, jnp.asarray(batch.image)
    bg = jnp.ones(3)

    fwd = jax.jit(lambda gg: render_tiles(gg, cam, capacity=cap, background=bg).rgb)

    def loss_fn(gg):
        return photometric_loss(render_tiles(gg, cam, capacity=cap, background=bg).rgb, target)

    grad = jax.jit(jax.value_and_grad(
        lambda p: loss_fn(dataclasses.replace(p, alive=g.alive))))
    params = dataclasses.replace(g, alive=None)
    strategy = D.strategy_for(refine_cfg.densify, iterations=refine_cfg.iterations)
    aux = D.RenderAux(grad_means2d=jnp.full((g.capacity, 2), 1e-4), radii=jnp.ones(g.capacity),
                      visible=g.alive, image_size=jnp.asarray([size, size], jnp.float32))
    refine_state = dataclasses.replace(state, config=refine_cfg)
    parts = {
        "render_forward": (fwd, g),
        "loss_and_grad": (grad, params),
        "train_step": (T.train_step, state, batch, key),
        "train_step_refine": (T.train_step, refine_state, batch, key),
        "densify_update": (jax.jit(functools.partial(strategy.update, scene_extent=extent)),
                           g, state.opt_state, state.densify_stats, aux, 1, key),
    }
    # fit's device-resident loop: a chunk of T.CHUNK steps in one call (timed per chunk,
    # reported per step below), the views picked from the images on the device.
    imgs, cams_d = jax.device_put(jnp.asarray(images)), jax.device_put(cams)
    n_chunk = jax.device_put(jnp.int32(T.CHUNK))
    parts["train_chunk"] = (lambda st: T.train_chunk(st, imgs, cams_d, n_chunk, length=T.CHUNK),
                            state)
    if args.smoke:  # each part is one more compile: keep the smoke run short
        parts = {k: parts[k] for k in ("train_step", "densify_update")}
    results = {name: time_fn(*fn_args, repeats=repeats) for name, fn_args in parts.items()}
    if "train_chunk" in results:
        r = results["train_chunk"]
        results["train_chunk_per_step"] = {k: (v / T.CHUNK if k.endswith("_ms") else v)
                                           for k, v in r.items()}
    _, metrics = T.train_step(state, batch, key)
    payload = {"size": size, "gaussians": n, "capacity": g.capacity,
               "max_intersections": cap, "intersections": int(metrics["num_intersections"]),
               "min_capacity_ladder": next_capacity(1), "smoke": bool(args.smoke),
               "timings": results, "peak_rss_mb": peak_rss_mb(),
               "note": "CPU timings on a shared machine are noisy"}
    write_json(args.out, "train_step", payload)
    for name, r in results.items():
        print(f"{name:18s} median {r['median_ms']:9.2f} ms   compile {r['compile_ms']:9.0f} ms")


if __name__ == "__main__":
    main()
