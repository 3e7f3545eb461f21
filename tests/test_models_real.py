"""jaxedit.models at the REAL Stable Diffusion 1.5 / InstructPix2Pix architecture, random weights.

The tiny configs of test_models.py prove the mapping; this proves the full-size networks
(UNet 320/640/1280/1280 with 8 input channels, VAE 128/256/512/512, CLIP ViT-L/14's text
tower) load from ``save_pretrained`` folders and match diffusers / transformers in fp32
within 1e-4 relative. One network at a time, freed before the next (the UNet is 860 M
parameters, 3.4 GB per framework). Minutes on a CPU, so it runs only with
``JAXEDIT_REAL_CONFIG=1``; ``JAXEDIT_REAL_CONFIG_OUT=FILE`` also writes the measured
differences and times as JSON (the committed record: benchmarks/results/cpu/
models_equivalence.json).
"""

from __future__ import annotations

import gc
import json
import os
import platform
import resource
import time
from pathlib import Path

import numpy as np
import pytest

pytestmark = [pytest.mark.slow, pytest.mark.skipif(
    os.environ.get("JAXEDIT_REAL_CONFIG") != "1",
    reason="real-size networks take minutes: set JAXEDIT_REAL_CONFIG=1")]

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")
pytest.importorskip("transformers")

import equinox as eqx  # noqa: E402
import jax  # noqa: E402

from jaxedit.models import AutoencoderKL, CLIPTextEncoder, UNet2DCondition, load_module  # noqa: E402
from jaxedit.models.memory import CLIP_L14_TEXT, SD15_UNET_IP2P, SD15_VAE  # noqa: E402
from test_models import nchw, nhwc, perturb  # noqa: E402

# Stable Diffusion 1.5 as timbrooks/instruct-pix2pix ships it: the configs the memory estimate
# builds (jaxedit.models.memory), so both describe one architecture.
SD15_UNET = SD15_UNET_IP2P
REL_TOL = 1e-4
# Noise on every parameter, kept small next to the real layers' weights (std ~ 0.005-0.02).
NOISE = dict(scale=0.3, floor=0.002)


@pytest.fixture(scope="module")
def record():
    """Collects each network's figures; written as JSON at the end when asked to."""
    import diffusers
    import transformers
    rec = {"what": "jaxedit.models vs diffusers/transformers at the real SD 1.5 / IP2P configs, "
                   "random perturbed weights, fp32, CPU",
           "command": "JAXEDIT_REAL_CONFIG=1 JAXEDIT_REAL_CONFIG_OUT=FILE python -m pytest -s "
                      "tests/test_models_real.py",
           "relative_tolerance": REL_TOL,
           "versions": {"torch": torch.__version__, "diffusers": diffusers.__version__,
                        "transformers": transformers.__version__, "jax": jax.__version__,
                        "equinox": eqx.__version__, "python": platform.python_version()},
           "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count()},
           "networks": {}}
    yield rec
    out = os.environ.get("JAXEDIT_REAL_CONFIG_OUT")
    if out:
        rec["peak_rss_gib"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 2)
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(json.dumps(rec, indent=2) + "\n")


def compare(name: str, ours, ref, record: dict, **extra) -> None:
    ours, ref = np.asarray(ours, np.float64), np.asarray(ref, np.float64)
    assert ours.shape == ref.shape
    err, scale = float(np.abs(ours - ref).max()), float(np.abs(ref).max())
    entry = {"shape": list(ref.shape), "max_abs_diff": err, "max_abs_ref": scale,
             "relative": err / scale, **extra}
    record[name] = entry
    print(f"\n{name}: max |diff| {err:.3g}, max |ref| {scale:.3g}, relative {err / scale:.3g}")
    assert err <= REL_TOL * scale, entry


def _save(model, folder: Path) -> int:
    """Save, count parameters, and free the torch model (one network in memory at a time)."""
    params = sum(p.numel() for p in model.parameters())
    model.save_pretrained(folder)
    return params


def _free():
    gc.collect()
    jax.clear_caches()


