"""InstructPix2Pix editor on a tiny random pipeline the test builds and saves itself.

The pipeline has the real architecture classes (UNet2DConditionModel with 8 input channels,
AutoencoderKL with the x8 downsampling, CLIPTextModel, a CLIPTokenizer from a vocabulary
written here, DDIMScheduler with SD 1.5's betas) at toy widths, saved in diffusers'
save_pretrained layout and loaded back through ``InstructPix2PixEditor.from_pretrained``.
"""

from __future__ import annotations

import importlib
import json
import shutil
import subprocess
import sys
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxedit.editors.base import Editor, interpolate_embedding
from jaxedit.errors import DataError

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")
pytest.importorskip("transformers")

from jaxedit.editors import ip2p  # noqa: E402

PROMPT = "turn the bear into a panda"


def build_tiny_ip2p(root):
    """Write a tiny random InstructPix2Pix pipeline to ``root`` (diffusers layout)."""
    from diffusers import AutoencoderKL, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer

    torch.manual_seed(0)
    UNet2DConditionModel(
        sample_size=8, in_channels=8, out_channels=4, layers_per_block=1,
        block_out_channels=(16, 32), down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
        up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"), cross_attention_dim=32,
        attention_head_dim=4, norm_num_groups=8).save_pretrained(root / "unet")
    AutoencoderKL(
        in_channels=3, out_channels=3, latent_channels=4, block_out_channels=(8, 8, 8, 8),
        layers_per_block=1, down_block_types=("DownEncoderBlock2D",) * 4,
        up_block_types=("UpDecoderBlock2D",) * 4, norm_num_groups=4,
        sample_size=64).save_pretrained(root / "vae")
    letters = "abcdefghijklmnopqrstuvwxyz"
    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for token in list(letters) + [c + "</w>" for c in letters] + ["th", "the</w>"]:
        vocab[token] = len(vocab)
    CLIPTextModel(CLIPTextConfig(
        vocab_size=len(vocab), hidden_size=32, intermediate_size=37, num_hidden_layers=2,
        num_attention_heads=4, max_position_embeddings=77, bos_token_id=0, eos_token_id=1,
        pad_token_id=1)).save_pretrained(root / "text_encoder")
    tok_dir = root / "tokenizer"
    tok_dir.mkdir(parents=True)
    (tok_dir / "vocab.json").write_text(json.dumps(vocab))
    (tok_dir / "merges.txt").write_text("#version: 0.2\nt h\nth e</w>\n")
    CLIPTokenizer(vocab=str(tok_dir / "vocab.json"), merges=str(tok_dir / "merges.txt"),
                  model_max_length=77).save_pretrained(tok_dir)
    write_scheduler_and_index(root)
    return root


def write_scheduler_and_index(root):
    """The pipeline's scheduler/ and model_index.json, as timbrooks/instruct-pix2pix ships them.

    It ships an Euler-ancestral scheduler config; the editors read it as Stable Diffusion's
    DDIM, so the tests write the same kind of file.
    """
    from diffusers import EulerAncestralDiscreteScheduler

    with warnings.catch_warnings():  # diffusers' own NumPy 2 deprecation, not ours
        warnings.simplefilter("ignore", DeprecationWarning)
        EulerAncestralDiscreteScheduler(beta_start=0.00085, beta_end=0.012,
                                        beta_schedule="scaled_linear",
                                        steps_offset=1).save_pretrained(root / "scheduler")
    (root / "model_index.json").write_text(json.dumps(
        {"_class_name": "StableDiffusionInstructPix2PixPipeline"}))


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # toy tensors: threads only add contention on a shared 2-core box
    yield build_tiny_ip2p(tmp_path_factory.mktemp("ip2p") / "tiny-ip2p")
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def editor(weights):
    return ip2p.InstructPix2PixEditor.from_pretrained(weights, device="cpu", size=64, steps=2)


def _image(seed, shape=(48, 40, 3)):
    return np.random.default_rng(seed).uniform(0, 1, shape).astype(np.float32)


def test_loads_as_editor(editor):
    assert isinstance(editor, Editor) and editor.name == "ip2p"
    assert editor.device.type == "cpu" and editor.dtype == torch.float32
    assert editor.vae_factor == 8
    d = editor.describe()
    assert d["unet_in_channels"] == 8 and d["steps"] == 2 and d["size"] == 64


