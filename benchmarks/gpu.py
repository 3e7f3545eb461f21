"""jaxedit's splatter and training loop against gsplat, side by side, at real scale.

    python benchmarks/gpu.py [--smoke] [--out DIR] [--repeats R] [--backends pallas,xla]

Rows (scene draws of ``benchmarks/raster.py``: means N(0, 0.5^2), scales U[0.01, 0.05],
random quaternions, opacity sigmoid(N(0, 1)), SH degree 3, camera 3 units out, focal = width):

* 512 x 512 px with 200k Gaussians and 1920 x 1080 px with 1M: forward and
  forward+backward (sum of the image times fixed weights) for each jaxedit
  backend and for gsplat 1.5.3 (``rasterization(..., sh_degree=3, packed=True)``,
  background composited by hand), timed after warm-up with the device synced;
* training throughput at 512 px with 300k Gaussians: steps/s of jaxedit's
  device-resident chunked loop against a minimal gsplat + torch loop with the
  same loss (0.8 L1 + 0.2 D-SSIM) and Adam;
* memory at 1080p / 1M: XLA's memory analysis of the compiled forward+backward
  (lowered and compiled, not run, so it is reported on a CPU too) and the bytes
  of the backward's residuals per backend (O(pixels + pairs)).

gsplat rows run where ``gsplat`` and a CUDA torch are importable; elsewhere they
are recorded as skipped with the reason. On a machine without a GPU the Pallas
backend runs in its interpreter, far too slowly for the full sizes: ``--smoke``
(64 px, 2k Gaussians) keeps every code path alive in CI, and the full run is for
a GPU. Writes DIR/gpu.json and prints each jaxedit/gsplat ratio.
"""

from __future__ import annotations

import importlib
import time

import numpy as np

from common import parse_args, write_json  # noqa: E402  (sets sys.path)
from raster import compile_and_time, scene  # noqa: E402

RASTER_ROWS = [(512, 512, 200_000), (1920, 1080, 1_000_000)]
SMOKE_ROWS = [(64, 64, 2_000)]
TRAIN_ROW = (512, 300_000)
SMOKE_TRAIN_ROW = (32, 500)
MEMORY_ROW = (1920, 1080, 1_000_000)


# ----------------------------------------------------------------------------- jaxedit
def _capacity(g, cam, backend):
    R = importlib.import_module("jaxedit.raster.render")  # the module, not the function

    return R.next_capacity(R.count_pairs(g, cam, backend=backend) * R.HEADROOM)


def _loss_fn(cam, cap, backend):
    import jax.numpy as jnp

    from jaxedit.raster import render_tiles

    def loss(g, w):  # w is an argument, not a constant XLA would fold at compile time
        return jnp.sum(render_tiles(g, cam, capacity=cap, backend=backend).rgb * w)

    return loss


def jaxedit_raster(g, cam, backend: str, repeats: int) -> dict:
    """Forward and forward+backward times of one backend on one scene."""
    import jax
    import jax.numpy as jnp

    from jaxedit.raster import render_tiles

    cap = _capacity(g, cam, backend)
    w = jnp.asarray(np.random.default_rng(1).normal(size=(cam.height, cam.width, 3)), jnp.float32)
    fwd = jax.jit(lambda g: render_tiles(g, cam, capacity=cap, backend=backend).rgb)
    fwd_bwd = jax.jit(jax.value_and_grad(_loss_fn(cam, cap, backend), allow_int=True))
    return {"backend": backend, "capacity": cap, "stages": stage_times(g, cam, backend, cap, repeats),
            "forward": compile_and_time(fwd, g, repeats=repeats),
            "forward_backward": compile_and_time(fwd_bwd, g, w, repeats=repeats)}


def stage_times(g, cam, backend: str, cap: int, repeats: int) -> dict:
    """Forward time of the pipeline's prefixes (projection; projection + binning), so the
    compositing share is the full forward minus the second: where the time goes."""
    import jax

    from jaxedit.raster import binning as B
    from jaxedit.raster import project as P
    from jaxedit.raster.render import tile_size

    tile = tile_size(backend)

    def projected(g):
        return P.project(g, cam, sh_degree=3)

    def binned(g):
        return B.bin_gaussians(projected(g), cam.width, cam.height, cap, tile).gids

    return {"project": compile_and_time(jax.jit(lambda g: projected(g).means2d), g,
                                        repeats=repeats),
            "project_and_bin": compile_and_time(jax.jit(binned), g, repeats=repeats)}


