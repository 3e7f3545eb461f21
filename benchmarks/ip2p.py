"""InstructPix2Pix editor cost, JAX editor vs the torch reference: seconds per edit (VAE
encode, DDIM with three-branch guidance, decode) after compilation, compile time, peak memory.

The time of a diffusion edit does not depend on the weight values, so ``--arch sd15``
builds Stable Diffusion 1.5's UNet (8 input channels, as IP2P), VAE and CLIP ViT-L text
encoder from their published configurations with random weights and saves them with
``save_pretrained``; both editors then load that folder, as they would load
timbrooks/instruct-pix2pix. ``--weights DIR`` uses real weights instead.

Each framework runs in its own child process, one after the other, so that peak memory is
its own (JAX: ``device.memory_stats()["peak_bytes_in_use"]`` where the device reports it,
else the process's peak RSS; torch: ``torch.cuda.max_memory_allocated`` on a GPU, else
peak RSS). The JAX editor edits a batch of B views in one call (``edit_many``); the torch
editor edits one view per call, so its batch of B is B calls. Seconds per edit = batch
time / B.

    python benchmarks/ip2p.py --smoke                                   # tiny model, CI
    python benchmarks/ip2p.py --arch sd15 --size 512 --steps 20 --batch 1 8   # a GPU
    python benchmarks/ip2p.py --arch sd15 --size 128 --steps 2 --batch 1 2    # the CPU record
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from common import parse_args, peak_rss_mb, write_json

import jax

PROMPT = "turn the bear into a panda"


def _extra(p):
    p.add_argument("--arch", choices=["tiny", "sd15"], default="sd15")
    p.add_argument("--weights", type=Path, default=None, help="real diffusers folder instead")
    p.add_argument("--size", type=int, default=None, help="model size (default 512; CPU 128)")
    p.add_argument("--steps", type=int, default=None, help="DDIM steps (default 20; CPU 2)")
    p.add_argument("--batch", type=int, nargs="+", default=None,
                   help="views per batch (default 1 8; CPU 1 2)")
    p.add_argument("--frameworks", nargs="+", choices=["jax", "torch"], default=["jax", "torch"])
    p.add_argument("--torch-device", default=None, help="torch device (default cuda:0 or cpu)")
    p.add_argument("--worker", choices=["jax", "torch"], default=None, help=argparse_hidden())
    p.add_argument("--folder", type=Path, default=None, help=argparse_hidden())


def argparse_hidden():
    import argparse

    return argparse.SUPPRESS


def _tokenizer(tmp: Path):
    from transformers import CLIPTokenizer

    letters = "abcdefghijklmnopqrstuvwxyz"
    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for token in list(letters) + [c + "</w>" for c in letters]:
        vocab[token] = len(vocab)
    (tmp / "vocab.json").write_text(json.dumps(vocab))
    (tmp / "merges.txt").write_text("#version: 0.2\n")
    return CLIPTokenizer(vocab=str(tmp / "vocab.json"), merges=str(tmp / "merges.txt"),
                         model_max_length=77)


def random_components(arch: str, tmp: Path, seed: int = 0):
    """(unet, vae, text_encoder, tokenizer, scheduler) with random weights."""
    import torch
    from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel

    torch.manual_seed(seed)
    if arch == "sd15":
        unet = UNet2DConditionModel(
            sample_size=64, in_channels=8, out_channels=4, layers_per_block=2,
            block_out_channels=(320, 640, 1280, 1280),
            down_block_types=("CrossAttnDownBlock2D",) * 3 + ("DownBlock2D",),
            up_block_types=("UpBlock2D",) + ("CrossAttnUpBlock2D",) * 3,
            cross_attention_dim=768, attention_head_dim=8, norm_num_groups=32)
        vae = AutoencoderKL(
            in_channels=3, out_channels=3, latent_channels=4,
            block_out_channels=(128, 256, 512, 512),
            layers_per_block=2, down_block_types=("DownEncoderBlock2D",) * 4,
            up_block_types=("UpDecoderBlock2D",) * 4, norm_num_groups=32, sample_size=512)
        text = CLIPTextModel(CLIPTextConfig(
            vocab_size=49408, hidden_size=768, intermediate_size=3072, num_hidden_layers=12,
            num_attention_heads=12, max_position_embeddings=77, hidden_act="quick_gelu",
            bos_token_id=0, eos_token_id=1, pad_token_id=1))
    else:
        unet = UNet2DConditionModel(
            sample_size=8, in_channels=8, out_channels=4, layers_per_block=1,
            block_out_channels=(16, 32), down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
            up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"), cross_attention_dim=32,
            attention_head_dim=4, norm_num_groups=8)
        vae = AutoencoderKL(
            in_channels=3, out_channels=3, latent_channels=4, block_out_channels=(8, 8, 8, 8),
            layers_per_block=1, down_block_types=("DownEncoderBlock2D",) * 4,
            up_block_types=("UpDecoderBlock2D",) * 4, norm_num_groups=4, sample_size=64)
        text = CLIPTextModel(CLIPTextConfig(
            vocab_size=60, hidden_size=32, intermediate_size=37, num_hidden_layers=2,
            num_attention_heads=4, max_position_embeddings=77, bos_token_id=0, eos_token_id=1,
            pad_token_id=1))
    scheduler = DDIMScheduler(beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear",
                              clip_sample=False, set_alpha_to_one=False, steps_offset=1)
    return unet, vae, text, _tokenizer(tmp), scheduler


def save_random_pipeline(arch: str, root: Path) -> Path:
    """``random_components(arch)`` saved in diffusers' layout (what both editors load)."""
    import warnings

    root.mkdir(parents=True)
    unet, vae, text, tokenizer, scheduler = random_components(arch, root)
    unet.save_pretrained(root / "unet")
    vae.save_pretrained(root / "vae")
    text.save_pretrained(root / "text_encoder")
    tokenizer.save_pretrained(root / "tokenizer")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        scheduler.save_pretrained(root / "scheduler")
    (root / "model_index.json").write_text(json.dumps(
        {"_class_name": "StableDiffusionInstructPix2PixPipeline"}))
    return root