def test_encode(editor):
    e, null = editor.encode(PROMPT), editor.encode("")
    assert isinstance(e, np.ndarray) and e.dtype == np.float32 and e.shape == (77, 32)
    assert not np.allclose(e, null)
    np.testing.assert_array_equal(editor.encode(PROMPT), e)
    # The cache hands out copies: a caller cannot corrupt later embeddings.
    e[:] = 0
    assert np.abs(editor.encode(PROMPT)).sum() > 0


def test_edit_shape_range_determinism(editor):
    img, orig = _image(0), _image(1)
    e = editor.encode(PROMPT)
    out = editor.edit(img, orig, e, jax.random.key(0), timestep_range=(0.5, 0.9))
    assert out.shape == img.shape and out.dtype == np.float32
    assert out.min() >= 0.0 and out.max() <= 1.0 and np.isfinite(out).all()
    again = editor.edit(img, orig, e, jax.random.key(0), timestep_range=(0.5, 0.9))
    np.testing.assert_array_equal(out, again)
    other = editor.edit(img, orig, e, jax.random.key(1), timestep_range=(0.5, 0.9))
    assert np.abs(other - out).max() > 1e-4
    # JAX arrays (DLPack) and raw uint32 keys give the same bits as NumPy / typed keys.
    via_jax = editor.edit(jnp.asarray(img), jnp.asarray(orig), jnp.asarray(e),
                          jax.random.PRNGKey(0), timestep_range=(0.5, 0.9))
    np.testing.assert_array_equal(out, via_jax)


def test_interpolated_embedding_end_points(editor):
    e_p, e_null = editor.encode(PROMPT), editor.encode("")
    np.testing.assert_array_equal(interpolate_embedding(e_p, e_null, 1.0), e_p)
    np.testing.assert_array_equal(interpolate_embedding(e_p, e_null, 0.0), e_null)
    img, key = _image(2), jax.random.key(3)
    edit = lambda emb: editor.edit(img, img, emb, key, timestep_range=(0.6, 0.6))  # noqa: E731
    np.testing.assert_array_equal(edit(interpolate_embedding(e_p, e_null, 1.0)), edit(e_p))
    np.testing.assert_array_equal(edit(interpolate_embedding(e_p, e_null, 0.0)), edit(e_null))
    half = edit(interpolate_embedding(e_p, e_null, 0.5))
    assert np.abs(half - edit(e_p)).max() > 1e-5 and np.abs(half - edit(e_null)).max() > 1e-5


@pytest.mark.parametrize("guidance", [(7.5, 1.5), (3.0, 0.25)])
def test_three_branch_guidance_reaches_unet(editor, monkeypatch, guidance):
    calls, steps = [], []
    forward = editor.unet.forward

    def recording_forward(sample, timestep, encoder_hidden_states, **kw):
        out = forward(sample, timestep, encoder_hidden_states, **kw)
        calls.append((sample.clone(), int(timestep), encoder_hidden_states.clone(),
                      out.sample.clone()))
        return out

    ddim = ip2p.ddim_step

    def recording_step(sample, model_output, a_t, a_prev, *args):
        steps.append((model_output.clone(), a_t, a_prev))
        return ddim(sample, model_output, a_t, a_prev, *args)

    monkeypatch.setattr(editor.unet, "forward", recording_forward)
    monkeypatch.setattr(ip2p, "ddim_step", recording_step)
    e_p, e_null = editor.encode(PROMPT), editor.encode("")
    editor.edit(_image(4), _image(5), e_p, jax.random.key(7), timestep_range=(0.5, 0.5),
                guidance=guidance)

    assert [c[1] for c in calls] == [500, 250]  # T = 0.5 x 1000, 2 evenly spaced DDIM steps
    # The conditioning latent is the VAE mode of the original at model size, unscaled.
    orig = torch.from_numpy(_image(5)).permute(2, 0, 1)[None]
    orig = torch.nn.functional.interpolate(orig, size=(64, 56), mode="bilinear",
                                           align_corners=False, antialias=True)
    with torch.no_grad():
        mode = editor.vae.encode(orig * 2 - 1).latent_dist.mode()
    torch.testing.assert_close(calls[0][0][:1, 4:], mode, rtol=1e-4, atol=1e-5)
    alphas = editor.alphas_cumprod
    assert [(s[1], s[2]) for s in steps] == [(alphas[500], alphas[250]),
                                             (alphas[250], editor.final_alpha)]
    s_t, s_i = guidance
    for (sample, _, hidden, eps), (combined, _, _) in zip(calls, steps):
        # 48x40 -> model size 64x56 (longer side 64, multiples of 8) -> latents 8x7.
        assert sample.shape == (3, 8, 8, 7) and hidden.shape == (3, 77, 32)
        # Same noisy latent in every branch; conditioning latent in the first two, zeros last.
        assert torch.equal(sample[0, :4], sample[1, :4])
        assert torch.equal(sample[0, :4], sample[2, :4])
        assert torch.equal(sample[0, 4:], sample[1, 4:]) and sample[0, 4:].abs().sum() > 0
        assert torch.count_nonzero(sample[2, 4:]) == 0
        # Text branch gets e, the other two E("").
        np.testing.assert_array_equal(hidden[0].numpy(), e_p)
        np.testing.assert_array_equal(hidden[1].numpy(), e_null)
        np.testing.assert_array_equal(hidden[2].numpy(), e_null)
        ti, i, u = eps.float()
        torch.testing.assert_close(combined[0], u + s_t * (ti - i) + s_i * (i - u))