def _guarded(fn, *args, **kwargs) -> dict:
    """``fn``'s record, or the error that stopped it (a row that fails, e.g. out of device
    memory, is recorded and the run goes on to the next)."""
    try:
        return fn(*args, **kwargs)
    except Exception as e:  # noqa: BLE001  (a benchmark records every failure as a row)
        msg = str(e).strip().splitlines()[0][:300] if str(e).strip() else ""
        print(f"  failed: {type(e).__name__}: {msg}", flush=True)
        return {"error": f"{type(e).__name__}: {msg}"}


def residual_bytes(g, cam, backend: str, cap: int) -> int:
    """Bytes the forward keeps for the backward (the leaves of the VJP closure), not run."""
    import jax

    loss = _loss_fn(cam, cap, backend)
    w = jax.ShapeDtypeStruct((cam.height, cam.width, 3), np.float32)

    def residuals(g, w):
        return jax.tree_util.tree_leaves(jax.vjp(lambda g: loss(g, w), g)[1])

    leaves = jax.eval_shape(residuals, g, w)
    return int(sum(np.prod(x.shape) * np.dtype(x.dtype).itemsize for x in leaves))


def memory_analysis(width: int, height: int, n: int, backends) -> dict:
    """XLA's memory analysis of the compiled fwd+bwd at ``width`` x ``height`` / ``n``."""
    import jax

    g, cam = scene(n, width, height=height)
    rec = {"width": width, "height": height, "gaussians": n, "platform": jax.default_backend()}
    inputs = sum(int(np.prod(x.shape)) * np.dtype(x.dtype).itemsize
                 for x in jax.tree_util.tree_leaves(g))
    rec["scene_bytes"] = inputs
    rec["pixels"] = width * height
    for backend in backends:
        cap = _capacity(g, cam, backend)
        row = {"capacity_pairs": cap,
               "residual_bytes": residual_bytes(g, cam, backend, cap)}
        row["residual_bytes_per_pair_and_pixel"] = round(
            row["residual_bytes"] / (cap + width * height), 2)
        # Off a GPU the Pallas kernels compile as the interpreter's loops over the same
        # buffers: XLA's figures then describe the buffers around the kernels, not the
        # GPU program's scratch (see "compiled_as").
        w = jax.ShapeDtypeStruct((height, width, 3), np.float32)
        t0 = time.perf_counter()
        fn = jax.jit(jax.value_and_grad(_loss_fn(cam, cap, backend), allow_int=True))
        compiled = fn.lower(g, w).compile()
        row["compile_s"] = round(time.perf_counter() - t0, 1)
        mem = compiled.memory_analysis()
        row["xla"] = {k: int(getattr(mem, k)) for k in (
            "argument_size_in_bytes", "output_size_in_bytes", "temp_size_in_bytes",
            "generated_code_size_in_bytes") if hasattr(mem, k)}
        row["compiled_as"] = ("Pallas interpreter (CPU)" if backend == "pallas"
                              and jax.default_backend() != "gpu" else jax.default_backend())
        rec[backend] = row
    return rec


# ----------------------------------------------------------------------------- gsplat
def gsplat_unavailable() -> str | None:
    """Why the gsplat rows cannot run here, or None."""
    try:
        import torch
    except ImportError:
        return "torch is not installed"
    if not torch.cuda.is_available():
        return "no CUDA device for torch"
    try:
        import gsplat  # noqa: F401
    except ImportError as e:
        return f"gsplat is not importable ({e})"
    return None


def _torch_scene(g, cam):
    import torch

    dev = "cuda"

    def t(x, grad=True):
        return torch.tensor(np.asarray(x), device=dev, requires_grad=grad)

    params = {"means": t(g.means), "quats": t(g.quats), "log_scales": t(g.log_scales),
              "opacity_logits": t(g.opacity_logits), "sh": t(g.sh)}
    view = torch.tensor(np.asarray(cam.world_to_camera), device=dev, dtype=torch.float32)[None]
    k = torch.tensor([[float(cam.fx), 0.0, float(cam.cx)], [0.0, float(cam.fy), float(cam.cy)],
                      [0.0, 0.0, 1.0]], device=dev)[None]
    return params, view, k


def _gsplat_render(params, view, k, width, height, background):
    import torch
    from gsplat import rasterization

    colors, alphas, _ = rasterization(
        params["means"], params["quats"], torch.exp(params["log_scales"]),
        torch.sigmoid(params["opacity_logits"]), params["sh"], view, k, width, height,
        sh_degree=3)
    # gsplat 1.5.3 asserts on backgrounds= with packed=True: composite by hand.
    return colors[0] + (1.0 - alphas[0]) * background


