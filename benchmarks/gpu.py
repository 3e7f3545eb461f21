"""jaxedit's splatter and training loop against gsplat, side by side and like for like.

    python benchmarks/gpu.py [--smoke] [--out DIR] [--runs K] [--repeats R]
                             [--backends pallas,xla] [--person-steps N] [--skip-training]

What is compared, and how each side is set up (issue #28's fairness list):

* gsplat 1.5.3 renders as its ``simple_trainer`` does: ``rasterization(...,
  sh_degree=3, packed=False)``, the background through its ``backgrounds=``.
* its training loop uses what ``simple_trainer`` uses: the fused SSIM of the
  ``fused_ssim`` package (when importable; else the same SSIM in plain torch, and
  ``gsplat_ssim`` says so) and torch's fused Adam (``Adam(fused=True)``).
* every timing is K runs (``--runs``, each after its own warm-up) of R calls: min,
  median, max and spread ((max - min) / median) over all K x R samples, plus the
  per-run medians, so one lucky run cannot decide a row.
* both sides render the same scene from the same camera, and the row records the
  PSNR between the two images (``render_agreement_psnr_db``): a speed row means
  something only if that is high.
* rows: random scenes (means N(0, 0.5^2), scales U[0.01, 0.05], camera 3 units out;
  512 px / 200k and 1080p / 1M), and the built-in person scene trained by jaxedit
  (``--person-steps``) and then timed at a training view: a real scene's depth
  complexity, which random clouds lack.
* training steps/s at 512 px / 300k, density control off on both sides: steady state
  (median over chunks after the first) and end to end (the whole run, compiles and
  warm-up included) reported separately; the person scene's fit adds the same pair
  with density control on.
* memory: gsplat's ``torch.cuda.max_memory_allocated`` over its fwd+bwd beside
  XLA's memory analysis of ours (arguments + outputs + temporaries of the compiled
  fwd+bwd), per row; and the residual bytes of our backward at 1080p / 1M.
* versions of jax, jaxlib, torch, gsplat and fused_ssim, and the device.

gsplat rows run where ``gsplat`` and a CUDA torch are importable; elsewhere they are
recorded as skipped with the reason. ``--smoke`` runs the jaxedit side on the CPU at
tiny sizes (64 px / 2k, the person scene at 32 px) so CI keeps every code path of
it alive; the full run is for a GPU. Writes DIR/gpu.json.
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
PERSON_STEPS, SMOKE_PERSON_STEPS = 3000, 30


# ----------------------------------------------------------------------------- timing
def summary(values, run_medians=None, unit: str = "ms") -> dict:
    """min / median / max / spread ((max - min) / median) of ``values`` in ``unit``."""
    t = np.asarray(values, np.float64)
    med = float(np.median(t))
    out = {f"min_{unit}": float(t.min()), f"median_{unit}": med, f"max_{unit}": float(t.max()),
           "spread": float((t.max() - t.min()) / med) if med > 0 else None, "samples": len(t)}
    if run_medians is not None:
        out[f"run_medians_{unit}"] = [round(float(m), 4) for m in run_medians]
    return out


def time_runs(call, sync, *, runs: int, repeats: int, warmup: int = 3) -> dict:
    """``runs`` x (``warmup`` untimed calls, then ``repeats`` timed ones), each synced."""
    samples, medians = [], []
    for _ in range(runs):
        for _ in range(warmup):
            sync(call())
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            sync(call())
            times.append(1e3 * (time.perf_counter() - t0))
        samples += times
        medians.append(float(np.median(times)))
    return summary(samples, medians)


def versions() -> dict:
    """Versions of everything that ran (None: not installed)."""
    out = {}
    for name in ("jax", "jaxlib", "torch", "gsplat", "fused_ssim"):
        try:
            mod = importlib.import_module(name)
            out[name] = getattr(mod, "__version__", "installed")
        except Exception:  # noqa: BLE001  (absent or broken: recorded as such)
            out[name] = None
    try:
        import torch

        out["torch_cuda"] = torch.version.cuda
    except ImportError:
        pass
    return out


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


def _render_fn(cam, cap, backend):
    import jax.numpy as jnp

    from jaxedit.raster import render_tiles

    def rgb(g):  # black background on both sides
        return render_tiles(g, cam, capacity=cap, backend=backend, background=jnp.zeros(3)).rgb

    return rgb


def compiled_bytes(compiled) -> int | None:
    """Arguments + outputs + temporaries of a compiled XLA program (its device footprint)."""
    try:
        mem = compiled.memory_analysis()
        return int(mem.argument_size_in_bytes + mem.output_size_in_bytes
                   + mem.temp_size_in_bytes)
    except Exception:  # noqa: BLE001  (best-effort on some backends)
        return None


def jaxedit_raster(g, cam, backend: str, runs: int, repeats: int) -> dict:
    """Forward and forward+backward times of one backend on one scene, and its image."""
    import jax

    cap = _capacity(g, cam, backend)
    w = jax.numpy.asarray(np.random.default_rng(1).normal(size=(cam.height, cam.width, 3)),
                          np.float32)
    rgb = _render_fn(cam, cap, backend)
    rec = {"backend": backend, "capacity": cap,
           "stages": stage_times(g, cam, backend, cap, repeats)}
    for name, fn, args in (("forward", jax.jit(rgb), (g,)),
                           ("forward_backward", jax.jit(jax.value_and_grad(
                               _loss_fn(cam, cap, backend), allow_int=True)), (g, w))):
        t0 = time.perf_counter()
        compiled = fn.lower(*args).compile()
        rec[name] = time_runs(lambda: compiled(*args), jax.block_until_ready, runs=runs,
                              repeats=repeats)
        rec[name]["compile_ms"] = 1e3 * (time.perf_counter() - t0)
        rec[name]["xla_bytes"] = compiled_bytes(compiled)
    rec["image"] = np.asarray(jax.jit(rgb)(g))
    return rec


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
    """[H, W, 3] as simple_trainer renders: packed=False, the background composited by gsplat."""
    import torch
    from gsplat import rasterization

    colors, _, _ = rasterization(
        params["means"], params["quats"], torch.exp(params["log_scales"]),
        torch.sigmoid(params["opacity_logits"]), params["sh"], view, k, width, height,
        sh_degree=3, packed=False, backgrounds=background[None])
    return colors[0]


def gsplat_raster(g, cam, runs: int, repeats: int) -> dict:
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

    def sync(_):
        torch.cuda.synchronize()

    rec = {"forward": time_runs(fwd, sync, runs=runs, repeats=repeats)}
    torch.cuda.reset_peak_memory_stats()
    base = torch.cuda.memory_allocated()
    rec["forward_backward"] = time_runs(fwd_bwd, sync, runs=runs, repeats=repeats)
    rec["forward_backward"]["peak_bytes"] = int(torch.cuda.max_memory_allocated())
    rec["forward_backward"]["peak_bytes_above_inputs"] = int(torch.cuda.max_memory_allocated()
                                                             - base)
    rec["image"] = fwd().clamp(0, 1).cpu().numpy()
    return rec


def _gsplat_ssim():
    """(SSIM function of [1, 3, H, W] pairs, its name): fused_ssim as simple_trainer uses it,
    else the same Gaussian-window SSIM in plain torch."""
    try:
        from fused_ssim import fused_ssim

        return (lambda a, b: fused_ssim(a, b, padding="valid")), "fused_ssim"
    except ImportError:
        from parity import torch_ssim  # the same window and constants, in plain torch

        return torch_ssim, "torch conv2d SSIM (fused_ssim is not installed)"


def gsplat_training(size: int, n: int, steps: int, chunk: int) -> dict:
    """Steps/s of a minimal simple_trainer-like loop: fused SSIM, fused Adam, packed=False."""
    import torch

    images, cams, start = _training_data(size, n)
    imgs = torch.tensor(np.asarray(images), device="cuda")
    params, _, _ = _torch_scene(start, cams[0])
    views = [_torch_scene(start, cams[i])[1:] for i in range(images.shape[0])]
    opt = torch.optim.Adam([{"params": [p], "lr": lr} for p, lr in zip(
        params.values(), (1.6e-4, 1e-3, 5e-3, 5e-2, 2.5e-3))], eps=1e-15, fused=True)
    bg = torch.ones(3, device="cuda")
    ssim, ssim_name = _gsplat_ssim()

    def step(i):
        v = i % len(views)
        view, k = views[v]
        out = _gsplat_render(params, view, k, size, size, bg)
        a, b = out.permute(2, 0, 1)[None], imgs[v].permute(2, 0, 1)[None]
        loss = 0.8 * torch.abs(out - imgs[v]).mean() + 0.2 * (1 - ssim(a, b))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    torch.cuda.synchronize()
    t_start = time.perf_counter()
    chunk_s = []
    done = 0
    while done < steps:  # synced every ``chunk`` steps, as jaxedit's loop reads its metrics
        t0 = time.perf_counter()
        for _ in range(min(chunk, steps - done)):
            step(done)
            done += 1
        torch.cuda.synchronize()
        chunk_s.append((time.perf_counter() - t0) / min(chunk, steps))
    total = time.perf_counter() - t_start
    steady = np.asarray(chunk_s[1:] or chunk_s)
    return {"steps": steps, "ssim": ssim_name, "adam": "torch.optim.Adam(fused=True)",
            "end_to_end_steps_per_s": steps / total,
            "steady_steps_per_s": 1.0 / float(np.median(steady)),
            "steady_chunks": summary(1.0 / steady, unit="steps_per_s")}


# ----------------------------------------------------------------------------- training
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


def jaxedit_training(size: int, n: int, steps: int, chunk: int, runs: int) -> dict:
    """Steps/s of jaxedit's device-resident loop (chunks of ``chunk`` steps in one
    ``lax.scan``), density control off as in the gsplat loop: end to end (state built,
    buffer sized, compiled, run) and steady state (median chunk after the first), per run."""
    import jax

    from jaxedit import train as T

    images, cams, start = _training_data(size, n)
    config = T.TrainConfig(iterations=10 ** 6, sh_degree_interval=1,
                           densify=T.DensifyConfig(enabled=False))
    active = jax.device_put(np.int32(chunk))
    rounds = max(2, steps // chunk)
    per_run = []
    for _ in range(runs):  # run 0 compiles; later runs reuse the compiled chunk
        t_start = time.perf_counter()
        state = T.size_buffer(T.init_state(start, config, 3.0), cams)
        chunk_s = []
        for _ in range(rounds):
            t0 = time.perf_counter()
            state, metrics = T.train_chunk(state, images, cams, active, length=chunk)
            losses = jax.device_get(metrics["loss"])  # the host reads each chunk once
            chunk_s.append((time.perf_counter() - t0) / chunk)
        total = time.perf_counter() - t_start
        per_run.append({"end_to_end_steps_per_s": rounds * chunk / total,
                        "steady_steps_per_s": 1.0 / float(np.median(chunk_s[1:])),
                        "final_loss": float(losses[-1])})
    return {"steps": rounds * chunk, "chunk": chunk, "runs": per_run,
            "end_to_end_steps_per_s_cold": per_run[0]["end_to_end_steps_per_s"],
            "steady_steps_per_s": float(np.median([r["steady_steps_per_s"] for r in per_run])),
            "steady_runs": summary([r["steady_steps_per_s"] for r in per_run],
                                   unit="steps_per_s")}


# ----------------------------------------------------------------------------- the person scene
def trained_person(steps: int, smoke: bool) -> dict:
    """The person scene trained by :func:`jaxedit.train.fit` (density control on), its
    end-to-end and steady steps/s, and (Gaussians, a training camera) to time renders with."""
    import tempfile
    from pathlib import Path

    import jax

    from jaxedit import gaussians as G
    from jaxedit import scenes
    from jaxedit import train as T
    from jaxedit.io import load_nerfstudio

    downscale, views = (8, 16) if smoke else (1, 72)
    dens = T.DensifyConfig(warmup=20, refine_every=20) if smoke else T.DensifyConfig()
    config = T.TrainConfig(iterations=steps, densify=dens)
    with tempfile.TemporaryDirectory() as tmp:
        data = load_nerfstudio(scenes.make_scene("person", Path(tmp) / "person",
                                                 downscale=downscale, views=views,
                                                 test_views=0))
    images, cams = data.train()
    g = G.from_points(np.asarray(data.points), np.asarray(data.point_colors), sh_degree=3)
    state = T.init_state(g, config, T.scene_extent(cams), key=jax.random.key(0))
    chunk_s, last = [], [0.0]

    def timer(st, metrics):
        jax.block_until_ready(st.gaussians.means)
        now = time.perf_counter()
        chunk_s.append((now - last[0]) / max(len(metrics["loss"]), 1))
        last[0] = now

    t0 = last[0] = time.perf_counter()
    state = T.fit(state, images, cams, callback=timer)
    total = time.perf_counter() - t0
    per_step = np.asarray(chunk_s)
    fast = per_step[per_step <= 10 * np.median(per_step)]  # drop the chunks that compiled
    return {"gaussians": G.compact(state.gaussians), "camera": cams[0],
            "record": {"steps": steps, "size": int(images.shape[2]), "train_views": views,
                       "num_gaussians": int(state.gaussians.num_alive()),
                       "capacity": state.capacity,
                       "end_to_end_steps_per_s": steps / total,
                       "steady_steps_per_s": 1.0 / float(np.median(fast))}}


# ----------------------------------------------------------------------------- main
def _ratio(a, b):
    return None if not a or not b else round(a / b, 2)


def raster_row(g, cam, backends, why_not_gsplat, runs: int, repeats: int) -> dict:
    """One scene: each jaxedit backend and gsplat, their ratios and render agreement."""
    from jaxedit.metrics import psnr

    row = {"width": cam.width, "height": cam.height, "gaussians": int(g.capacity), "jaxedit": {}}
    images = {}
    for backend in backends:
        rec = _guarded(jaxedit_raster, g, cam, backend, runs, repeats)
        if "image" in rec:
            images[backend] = np.clip(rec.pop("image"), 0.0, 1.0)
        row["jaxedit"][backend] = rec
    if len(images) > 1:
        a, b = list(images.values())[:2]
        row["backend_agreement_psnr_db"] = float(psnr(a, b))
    if why_not_gsplat is not None:
        row["gsplat"] = f"skipped: {why_not_gsplat}"
        return row
    row["gsplat"] = _guarded(gsplat_raster, g, cam, runs, repeats)
    theirs = row["gsplat"].pop("image", None)
    for backend in backends:
        ours = row["jaxedit"][backend]
        if theirs is not None and backend in images:
            row[f"render_agreement_psnr_db_{backend}"] = float(psnr(images[backend], theirs))
        for what in ("forward", "forward_backward"):
            for stat in ("median_ms", "min_ms"):
                row[f"ratio_{backend}_to_gsplat_{what}_{stat[:-3]}"] = _ratio(
                    ours.get(what, {}).get(stat), row["gsplat"].get(what, {}).get(stat))
        row[f"memory_{backend}_xla_bytes_vs_gsplat_peak"] = [
            ours.get("forward_backward", {}).get("xla_bytes"),
            row["gsplat"].get("forward_backward", {}).get("peak_bytes_above_inputs")]
    return row


def _print_row(label: str, row: dict, backends) -> None:
    for backend in backends:
        j = row["jaxedit"].get(backend, {})
        if "error" in j:
            continue
        print(f"{label}: {backend} fwd {j['forward']['median_ms']:.2f} ms (min "
              f"{j['forward']['min_ms']:.2f}), fwd+bwd {j['forward_backward']['median_ms']:.2f} "
              f"ms; to gsplat {row.get(f'ratio_{backend}_to_gsplat_forward_median')} / "
              f"{row.get(f'ratio_{backend}_to_gsplat_forward_backward_median')}; agreement "
              f"{row.get(f'render_agreement_psnr_db_{backend}')} dB", flush=True)


def training_rows(args, why_not_gsplat, runs: int) -> dict:
    size, n = SMOKE_TRAIN_ROW if args.smoke else TRAIN_ROW
    steps = args.train_steps or (4 if args.smoke else 300)
    chunk = min(steps, 50)
    train = {"size": size, "gaussians": n, "density_control": False,
             "jaxedit": _guarded(jaxedit_training, size, n, steps=steps, chunk=chunk, runs=runs)}
    if why_not_gsplat is None:
        train["gsplat"] = _guarded(gsplat_training, size, n, steps, chunk)
        for what in ("steady_steps_per_s", "end_to_end_steps_per_s"):
            theirs = train["gsplat"].get(what)
            ours = train["jaxedit"].get(what if what == "steady_steps_per_s"
                                        else "end_to_end_steps_per_s_cold")
            train[f"ratio_jaxedit_to_gsplat_{what}"] = _ratio(ours, theirs)
    else:
        train["gsplat"] = f"skipped: {why_not_gsplat}"
    print(f"training {size}px / {n}: jaxedit steady {train['jaxedit'].get('steady_steps_per_s')}"
          f" steps/s, end to end {train['jaxedit'].get('end_to_end_steps_per_s_cold')}; "
          f"gsplat {train['gsplat']}", flush=True)
    return train


def main(argv=None):
    def extra(p):
        p.add_argument("--backends", default="pallas,xla")
        p.add_argument("--runs", type=int, default=None, help="runs per timing (default 5)")
        p.add_argument("--skip-memory", action="store_true")
        p.add_argument("--train-steps", type=int, default=None)
        p.add_argument("--skip-training", action="store_true")
        p.add_argument("--person-steps", type=int, default=None,
                       help=f"train the person scene this long, then time it "
                            f"(default {PERSON_STEPS}; 0 skips)")
        p.add_argument("--rows", default=None,
                       help="raster rows to run, e.g. 512x512x200000 (default: all)")

    args = parse_args(__doc__.splitlines()[0], argv, extra)
    import jax

    backends = [b for b in args.backends.split(",") if b]
    rows = SMOKE_ROWS if args.smoke else RASTER_ROWS
    if args.rows:
        rows = [tuple(int(v) for v in r.split("x")) for r in args.rows.split(",")]
    repeats = args.repeats or (2 if args.smoke else 20)
    runs = args.runs or (2 if args.smoke else 5)
    why_not_gsplat = gsplat_unavailable()
    results = {"platform": jax.default_backend(), "versions": versions(),
               "gsplat": why_not_gsplat or "ran", "runs": runs, "repeats": repeats,
               "raster": [], "person": None, "training": None, "memory": None}

    def save(partial=True):
        write_json(args.out, "gpu", {"smoke": bool(args.smoke), "partial": partial, **results})

    for width, height, n in rows:
        g, cam = scene(n, width, height=height)
        row = raster_row(g, cam, backends, why_not_gsplat, runs, repeats)
        results["raster"].append(row)
        save()
        _print_row(f"{width}x{height} / {n}", row, backends)

    steps = SMOKE_PERSON_STEPS if args.smoke else PERSON_STEPS
    steps = steps if args.person_steps is None else args.person_steps
    if steps:
        person = _guarded(trained_person, steps, args.smoke)
        if "error" in person:
            results["person"] = person
        else:
            row = raster_row(person["gaussians"], person["camera"], backends, why_not_gsplat,
                             runs, repeats)
            results["person"] = {"training": person["record"], "raster": row}
            _print_row(f"person scene ({person['record']['num_gaussians']} Gaussians)", row,
                       backends)
        save()
    if not args.skip_training:
        results["training"] = training_rows(args, why_not_gsplat, runs)
        save()
    if not args.skip_memory:
        width, height, n = SMOKE_ROWS[0] if args.smoke else MEMORY_ROW
        results["memory"] = _guarded(memory_analysis, width, height, n, backends)
        print(f"memory {width}x{height} / {n}: {results['memory']}", flush=True)
    save(partial=False)


if __name__ == "__main__":
    main()