def _images(batch: int, hw) -> np.ndarray:
    return np.random.default_rng(0).uniform(0, 1, (batch, *hw, 3)).astype(np.float32)


def run_jax(args, folder: Path, size: int, steps: int, batches, hw) -> dict:
    """JAX editor: compile and steady-state time of edit_many per batch size, peak memory."""
    from jaxedit.editors.jax_ip2p import JaxIP2PEditor

    t0 = time.perf_counter()
    editor = JaxIP2PEditor.from_pretrained(folder, size=size, steps=steps)
    load_s = time.perf_counter() - t0
    emb = editor.encode(PROMPT)
    out = {"framework": "jax", "device": str(editor.devices[0]), "dtype": editor.dtype,
           "load_s": load_s, "batches": {}}
    for b in batches:
        images = _images(b, hw)
        keys = jax.random.split(jax.random.key(0), b)

        def one():
            t = time.perf_counter()
            editor.edit_many(images, images, emb, keys,
                             timestep_range=(0.85, 0.85)).block_until_ready()
            return time.perf_counter() - t

        first = one()
        times = [one() for _ in range(args.repeats)]
        med = float(np.median(times))
        out["batches"][str(b)] = {"first_call_s": first, "compile_s": max(first - med, 0.0),
                                  "batch_median_s": med, "s_per_edit": med / b,
                                  "repeats": args.repeats}
    stats = editor.devices[0].memory_stats() or {}
    out["peak_device_mb"] = (stats["peak_bytes_in_use"] / 2**20
                             if "peak_bytes_in_use" in stats else None)
    out["peak_rss_mb"] = peak_rss_mb()
    out["jax"] = jax.__version__
    return out