def _cuda_time(fn, repeats: int) -> dict:
    import torch

    for _ in range(3):
        fn()
    torch.cuda.synchronize()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    return {"median_ms": 1e3 * float(np.median(times)), "min_ms": 1e3 * float(np.min(times)),
            "repeats": repeats}


def gsplat_raster(g, cam, repeats: int) -> dict:
    import torch

    params, view, k = _torch_scene(g, cam)
    bg = torch.zeros(3, device="cuda")
    w = torch.tensor(np.random.default_rng(1).normal(size=(cam.height, cam.width, 3)),
                     device="cuda", dtype=torch.float32)

    def fwd():
        with torch.no_grad():
            return _gsplat_render(params, view, k, cam.width, cam.height, bg)

    def fwd_bwd():
        loss = torch.sum(_gsplat_render(params, view, k, cam.width, cam.height, bg) * w)
        loss.backward()
        return loss

    return {"forward": _cuda_time(fwd, repeats), "forward_backward": _cuda_time(fwd_bwd, repeats)}


def _training_data(size: int, n: int, views: int = 8, seed: int = 0):
    """A target scene rendered from ``views`` orbit cameras, and a perturbed copy to train."""
    import dataclasses

    import jax
    import jax.numpy as jnp

    from jaxedit import camera as cam_lib
    from jaxedit.raster import render

    target, _ = scene(n, size, seed=seed)
    cams = cam_lib.orbit(views, radius=3.0, width=size, height=size, focal=float(size))
    images = jnp.stack([render(target, cams[i], background=jnp.ones(3)).rgb for i in range(views)])
    rng = np.random.default_rng(seed + 1)
    start = dataclasses.replace(
        target, means=target.means + jnp.asarray(rng.normal(0, 0.02, target.means.shape),
                                                 jnp.float32),
        sh=target.sh.at[:, 0].set(0.0))
    return jax.device_put(images), cams, start


def jaxedit_training(size: int, n: int, steps: int, chunk: int) -> dict:
    """Steps/s of jaxedit's device-resident loop (chunks of ``chunk`` steps in one
    ``lax.scan``, images on the device), density control off as in the gsplat loop."""
    import jax

    from jaxedit import train as T

    images, cams, start = _training_data(size, n)
    config = T.TrainConfig(iterations=10 ** 6, sh_degree_interval=1,
                           densify=T.DensifyConfig(enabled=False))
    state = T.size_buffer(T.init_state(start, config, 3.0), cams)
    active = jax.device_put(np.int32(chunk))
    state, _ = T.train_chunk(state, images, cams, active, length=chunk)  # compile + warm up
    jax.block_until_ready(state)
    rounds = max(1, steps // chunk)
    t0 = time.perf_counter()
    for _ in range(rounds):
        state, metrics = T.train_chunk(state, images, cams, active, length=chunk)
        losses = jax.device_get(metrics["loss"])  # the host reads each chunk's losses once
    dt = time.perf_counter() - t0
    redone = int(np.sum(np.asarray(jax.device_get(metrics["redo"]))))
    return {"steps": rounds * chunk, "chunk": chunk, "seconds": dt,
            "steps_per_s": rounds * chunk / dt, "final_loss": float(losses[-1]),
            "redo_in_last_chunk": redone}


def gsplat_training(size: int, n: int, steps: int) -> dict:
    import torch


    images, cams, start = _training_data(size, n)
    imgs = torch.tensor(np.asarray(images), device="cuda")
    params, _, _ = _torch_scene(start, cams[0])
    views = [_torch_scene(start, cams[i])[1:] for i in range(images.shape[0])]
    opt = torch.optim.Adam([{"params": [p], "lr": lr} for p, lr in zip(
        params.values(), (1.6e-4, 1e-3, 5e-3, 5e-2, 2.5e-3))], eps=1e-15)
    bg = torch.ones(3, device="cuda")

    def ssim(a, b):
        import torch.nn.functional as F

        x, y = a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None]
        c1, c2 = 0.01 ** 2, 0.03 ** 2
        coords = torch.arange(11, device="cuda", dtype=torch.float32) - 5
        g1 = torch.exp(-coords ** 2 / (2 * 1.5 ** 2))
        g1 = g1 / g1.sum()
        win = (g1[:, None] * g1[None]).expand(3, 1, 11, 11)

        def f(z):
            return F.conv2d(z, win, groups=3)

        mx, my = f(x), f(y)
        sxx, syy, sxy = f(x * x) - mx ** 2, f(y * y) - my ** 2, f(x * y) - mx * my
        m = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx ** 2 + my ** 2 + c1) * (sxx + syy + c2))
        return m.mean()

    def step(i):
        v = i % len(views)
        view, k = views[v]
        out = _gsplat_render(params, view, k, size, size, bg)
        loss = 0.8 * torch.abs(out - imgs[v]).mean() + 0.2 * (1 - ssim(out, imgs[v]))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    for i in range(5):
        step(i)
    torch.cuda.synchronize()
    t0 = time.perf_counter()
    for i in range(steps):
        step(i)
    torch.cuda.synchronize()
    dt = time.perf_counter() - t0
    return {"steps": steps, "seconds": dt, "steps_per_s": steps / dt}