@pytest.mark.parametrize("clip", [True, False])
def test_ddim_step_matches_diffusers_scheduler(editor, clip):
    # IP2P's Euler config read as SD 1.x's DDIM: no x0 clipping, final alpha = alpha_0.
    assert type(editor.scheduler).__name__ == "DDIMScheduler"
    assert editor.clip_sample is None
    assert editor.final_alpha == pytest.approx(editor.alphas_cumprod[0])
    sched = editor.scheduler.__class__.from_config(editor.scheduler.config, clip_sample=clip)
    sched.set_timesteps(10)
    gen = torch.Generator().manual_seed(0)
    sample = torch.randn(1, 4, 8, 8, generator=gen)
    a = editor.alphas_cumprod
    for t in sched.timesteps.tolist():
        eps = torch.randn(1, 4, 8, 8, generator=gen)
        prev = t - sched.config.num_train_timesteps // 10
        a_prev = a[prev] if prev >= 0 else editor.final_alpha
        ours = ip2p.ddim_step(sample, 3 * eps, a[t], a_prev, "epsilon", 1.0 if clip else None)
        theirs = sched.step(3 * eps, t, sample).prev_sample  # large eps: clipping matters
        torch.testing.assert_close(ours, theirs, rtol=1e-5, atol=1e-5)
        sample = theirs


def test_explicit_ddim_config_is_respected(weights, tmp_path):
    from diffusers import DDIMScheduler

    folder = tmp_path / "w"
    shutil.copytree(weights, folder)
    shutil.rmtree(folder / "scheduler")
    DDIMScheduler(beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear",
                  clip_sample=True, clip_sample_range=2.0,
                  set_alpha_to_one=True).save_pretrained(folder / "scheduler")
    ed = ip2p.InstructPix2PixEditor.from_pretrained(folder, device="cpu", size=64, steps=2)
    assert ed.clip_sample == 2.0 and ed.final_alpha == 1.0


@settings(max_examples=30, deadline=None)
@given(lo=st.floats(0, 1), width=st.floats(0, 1), steps=st.integers(1, 50),
       seed=st.integers(0, 2**32 - 1))
def test_timestep_draw_and_schedule(lo, width, steps, seed):
    hi = min(1.0, lo + width)
    t = ip2p.draw_timestep(jax.random.PRNGKey(seed), (lo, hi))
    assert 1 <= t <= 999
    assert max(1, round(lo * 1000)) - 1 <= t <= max(round(hi * 1000), 1) + 1
    ts = ip2p.timestep_schedule(t, steps)
    assert ts[0] == t and all(a > b for a, b in zip(ts, ts[1:])) and ts[-1] >= 1
    assert len(ts) == min(steps, len(ts)) and len(ts) <= steps
    k_t, seed_torch = ip2p.seed_from_key(jax.random.PRNGKey(seed))
    assert 0 <= seed_torch < 2**63


@settings(max_examples=30, deadline=None)
@given(h=st.integers(1, 3000), w=st.integers(1, 3000), size=st.sampled_from([None, 64, 512]))
def test_model_size(h, w, size):
    mh, mw = ip2p.model_size(h, w, size)
    assert mh % 8 == 0 and mw % 8 == 0 and mh >= 8 and mw >= 8
    if size is not None:
        assert abs(max(mh, mw) - size) <= 8


@pytest.mark.parametrize("shape", [(64, 64, 3), (30, 50, 3)])
def test_sizes_round_trip(editor, shape):
    """Model-size views skip resizing; odd sizes go to multiples of 8 and back."""
    img = _image(6, shape)
    out = editor.edit(img, img, editor.encode(PROMPT), jax.random.key(0), timestep_range=(0.3, 0.3))
    assert out.shape == shape and np.isfinite(out).all()