def test_real_unet(tmp_path, record):
    from diffusers import UNet2DConditionModel
    t0 = time.perf_counter()
    torch.manual_seed(0)
    model = perturb(UNet2DConditionModel(**SD15_UNET), 10, **NOISE)
    rng = np.random.default_rng(0)
    sample = rng.standard_normal((2, 16, 16, 8)).astype(np.float32)  # latents of 128 x 128 images
    context = rng.standard_normal((2, 77, 768)).astype(np.float32)
    t = np.array([981, 17], np.int32)
    with torch.no_grad():
        t1 = time.perf_counter()
        ref = nhwc(model(nchw(sample), torch.from_numpy(t).long(), torch.from_numpy(context)).sample)
        torch_s = time.perf_counter() - t1
    params = _save(model, tmp_path / "unet")
    del model
    _free()
    t1 = time.perf_counter()
    unet = load_module(tmp_path / "unet", UNet2DCondition.from_config)
    load_s = time.perf_counter() - t1
    t1 = time.perf_counter()
    ours = np.asarray(eqx.filter_jit(lambda m, x, t, c: m(x, t, c))(unet, sample, t, context))
    jax_s = time.perf_counter() - t1
    del unet
    _free()
    entry = record["networks"]
    compare("unet_eps", ours, ref, entry, parameters=params, torch_forward_s=round(torch_s, 2),
            jax_load_s=round(load_s, 2), jax_compile_and_run_s=round(jax_s, 2),
            total_s=round(time.perf_counter() - t0, 1))


def test_real_vae(tmp_path, record):
    from diffusers import AutoencoderKL as TorchVAE
    t0 = time.perf_counter()
    torch.manual_seed(1)
    model = perturb(TorchVAE(**SD15_VAE), 11, **NOISE)
    rng = np.random.default_rng(1)
    image = rng.uniform(-1, 1, (1, 128, 128, 3)).astype(np.float32)
    latent = rng.standard_normal((1, 16, 16, 4)).astype(np.float32)
    with torch.no_grad():
        posterior = model.encode(nchw(image)).latent_dist
        ref_mean, ref_logvar = nhwc(posterior.mean), nhwc(posterior.logvar)
        ref_dec = nhwc(model.decode(nchw(latent)).sample)
    params = _save(model, tmp_path / "vae")
    del model
    _free()
    vae = load_module(tmp_path / "vae", AutoencoderKL.from_config)
    mean, logvar = eqx.filter_jit(lambda m, x: m.encode(x))(vae, image)
    dec = eqx.filter_jit(lambda m, z: m.decode(z))(vae, latent)
    del vae
    _free()
    entry = record["networks"]
    compare("vae_encode_mean", mean, ref_mean, entry, parameters=params)
    compare("vae_encode_logvar", logvar, ref_logvar, entry)
    compare("vae_decode", dec, ref_dec, entry, total_s=round(time.perf_counter() - t0, 1))


def test_real_text_encoder(tmp_path, record):
    from transformers import CLIPTextConfig, CLIPTextModel
    t0 = time.perf_counter()
    torch.manual_seed(2)
    model = perturb(CLIPTextModel(CLIPTextConfig(**CLIP_L14_TEXT)), 12, **NOISE)
    rng = np.random.default_rng(2)
    ids = rng.integers(0, 49406, (2, 77)).astype(np.int32)
    ids[:, 0], ids[0, 9:], ids[1, 40:] = 49406, 49407, 49407  # bos, prompt, eos + eos padding
    with torch.no_grad():
        ref = model(torch.from_numpy(ids).long()).last_hidden_state.numpy()
    params = _save(model, tmp_path / "text_encoder")
    del model
    _free()
    enc = load_module(tmp_path / "text_encoder", CLIPTextEncoder.from_config,
                      prefix=CLIPTextEncoder.CHECKPOINT_PREFIX)
    ours = eqx.filter_jit(lambda m, i: m(i))(enc, ids)
    compare("text_encoder_last_hidden_state", ours, ref, record["networks"], parameters=params,
            total_s=round(time.perf_counter() - t0, 1))