def run_torch(args, folder: Path, size: int, steps: int, batches, hw) -> dict:
    """torch reference: B single-view edits per batch (it has no batched edit), peak memory."""
    import torch

    from jaxedit.editors.ip2p import InstructPix2PixEditor

    if args.smoke:
        torch.set_num_threads(1)  # toy tensors: extra threads only add contention
    device = torch.device(args.torch_device or ("cuda:0" if torch.cuda.is_available() else "cpu"))
    t0 = time.perf_counter()
    editor = InstructPix2PixEditor.from_pretrained(folder, device=device, size=size, steps=steps)
    load_s = time.perf_counter() - t0
    emb = editor.encode(PROMPT)

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    out = {"framework": "torch", "device": str(device), "dtype": str(editor.dtype),
           "load_s": load_s, "batches": {}}
    for b in batches:
        images = _images(b, hw)

        def one():
            sync()
            t = time.perf_counter()
            for i in range(b):
                editor.edit(images[i], images[i], emb, jax.random.key(i),
                            timestep_range=(0.85, 0.85))
            sync()
            return time.perf_counter() - t

        first = one()
        times = [one() for _ in range(args.repeats)]
        med = float(np.median(times))
        out["batches"][str(b)] = {"first_call_s": first, "batch_median_s": med,
                                  "s_per_edit": med / b, "repeats": args.repeats}
    out["peak_device_mb"] = (torch.cuda.max_memory_allocated(device) / 2**20
                             if device.type == "cuda" else None)
    out["peak_rss_mb"] = peak_rss_mb()
    out["torch"] = torch.__version__
    out["torch_threads"] = torch.get_num_threads()
    return out


def _settings(args):
    import jax

    on_cpu = jax.default_backend() == "cpu"
    arch = "tiny" if args.smoke else args.arch
    size = args.size or (64 if arch == "tiny" else 128 if on_cpu else 512)
    steps = args.steps or (2 if (on_cpu or args.smoke) else 20)
    # Smoke: one batch size, since each is a compilation (CI's budget is seconds).
    batches = args.batch or ([2] if args.smoke else [1, 2] if on_cpu else [1, 8])
    args.repeats = args.repeats or (1 if (args.smoke or on_cpu) else 5)
    hw = (48, 40) if args.smoke else (size, size)
    return arch, size, steps, batches, hw


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv, extra=_extra)
    arch, size, steps, batches, hw = _settings(args)
    if args.worker is not None:  # a child: one framework, JSON on stdout
        run = run_jax if args.worker == "jax" else run_torch
        print("RESULT " + json.dumps(run(args, args.folder, size, steps, batches, hw)))
        return
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.weights
        if folder is None:
            t0 = time.perf_counter()
            folder = save_random_pipeline(arch, Path(tmp) / f"random-{arch}")
            print(f"random {arch} pipeline saved in {time.perf_counter() - t0:.0f} s", flush=True)
        results = {}
        for fw in args.frameworks:  # one after the other: each child's memory is its own
            cmd = [sys.executable, __file__, "--worker", fw, "--folder", str(folder),
                   "--arch", args.arch, "--repeats", str(args.repeats), "--size", str(size),
                   "--steps", str(steps), "--batch", *map(str, batches)]
            cmd += ["--smoke"] if args.smoke else []
            cmd += ["--torch-device", args.torch_device] if args.torch_device else []
            done = subprocess.run(cmd, capture_output=True, text=True, env=os.environ.copy())
            if done.returncode:
                sys.exit(f"{fw} worker failed:\n{done.stderr[-3000:]}")
            results[fw] = json.loads([x for x in done.stdout.splitlines()
                                      if x.startswith("RESULT ")][-1][len("RESULT "):])
            for b, r in results[fw]["batches"].items():
                print(f"{fw:5s} batch {b}: {r['s_per_edit']:.3f} s per edit"
                      + (f" (compile {r['compile_s']:.1f} s)" if "compile_s" in r else ""),
                      flush=True)
    result = {"smoke": args.smoke, "arch": "weights" if args.weights else arch,
              "load_average_1min": os.getloadavg()[0],  # a shared machine's timings need it
              "model_size": size, "image_hw": list(hw), "ddim_steps": steps,
              "unet_batch_per_view": 3, "timestep": 0.85, "batches": batches, **results}
    if "jax" in results and "torch" in results:
        result["speedup_jax_over_torch"] = {
            b: results["torch"]["batches"][b]["s_per_edit"] / results["jax"]["batches"][b]
            ["s_per_edit"] for b in results["jax"]["batches"]}
    write_json(args.out, "ip2p", result)


if __name__ == "__main__":
    main()