# ----------------------------------------------------------------------------- main
def training_rows(args, why_not_gsplat) -> dict:
    size, n = SMOKE_TRAIN_ROW if args.smoke else TRAIN_ROW
    steps = args.train_steps or (4 if args.smoke else 300)
    train = {"size": size, "gaussians": n,
             "jaxedit": _guarded(jaxedit_training, size, n, steps=steps, chunk=min(steps, 50))}
    if why_not_gsplat is None:
        train["gsplat"] = _guarded(gsplat_training, size, n, steps)
        train["ratio_steps_per_s_gsplat_to_jaxedit"] = _ratio(
            train["gsplat"].get("steps_per_s"), train["jaxedit"].get("steps_per_s"))
    else:
        train["gsplat"] = f"skipped: {why_not_gsplat}"
    print(f"training {size}px / {n}: jaxedit {train['jaxedit'].get('steps_per_s')} steps/s; "
          f"gsplat/jaxedit {train.get('ratio_steps_per_s_gsplat_to_jaxedit')}", flush=True)
    return train


def _ratio(a, b):
    return None if not a or not b else round(a / b, 2)


def main(argv=None):
    def extra(p):
        p.add_argument("--backends", default="pallas,xla")
        p.add_argument("--skip-memory", action="store_true")
        p.add_argument("--train-steps", type=int, default=None)
        p.add_argument("--skip-training", action="store_true")
        p.add_argument("--rows", default=None,
                       help="raster rows to run, e.g. 512x512x200000 (default: all)")

    args = parse_args(__doc__.splitlines()[0], argv, extra)
    import jax

    backends = [b for b in args.backends.split(",") if b]
    rows = SMOKE_ROWS if args.smoke else RASTER_ROWS
    if args.rows:
        rows = [tuple(int(v) for v in r.split("x")) for r in args.rows.split(",")]
    repeats = args.repeats or (2 if args.smoke else 20)
    why_not_gsplat = gsplat_unavailable()
    results = {"platform": jax.default_backend(), "gsplat": why_not_gsplat or "ran",
               "raster": [], "training": None, "memory": None}
    for width, height, n in rows:
        g, cam = scene(n, width, height=height)
        row = {"width": width, "height": height, "gaussians": n, "jaxedit": {}}
        for backend in backends:
            row["jaxedit"][backend] = _guarded(jaxedit_raster, g, cam, backend, repeats)
        if why_not_gsplat is None:
            row["gsplat"] = _guarded(gsplat_raster, g, cam, repeats)
            for backend in backends:
                for what in ("forward", "forward_backward"):
                    row[f"ratio_{backend}_to_gsplat_{what}"] = _ratio(
                        row["jaxedit"][backend].get(what, {}).get("median_ms"),
                        row["gsplat"].get(what, {}).get("median_ms"))
        else:
            row["gsplat"] = f"skipped: {why_not_gsplat}"
        results["raster"].append(row)
        write_json(args.out, "gpu", {"smoke": bool(args.smoke), "partial": True, **results})
        for backend in backends:
            j = row["jaxedit"][backend]
            if "error" in j:
                continue
            print(f"{width}x{height} / {n}: {backend} fwd {j['forward']['median_ms']:.2f} ms, "
                  f"fwd+bwd {j['forward_backward']['median_ms']:.2f} ms; to gsplat "
                  f"{row.get(f'ratio_{backend}_to_gsplat_forward')} / "
                  f"{row.get(f'ratio_{backend}_to_gsplat_forward_backward')}", flush=True)

    if not args.skip_training:
        results["training"] = training_rows(args, why_not_gsplat)
        write_json(args.out, "gpu", {"smoke": bool(args.smoke), "partial": True, **results})
    if not args.skip_memory:
        width, height, n = SMOKE_ROWS[0] if args.smoke else MEMORY_ROW
        results["memory"] = _guarded(memory_analysis, width, height, n, backends)
        print(f"memory {width}x{height} / {n}: {results['memory']}", flush=True)
    write_json(args.out, "gpu", {"smoke": bool(args.smoke), **results})


if __name__ == "__main__":
    main()
