"""Memory of an edit at 512 px with Stable Diffusion 1.5 / InstructPix2Pix (editor and 3DGS
trainer on one device): an estimate that needs no big machine, and peak RSS on this CPU.

Estimate. The networks are built abstractly (``eqx.filter_eval_shape`` of their
``from_config``: no weights allocated) and their parameters counted in float32 and
bfloat16. Each stage of one edit is compiled for shapes only and XLA's
``memory_analysis()`` gives its argument, output and temporary bytes: text encoding,
one DDIM step (the UNet on 3 x B samples, dual classifier-free guidance), VAE encode,
VAE decode, and one 3DGS training step at 512 px at the edit's Gaussian cap. The peak is
what stays resident (weights, the train state, the views) plus the largest stage's
temporaries, with and without each measure: bf16 weights, the text encoder released, the
UNet's attention in query chunks, the VAE in chunks of views, donated buffers.

This is XLA:CPU's buffer assignment, an estimate of a GPU's: the fusion and the
scheduling differ between backends, a GPU allocator adds fragmentation, the splatter's
compositor is the XLA path here (a GPU runs the Pallas kernel), and XLA:CPU has no bf16
dots or convolutions: it converts them to float32, which puts float32 copies of the
weights among a bf16 program's temporaries (4 GB for the UNet). So the activations of
the bf16 stages are taken from their float32 compilations, an upper bound of the bf16
ones (bf16 activations are half of float32's but for the float32 attention logits and
normalisation statistics, which are the same).

Measured. Peak RSS (``ru_maxrss``) of a child process per configuration: (a) the real
configuration (SD 1.5 / IP2P networks with random bfloat16 weights made in JAX, no
files) editing one 512 px view with a 1-step DDIM schedule (each step is the same
program, so the step count does not change the peak); (b) the demo's editor path (the
bundled small editor at 64 px, float32, its 20 steps, batch 1 as on a CPU): load,
encode the demo's prompt, edit views. On the CPU the device memory is the process's, so
RSS also holds the JAX runtime, the compiler and the compiled code.

    python benchmarks/memory.py                 # the record (benchmarks/results/cpu/memory.json)
    python benchmarks/memory.py --smoke --out DIR   # tiny configs, CI
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

from common import parse_args, peak_rss_mb, write_json

GIB = 2.0 ** 30
MIB = 2.0 ** 20
GPU_BUDGET_GIB = 24.0

# Tiny stand-ins of the three configurations for --smoke (and tests/test_memory.py).
TINY_UNET = dict(in_channels=8, out_channels=4, layers_per_block=1, block_out_channels=(16, 32),
                 down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
                 up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"), cross_attention_dim=32,
                 attention_head_dim=4, norm_num_groups=8)
TINY_VAE = dict(in_channels=3, out_channels=3, latent_channels=4, block_out_channels=(8, 8, 8, 8),
                layers_per_block=1, norm_num_groups=4, sample_size=64)
TINY_TEXT = dict(vocab_size=60, hidden_size=32, intermediate_size=37, num_hidden_layers=2,
                 num_attention_heads=4, max_position_embeddings=77)


def _extra(p):
    p.add_argument("--size", type=int, default=None, help="model size (default 512)")
    p.add_argument("--batches", type=int, nargs="+", default=None,
                   help="views per edit call (default 1 8: a CPU's and an accelerator's)")
    p.add_argument("--input-gaussians", type=int, default=None,
                   help="the input scene's Gaussians (default 1M); the train state is sized "
                        "at the edit's cap, default_max_gaussians of it")
    p.add_argument("--intersections", type=int, default=None,
                   help="the splatter's tile buffer (default 2^23 at 512 px)")
    p.add_argument("--views", type=int, default=None,
                   help="training views held on the device (default 100)")
    p.add_argument("--no-measure", action="store_true", help="the estimate only")
    p.add_argument("--recompute", type=Path, default=None,
                   help="a memory.json whose stages and measurements are kept: only the peak "
                        "table is computed again")
    p.add_argument("--worker", default=None, help=argparse_hidden())


def argparse_hidden():
    import argparse

    return argparse.SUPPRESS


# ----------------------------------------------------------------------------- the estimate

def _configs(smoke: bool):
    from jaxedit.models.memory import CLIP_L14_TEXT, SD15_UNET_IP2P, SD15_VAE

    return (TINY_UNET, TINY_VAE, TINY_TEXT) if smoke else (SD15_UNET_IP2P, SD15_VAE,
                                                           CLIP_L14_TEXT)


def edit_stages(size: int, batches, smoke: bool) -> dict:
    """name -> compiled_memory of each stage of the edit (float32 and some bf16 programs)."""
    import jax
    import jax.numpy as jnp

    from jaxedit.editors import jax_ip2p as jx
    from jaxedit.models import set_query_chunk
    from jaxedit.models.memory import abstract_ip2p, compiled_memory

    unet_cfg, vae_cfg, text_cfg = _configs(smoke)
    S, f32 = jax.ShapeDtypeStruct, jnp.float32
    nets = {d: abstract_ip2p(d, unet=unet_cfg, vae=vae_cfg, text=text_cfg)
            for d in (jnp.float32, jnp.bfloat16)}
    d_ctx = int(text_cfg["hidden_size"])
    f = 2 ** (len(vae_cfg["block_out_channels"]) - 1)
    lat_hw = (size // f, size // f)
    sched = jx.DiffusionSchedule(S((1000,), f32), S((), f32))
    chunk = jx.ATTENTION_CHUNK if not smoke else 16
    out = {}

    def run(name, fn, *args, donate=()):
        t0 = time.perf_counter()
        out[name] = compiled_memory(fn, *args, donate=donate)
        print(f"  {name}: temp {out[name]['temp'] / MIB:.0f} MiB, args "
              f"{out[name]['argument'] / MIB:.0f} MiB ({time.perf_counter() - t0:.0f} s)",
              flush=True)

    run("text_encode/float32", lambda enc, ids: enc(ids), nets[jnp.float32]["text_encoder"],
        S((1, 77), jnp.int32))
    for b in batches:
        lat = S((b, *lat_hw, 4), f32)
        den_args = (lat, lat, S((b, 77, d_ctx), f32), S((77, d_ctx), f32), S((b,), jnp.int32),
                    lat, sched)
        variants = ((jnp.float32, chunk),) if smoke else (
            (jnp.float32, chunk), (jnp.float32, None), (jnp.bfloat16, chunk))
        for dt, q in variants:
            if dt == jnp.bfloat16 and b != batches[0]:
                continue  # one bf16 compilation shows XLA:CPU's float32 copies of the weights
            cfg = jx.SamplerConfig(steps=1, dtype=jnp.dtype(dt).name)
            run(f"ddim_step/B{b}/{jnp.dtype(dt).name}/attention_chunk={q}",
                lambda u, *a, cfg=cfg: jx.denoise(u, *a, cfg),
                set_query_chunk(nets[dt]["unet"], q), *den_args)
        img = S((b, size, size, 3), f32)
        for vc in ((None, 1) if b > 1 else (None,)):
            cfg = jx.SamplerConfig(steps=1, vae_chunk=vc)
            vae = set_query_chunk(nets[jnp.float32]["vae"], chunk)
            run(f"vae_encode/B{b}/float32/vae_chunk={vc}",
                lambda v, i, o, n, cfg=cfg: jx.encode_latents(v, i, o, n, cfg), vae, img, img,
                S((b, *lat_hw, 4), f32))
            run(f"vae_decode/B{b}/float32/vae_chunk={vc}",
                lambda v, z, cfg=cfg: jx.decode(v, z, cfg), vae, S((b, *lat_hw, 4), f32))
        if b == batches[-1] and not smoke:  # the VAE's attention unchunked, whole batch
            vae = nets[jnp.float32]["vae"]
            cfg = jx.SamplerConfig(steps=1, vae_chunk=None)
            run(f"vae_decode/B{b}/float32/vae_chunk=None/attention_chunk=None",
                lambda v, z, cfg=cfg: jx.decode(v, z, cfg), vae, S((b, *lat_hw, 4), f32))
    return out


def train_step_stages(size: int, n_input: int, intersections: int,
                      donations=(False, True)) -> dict:
    """compiled_memory of one 3DGS training step (the edit trainer's config) at ``capacity``
    Gaussians (SH degree 3), with and without the train state donated. ``capacity``: the
    edit's cap for an input of ``n_input`` Gaussians (:func:`resolve_max_gaussians`)."""
    import dataclasses

    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxedit.camera import Camera
    from jaxedit.edit.trainer import EditTrainConfig, resolve_max_gaussians
    from jaxedit.gaussians import Gaussians
    from jaxedit.models.memory import compiled_memory
    from jaxedit.train import Batch, apply_step, init_state

    settings = resolve_max_gaussians(EditTrainConfig(), n_input)
    capacity = int(settings.densify.max_gaussians)
    config = dataclasses.replace(settings.train_config(), sh_degree=3)

    def state_of(c):
        g = Gaussians(means=jnp.zeros((c, 3)), log_scales=jnp.zeros((c, 3)),
                      quats=jnp.zeros((c, 4)), opacity_logits=jnp.zeros((c,)),
                      sh=jnp.zeros((c, 16, 3)), alive=jnp.zeros((c,), bool))
        return init_state(g, config, 1.0, max_intersections=intersections)

    state = jax.eval_shape(lambda: state_of(capacity))
    cam = Camera(world_to_camera=np.eye(4, dtype=np.float32), fx=np.float32(size),
                 fy=np.float32(size), cx=np.float32(size / 2), cy=np.float32(size / 2),
                 width=size, height=size)
    batch = Batch(image=jax.ShapeDtypeStruct((size, size, 3), jnp.float32), camera=cam)
    key = jax.ShapeDtypeStruct((), jax.random.key(0).dtype)
    out = {}
    for donate in donations:
        name = f"train_step/C{capacity}/donate_state={donate}"
        t0 = time.perf_counter()
        out[name] = compiled_memory(apply_step, state, batch, key, donate=(0,) if donate else ())
        print(f"  {name}: temp {out[name]['temp'] / MIB:.0f} MiB, args "
              f"{out[name]['argument'] / MIB:.0f} MiB ({time.perf_counter() - t0:.0f} s)",
              flush=True)
    return out


def estimate(args) -> dict:
    import jax.numpy as jnp

    from jaxedit.edit.trainer import default_max_gaussians
    from jaxedit.models.memory import abstract_ip2p, param_bytes, param_count

    smoke = args.smoke
    size = args.size or (64 if smoke else 512)
    batches = args.batches or ([2] if smoke else [1, 8])
    n_input = args.input_gaussians or (2000 if smoke else 1_000_000)
    capacity = default_max_gaussians(n_input)
    intersections = args.intersections or (2 ** 14 if smoke else 2 ** 23)
    views = args.views or (4 if smoke else 100)
    unet_cfg, vae_cfg, text_cfg = _configs(smoke)
    nets = abstract_ip2p(jnp.float32, unet=unet_cfg, vae=vae_cfg, text=text_cfg)
    params = {k: {"parameters": param_count(v), "float32_bytes": param_bytes(v, jnp.float32),
                  "bfloat16_bytes": param_bytes(v, jnp.bfloat16)} for k, v in nets.items()}
    print("parameters: " + ", ".join(f"{k} {v['parameters'] / 1e6:.1f} M"
                                     for k, v in params.items()), flush=True)
    stages = edit_stages(size, batches, smoke)
    # --smoke: one compilation of the training step (the donated one, the default's).
    donations = (True,) if smoke else (False, True)
    stages.update(train_step_stages(size, n_input, intersections, donations))
    # Views on the device: the originals and the edited targets, float32 [V, H, W, 3] each.
    views_bytes = 2 * views * size * size * 3 * 4
    train_args = stages[f"train_step/C{capacity}/donate_state=True"]["argument"]
    state_bytes = train_args - size * size * 3 * 4  # the state, not the target image
    est = {"model_size": size, "latent_factor": 2 ** (len(vae_cfg["block_out_channels"]) - 1),
           "context_dim": int(text_cfg["hidden_size"]), "batches": batches,
           "input_gaussians": n_input, "capacity": capacity, "intersections": intersections,
           "views_on_device": views, "parameters": params, "stages": stages,
           "train_state_bytes": state_bytes, "views_bytes": views_bytes}
    est["peaks"] = peak_table(est, smoke)
    return est


def peak_table(est: dict, smoke: bool) -> list:
    """Peak = resident (weights, train state, views) + the largest temporaries, per setting.

    ``serial``: the edit's and the training step's programs run one after the other (one
    device queue), so the peak is the larger of the two; ``overlapped``: both in flight
    at once (the edit runs beside training), their temporaries add up."""
    chunk = "16" if smoke else "1024"
    stages = est["stages"]
    train = {d: stages[f"train_step/C{est['capacity']}/donate_state={d}"] for d in (False, True)
             if f"train_step/C{est['capacity']}/donate_state={d}" in stages}
    rows = []
    for b in est["batches"]:
        for bf16 in (False, True):
            for text_released in (False, True):
                for attn in (chunk, "None"):
                    for vae_chunk in (("None", "1") if b > 1 else ("None",)):
                        for donate in train:
                            if f"ddim_step/B{b}/float32/attention_chunk={attn}" in stages:
                                rows.append(_row(est, b, bf16, text_released, attn,
                                                 vae_chunk, donate, train))
    return rows


def _stage_inputs(est: dict, b: int) -> dict:
    """Bytes of each edit stage's data arguments (float32), the weights left out: XLA drops
    the arguments a program does not read (the decoder's program has no encoder weights), so
    the weights' share of its ``argument`` bytes is not the whole VAE's."""
    size, f, d = est["model_size"], est["latent_factor"], est["context_dim"]
    latent = b * (size // f) ** 2 * 4 * 4
    image = b * size * size * 3 * 4
    return {"ddim_step": 3 * latent + (b + 1) * 77 * d * 4 + 4 * b + 4 * 1001,
            "vae_encode": 2 * image + latent, "vae_decode": latent}


def _row(est, b, bf16, text_released, attn, vae_chunk, donate, train):
    params, stages = est["parameters"], est["stages"]
    state_bytes, views_bytes = est["train_state_bytes"], est["views_bytes"]
    wkey = "bfloat16_bytes" if bf16 else "float32_bytes"
    weights = params["unet"][wkey] + params["vae"][wkey]
    text = 0 if text_released else params["text_encoder"][wkey]
    # Each edit stage's transient bytes: its temporaries and its non-weight arguments and
    # outputs (latents, images; the weights are counted once, as resident).
    ddim = stages[f"ddim_step/B{b}/float32/attention_chunk={attn}"]
    enc = stages[f"vae_encode/B{b}/float32/vae_chunk={vae_chunk}"]
    dec_name = f"vae_decode/B{b}/float32/vae_chunk={vae_chunk}"
    if attn == "None" and f"{dec_name}/attention_chunk=None" in stages:
        dec_name += "/attention_chunk=None"
    dec = stages[dec_name]
    inputs = _stage_inputs(est, b)
    edit_transient = {name: m["temp"] + m["output"] + inputs[name]
                      for name, m in (("ddim_step", ddim), ("vae_encode", enc),
                                      ("vae_decode", dec))}
    largest = max(edit_transient, key=edit_transient.get)
    t = train[donate]
    # The training step's transient: its temporaries, plus its output state unless the
    # state is donated (then the output is written into the input's buffers).
    train_transient = t["temp"] + t["output"] - t["alias"]
    resident = weights + text + state_bytes + views_bytes
    serial = resident + max(edit_transient[largest], train_transient)
    overlapped = resident + edit_transient[largest] + train_transient
    return {"batch": b, "weights": "bfloat16" if bf16 else "float32",
            "text_encoder": "released" if text_released else "kept",
            "attention_chunk": None if attn == "None" else int(attn),
            "vae_chunk": None if vae_chunk == "None" else int(vae_chunk),
            "train_state_donated": donate,
            "resident_gib": round(resident / GIB, 3),
            "weights_gib": round((weights + text) / GIB, 3),
            "largest_edit_stage": largest,
            "edit_transient_gib": {k: round(v / GIB, 3) for k, v in edit_transient.items()},
            "train_step_transient_gib": round(train_transient / GIB, 3),
            "peak_serial_gib": round(serial / GIB, 3),
            "peak_overlapped_gib": round(overlapped / GIB, 3),
            "fits_24gb": bool(overlapped / GIB <= GPU_BUDGET_GIB)}


# ----------------------------------------------------------------------------- measurements

def _rss_now_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def worker_real(smoke: bool) -> dict:
    """One 512 px edit (1 DDIM step) with the real architecture, random bf16 weights."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxedit.editors.jax_ip2p import DiffusionSchedule, JaxIP2PEditor
    from jaxedit.models import AutoencoderKL, CLIPTextEncoder, UNet2DCondition

    phases = {"import": _rss_now_mb()}
    jax.devices()
    unet_cfg, vae_cfg, text_cfg = _configs(smoke)
    size = 64 if smoke else 512
    dtype = jnp.bfloat16
    t0 = time.perf_counter()
    unet = UNet2DCondition.from_config(unet_cfg, key=jax.random.key(1), dtype=dtype)
    vae = AutoencoderKL.from_config(vae_cfg, key=jax.random.key(2), dtype=dtype)

    def text():  # the same random weights each time (the released encoder's reload)
        return CLIPTextEncoder.from_config(text_cfg, key=jax.random.key(3), dtype=dtype)

    def tokenize(prompts):
        out = np.ones((len(prompts), 77), np.int32)
        for i, p in enumerate(prompts):
            ids = [0] + [2 + ord(c) % 50 for c in p][:75] + [1]
            out[i, :len(ids)] = ids
        return out

    betas = np.linspace(0.00085 ** 0.5, 0.012 ** 0.5, 1000) ** 2
    ac = np.cumprod(1 - betas).astype(np.float32)
    editor = JaxIP2PEditor(unet, vae, text(), tokenize, DiffusionSchedule(ac, ac[0]),
                           size=size, steps=1, load_text_encoder=text)
    del unet, vae
    jax.block_until_ready(editor.nets)
    build_s = time.perf_counter() - t0
    phases["built"] = _rss_now_mb()
    emb = editor.encode("turn him into a bronze statue")
    phases["encoded"] = _rss_now_mb()
    image = np.random.default_rng(0).uniform(0, 1, (size, size, 3)).astype(np.float32)
    t0 = time.perf_counter()
    out = editor.edit(image, image, emb, jax.random.key(0), timestep_range=(0.5, 0.5))
    out = np.asarray(out)
    edit_s = time.perf_counter() - t0
    phases["edited"] = _rss_now_mb()
    return {"what": "SD 1.5 / IP2P architecture, random bf16 weights, one view, 1 DDIM step",
            "model_size": size, "dtype": editor.dtype, "describe": editor.describe(),
            "build_s": round(build_s, 1), "first_edit_s": round(edit_s, 1),
            "output_finite": bool(np.isfinite(out).all()),
            "rss_mb_after": {k: round(v) for k, v in phases.items()},
            "peak_rss_mb": round(peak_rss_mb())}


def worker_demo(smoke: bool) -> dict:
    """The demo's editor path: the bundled editor at its 64 px, float32, batch 1, 20 steps."""
    import jax
    import numpy as np

    from jaxedit.editors.jax_ip2p import load_bundled

    phases = {"import": _rss_now_mb()}
    jax.devices()
    steps = 2 if smoke else 20
    t0 = time.perf_counter()
    editor = load_bundled(steps=steps)
    size = editor.size
    load_s = time.perf_counter() - t0
    phases["loaded"] = _rss_now_mb()
    emb = editor.encode("turn him into a bronze statue")
    phases["encoded"] = _rss_now_mb()
    rng = np.random.default_rng(0)
    n = 2 if smoke else 4
    t0 = time.perf_counter()
    for i in range(n):
        view = rng.uniform(0, 1, (64, 64, 3)).astype(np.float32)
        np.asarray(editor.edit(view, view, emb, jax.random.key(i)))
    phases["edited"] = _rss_now_mb()
    return {"what": f"bundled editor, {size} px views of 64 x 64, float32, batch 1, "
                    f"{steps} DDIM steps, {n} edits", "describe": editor.describe(),
            "load_s": round(load_s, 1), "edits_s": round(time.perf_counter() - t0, 1),
            "rss_mb_after": {k: round(v) for k, v in phases.items()},
            "peak_rss_mb": round(peak_rss_mb())}


def measure(which: str, smoke: bool) -> dict:
    cmd = [sys.executable, __file__, "--worker", which] + (["--smoke"] if smoke else [])
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, env=os.environ.copy())
    if done.returncode:
        sys.exit(f"{which} worker failed:\n{done.stderr[-3000:]}")
    result = json.loads([x for x in done.stdout.splitlines()
                         if x.startswith("RESULT ")][-1][len("RESULT "):])
    result["wall_s"] = round(time.perf_counter() - t0, 1)
    print(f"{which}: peak RSS {result['peak_rss_mb']} MiB ({result['wall_s']} s)", flush=True)
    return result


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv, extra=_extra)
    if args.worker is not None:
        run = {"real": worker_real, "demo": worker_demo}[args.worker]
        print("RESULT " + json.dumps(run(args.smoke)))
        return
    if args.recompute is not None:
        result = json.loads(args.recompute.read_text())
        unet_cfg, vae_cfg, text_cfg = _configs(result["smoke"])
        result["estimate"].setdefault("latent_factor",
                                      2 ** (len(vae_cfg["block_out_channels"]) - 1))
        result["estimate"].setdefault("context_dim", int(text_cfg["hidden_size"]))
        result["estimate"]["peaks"] = peak_table(result["estimate"], result["smoke"])
        result.pop("benchmark", None), result.pop("machine", None)
        write_json(args.out, "memory", result)
        return
    t0 = time.perf_counter()
    result = {"smoke": args.smoke, "load_average_1min": os.getloadavg()[0],
              "estimate_note": (
                  "XLA:CPU memory_analysis of each stage compiled for shapes only: an "
                  "estimate of a GPU's. Edit stages' activations are from their float32 "
                  "compilations (XLA:CPU converts bf16 dots/convolutions to float32, so a bf16 "
                  "program's temporaries hold float32 weight copies: compare the "
                  "ddim_step .../bfloat16 stage); bf16 activations are at most those. "
                  "Transient = a stage's temporaries + its non-weight arguments and outputs; "
                  "peak_serial = resident + max(largest edit stage, training step); "
                  "peak_overlapped = resident + both (the edit running beside training)."),
              "estimate": estimate(args)}
    if not args.no_measure:  # --smoke: the demo's editor path only (CI's time)
        result["measured"] = {"demo_editor_64": measure("demo", args.smoke)}
        if not args.smoke:
            result["measured"]["real_config_512"] = measure("real", args.smoke)
    result["wall_s"] = round(time.perf_counter() - t0, 1)
    write_json(args.out, "memory", result)


if __name__ == "__main__":
    main()
