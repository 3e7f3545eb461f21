"""InstructPix2Pix editor cost: one view edit (VAE encode, DDIM with three-branch guidance,
decode) and the text encoder, with the real architecture at random weights or real weights.

The time of a diffusion edit does not depend on the weight values, so ``--arch sd15``
builds Stable Diffusion 1.5's UNet (8 input channels, as IP2P), VAE and CLIP ViT-L text
encoder from their published configurations with random weights: a GPU user can measure
the cost of a full edit before downloading anything. ``--weights DIR`` uses real weights.

    python benchmarks/ip2p.py --smoke                         # tiny model, CI
    python benchmarks/ip2p.py --arch sd15 --size 512 --steps 20 --torch-device cuda:0
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import numpy as np
from common import parse_args, peak_rss_mb, write_json

import jax


def _extra(p):
    p.add_argument("--arch", choices=["tiny", "sd15"], default="sd15")
    p.add_argument("--weights", type=Path, default=None, help="real diffusers folder instead")
    p.add_argument("--size", type=int, default=None, help="model size (default 512; CPU 256)")
    p.add_argument("--steps", type=int, default=None, help="DDIM steps (default 20; CPU 2)")
    p.add_argument("--image", type=int, nargs=2, default=(512, 512), metavar=("H", "W"))
    p.add_argument("--torch-device", default=None, help="torch device (default cuda:0 or cpu)")


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


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv, extra=_extra)
    import torch

    from jaxedit.edit.ip2p import InstructPix2PixEditor

    if args.smoke:
        torch.set_num_threads(1)  # toy tensors: extra threads only add contention
    device = torch.device(args.torch_device or ("cuda:0" if torch.cuda.is_available() else "cpu"))
    on_cpu = device.type == "cpu"
    arch = "tiny" if args.smoke else args.arch
    size = args.size or (64 if arch == "tiny" else 256 if on_cpu else 512)
    steps = args.steps or (2 if (on_cpu or args.smoke) else 20)
    image_hw = (48, 40) if args.smoke else tuple(args.image)
    repeats = args.repeats or (2 if (args.smoke or on_cpu) else 5)

    t0 = time.perf_counter()
    if args.weights is not None:
        editor = InstructPix2PixEditor.from_pretrained(args.weights, device=device, size=size,
                                                       steps=steps)
        arch = f"weights:{args.weights}"
    else:
        with tempfile.TemporaryDirectory() as tmp:
            editor = InstructPix2PixEditor(*random_components(arch, Path(tmp)), device=device,
                                           size=size, steps=steps, source=f"random-{arch}")
    load_s = time.perf_counter() - t0

    rng = np.random.default_rng(0)
    image = rng.uniform(0, 1, image_hw + (3,)).astype(np.float32)
    t0 = time.perf_counter()
    emb = editor.encode("turn the bear into a panda")
    encode_ms = 1e3 * (time.perf_counter() - t0)

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    def one(i):
        sync()
        t = time.perf_counter()
        # A fixed timestep range so every repeat runs the same number of DDIM steps.
        editor.edit(image, image, emb, jax.random.key(i), timestep_range=(0.85, 0.85))
        sync()
        return time.perf_counter() - t

    first = one(0)
    times = [one(i + 1) for i in range(repeats)]
    med = float(np.median(times))
    result = {
        "smoke": args.smoke, "arch": arch, "device": str(device), "dtype": str(editor.dtype),
        "model_size": size, "image_hw": list(image_hw), "ddim_steps": steps,
        "unet_passes_per_edit": steps, "unet_batch": 3,
        "load_s": load_s, "encode_ms": encode_ms, "first_edit_ms": 1e3 * first,
        "edit_median_ms": 1e3 * med, "edit_min_ms": 1e3 * min(times), "repeats": repeats,
        "ms_per_ddim_step": 1e3 * med / steps, "peak_rss_mb": peak_rss_mb(),
        "torch": torch.__version__, "torch_threads": torch.get_num_threads(),
    }
    if device.type == "cuda":
        result["cuda_peak_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
        result["gpu"] = torch.cuda.get_device_name(device)
    print(f"ip2p {arch} on {device} ({editor.dtype}), size {size}, {steps} steps: "
          f"{1e3 * med:.0f} ms per edit ({1e3 * med / steps:.0f} ms per DDIM step)")
    write_json(args.out, "ip2p", result)


if __name__ == "__main__":
    main()