def test_half_precision_path(weights, editor):
    """The GPU's fp16 code path (casts at the network boundaries, fp32 latents and DDIM),
    run on the CPU: it agrees with fp32 far more closely than two keys differ."""
    half = ip2p.load_editor(weights, device="cpu", dtype=torch.float16, size=64, steps=2)
    assert half.unet.dtype == torch.float16 and half.vae.dtype == torch.float16
    img, key = _image(7), jax.random.key(11)
    e = half.encode(PROMPT)
    assert e.dtype == np.float32
    out16 = half.edit(img, img, e, key, timestep_range=(0.7, 0.7))
    out32 = editor.edit(img, img, editor.encode(PROMPT), key, timestep_range=(0.7, 0.7))
    assert out16.dtype == np.float32 and np.isfinite(out16).all()
    assert np.abs(out16 - out32).mean() < 5e-3


def test_load_editor_factory(weights):
    ed = ip2p.load_editor(weights, device="cpu", dtype="fp32", size=32, steps=1)
    assert ed.size == 32 and ed.steps == 1 and ed.source == str(weights)
    assert ed.dtype == torch.float32
    with pytest.raises(DataError, match="dtype"):
        ip2p.load_editor(weights, device="cpu", dtype="int8")
    with pytest.raises(DataError, match="not a multiple of 8"):
        ip2p.load_editor(weights, device="cpu", size=60)


def test_bad_inputs(editor):
    e = editor.encode(PROMPT)
    with pytest.raises(DataError, match="image"):
        editor.edit(np.zeros((8, 8, 4), np.float32), np.zeros((8, 8, 3), np.float32), e,
                    jax.random.key(0))
    with pytest.raises(DataError, match="embedding"):
        editor.edit(_image(0), _image(0), e[:10], jax.random.key(0))
    with pytest.raises(DataError, match="timestep_range"):
        editor.edit(_image(0), _image(0), e, jax.random.key(0), timestep_range=(0.9, 0.1))


def test_missing_weights(weights, tmp_path, monkeypatch):
    with pytest.raises(DataError) as err:
        ip2p.InstructPix2PixEditor.from_pretrained(tmp_path / "nowhere")
    msg = str(err.value)
    assert "nowhere" in msg and "timbrooks/instruct-pix2pix" in msg
    # the library names no flag; the CLI adds "(given as --ip2p-weights)" (test_cli_flags)
    assert "huggingface-cli download" in msg and "\n" not in msg

    partial = tmp_path / "partial"
    shutil.copytree(weights, partial)
    shutil.rmtree(partial / "unet")
    with pytest.raises(DataError, match="missing unet/config.json"):
        ip2p.InstructPix2PixEditor.from_pretrained(partial)

    shutil.copytree(weights / "unet", partial / "unet")
    (partial / "unet" / "diffusion_pytorch_model.safetensors").unlink()
    with pytest.raises(DataError, match=r"unet: cannot load"):
        ip2p.InstructPix2PixEditor.from_pretrained(partial)

    # A Hub id that is not in the (empty) local cache: no network attempt, a clear error.
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    with pytest.raises(DataError, match="not in the local Hugging Face cache"):
        ip2p.InstructPix2PixEditor.from_pretrained("someone/not-cached-model")


def test_rejects_plain_stable_diffusion_unet(weights, tmp_path):
    from diffusers import UNet2DConditionModel

    sd = tmp_path / "sd"
    shutil.copytree(weights, sd)
    cfg = json.loads((sd / "unet" / "config.json").read_text())
    cfg["in_channels"] = 4
    shutil.rmtree(sd / "unet")
    UNet2DConditionModel.from_config(cfg).save_pretrained(sd / "unet")
    with pytest.raises(DataError, match="not an InstructPix2Pix model"):
        ip2p.InstructPix2PixEditor.from_pretrained(sd)


def test_import_without_torch_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "torch", None)
    monkeypatch.delitem(sys.modules, "jaxedit.editors.ip2p")
    with pytest.raises(ImportError, match=r"jaxedit\[ip2p\]"):
        importlib.import_module("jaxedit.editors.ip2p")


def test_core_never_imports_torch():
    code = ("import sys, jaxedit, jaxedit.edit, jaxedit.lpips, jaxedit.clip_metrics; "
            "bad = sorted(m for m in ('torch', 'diffusers', 'transformers') if m in sys.modules); "
            "assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
