"""jaxedit.models against diffusers / transformers (the oracle) on tiny random pipelines.

The tiny configs keep every block kind Stable Diffusion 1.5 / InstructPix2Pix uses
(CrossAttnDownBlock2D, DownBlock2D, UNetMidBlock2DCrossAttn, UpBlock2D, CrossAttnUpBlock2D,
layers_per_block 2, attention_head_dim as a head count, cross-attention, 8 input channels;
the VAE's asymmetric downsampling and mid-block attention; CLIP's causal quick-gelu layers).
Every parameter is perturbed before saving so that norms are not (1, 0) and no tensor is
zero: a wrong name mapping or layout cannot pass.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

torch = pytest.importorskip("torch")
diffusers = pytest.importorskip("diffusers")
transformers = pytest.importorskip("transformers")

from safetensors.numpy import load_file, save_file  # noqa: E402

from jaxedit.errors import DataError  # noqa: E402
from jaxedit.models import (AutoencoderKL, CLIPTextEncoder, CLIPTokenizer, UNet2DCondition,  # noqa: E402
                            cast, load_ip2p, load_module, set_query_chunk)
from jaxedit.models.layers import Attention, attention, standard_normal  # noqa: E402
from test_ip2p import write_scheduler_and_index  # noqa: E402 - the one scheduler writer
from without_torch import run_without_torch  # noqa: E402


TINY_UNET = dict(
    sample_size=8, in_channels=8, out_channels=4, layers_per_block=2,
    block_out_channels=(16, 32), down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
    up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
    cross_attention_dim=24, attention_head_dim=2, norm_num_groups=8)
TINY_VAE = dict(
    in_channels=3, out_channels=3, latent_channels=4, block_out_channels=(8, 16, 16),
    layers_per_block=2, down_block_types=("DownEncoderBlock2D",) * 3,
    up_block_types=("UpDecoderBlock2D",) * 3, norm_num_groups=4, sample_size=32)
TINY_CLIP = dict(hidden_size=24, intermediate_size=37, num_hidden_layers=2, num_attention_heads=4,
                 max_position_embeddings=77, hidden_act="quick_gelu")
PROMPTS = ["Turn him into a clown!", "the  THE\tthe thethe", "what's up? it'll rain, 42 C...",
           "émigré café ☃ naïve", "", "<|endoftext|> in the middle",
           " ".join(["make it look like a painting by van gogh"] * 12)]


def perturb(model: "torch.nn.Module", seed: int, scale: float = 0.3,
            floor: float = 0.02) -> "torch.nn.Module":
    """Add N(0, (scale std(p) + floor)^2) noise to every parameter p (norm weights leave 1,
    biases leave 0)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            std = float(p.std()) if p.numel() > 1 else 0.0
            p.add_(torch.randn(p.shape, generator=g) * (scale * std + floor))
    return model.eval()


def byte_level_vocab(words: list[str], merges: list[tuple[str, str]]) -> dict[str, int]:
    """A CLIP-style vocabulary: specials, the 256 byte symbols (plain and word-final), merges."""
    from tokenizers import pre_tokenizers
    alphabet = pre_tokenizers.ByteLevel.alphabet()
    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for token in sorted(alphabet) + [c + "</w>" for c in sorted(alphabet)] + words:
        vocab.setdefault(token, len(vocab))
    for a, b in merges:
        vocab.setdefault(a + b, len(vocab))
    return vocab


MERGES = [("t", "h"), ("th", "e</w>"), ("i", "n"), ("a", "n"), ("o", "n</w>"), ("c", "l"),
          ("cl", "o"), ("clo", "w"), ("clow", "n</w>"), ("t", "o</w>"), ("in", "to</w>")]


def write_tokenizer_files(folder: Path) -> Path:
    """vocab.json + merges.txt only (the reader's own BPE construction path)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "vocab.json").write_text(json.dumps(byte_level_vocab([], MERGES)))
    (folder / "merges.txt").write_text("#version: 0.2\n" + "".join(f"{a} {b}\n" for a, b in MERGES))
    return folder


def build_tiny_pipeline(root: Path, *, linear_projection: bool = False) -> Path:
    """A tiny random SD / IP2P pipeline in diffusers' layout (perturbed weights)."""
    from diffusers import AutoencoderKL as TorchVAE
    from diffusers import UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel
    from transformers import CLIPTokenizer as TorchTokenizer

    torch.manual_seed(0)
    perturb(UNet2DConditionModel(**TINY_UNET, use_linear_projection=linear_projection), 1) \
        .save_pretrained(root / "unet")
    perturb(TorchVAE(**TINY_VAE), 2).save_pretrained(root / "vae")
    tok_dir = write_tokenizer_files(root / "tokenizer")
    vocab_size = len(json.loads((tok_dir / "vocab.json").read_text()))
    perturb(CLIPTextModel(CLIPTextConfig(vocab_size=vocab_size, bos_token_id=0, eos_token_id=1,
                                         pad_token_id=1, **TINY_CLIP)), 3) \
        .save_pretrained(root / "text_encoder")
    TorchTokenizer(vocab=str(tok_dir / "vocab.json"), merges=str(tok_dir / "merges.txt"),
                   model_max_length=77).save_pretrained(tok_dir)
    write_scheduler_and_index(root)
    return root


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # toy tensors: threads only add contention on a shared 2-core box
    yield build_tiny_pipeline(tmp_path_factory.mktemp("models") / "tiny-ip2p")
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def models(tiny):
    return load_ip2p(tiny)


def nchw(x: np.ndarray) -> "torch.Tensor":
    return torch.from_numpy(np.ascontiguousarray(np.asarray(x).transpose(0, 3, 1, 2)))


def nhwc(t: "torch.Tensor") -> np.ndarray:
    return t.detach().numpy().transpose(0, 2, 3, 1)


def assert_close(ours, ref, rel=1e-4):
    ours, ref = np.asarray(ours, np.float64), np.asarray(ref, np.float64)
    assert ours.shape == ref.shape
    err, scale = np.abs(ours - ref).max(), np.abs(ref).max()
    assert scale > 1e-3, "reference output is degenerate"
    assert err <= rel * scale, f"max |diff| {err:.3g} > {rel} x max |ref| {scale:.3g}"


# ----------------------------------------------------------------------------- equivalence

@pytest.fixture(scope="module")
def unet_fn():
    """One jitted UNet call shared by the tests (compiled once per shape and dtype)."""
    return eqx.filter_jit(lambda unet, x, t, c: unet(x, t, c))


def test_random_init_draws_are_jax_random_normal_bit_for_bit():
    """Random weights come from one program per power-of-two length (standard_normal): the
    same bits as jax.random.normal of each shape, in each dtype a network is built in."""
    key = jax.random.key(7)
    for dtype in (jnp.float32, jnp.bfloat16):
        for shape in ((), (1,), (5, 7), (3, 3, 8, 16), (320,), (77, 24)):
            got, want = standard_normal(key, shape, dtype), jax.random.normal(key, shape, dtype)
            assert got.shape == want.shape and got.dtype == want.dtype
            np.testing.assert_array_equal(np.asarray(got, np.float32),
                                          np.asarray(want, np.float32))


@pytest.mark.parametrize("hw, timestep", [((8, 8), [981, 17]), ((7, 10), 500)])
def test_unet_matches_diffusers(tiny, models, unet_fn, hw, timestep):
    """eps for a batch of two; a scalar timestep is broadcast over the batch. (7, 10) is not
    a multiple of 2, so the up path must resize to the skips' sizes as diffusers does."""
    from diffusers import UNet2DConditionModel
    ref_model = UNet2DConditionModel.from_pretrained(tiny / "unet").eval()
    rng = np.random.default_rng(0)
    sample = rng.standard_normal((2, *hw, 8)).astype(np.float32)
    context = rng.standard_normal((2, 7, 24)).astype(np.float32)
    t = np.asarray(timestep, np.int32)
    with torch.no_grad():
        ref = ref_model(nchw(sample), torch.from_numpy(t).long() if t.ndim else int(t),
                        torch.from_numpy(context)).sample
    assert_close(unet_fn(models.unet, sample, t, context), nhwc(ref))


def test_unet_linear_projection_matches_diffusers(tmp_path):
    """SD 2.x's use_linear_projection: proj_in / proj_out are linear layers."""
    from diffusers import UNet2DConditionModel
    torch.manual_seed(4)
    ref_model = perturb(UNet2DConditionModel(**{**TINY_UNET, "block_out_channels": (16, 16)},
                                             use_linear_projection=True), 5)
    ref_model.save_pretrained(tmp_path / "unet")
    unet = load_module(tmp_path / "unet", UNet2DCondition.from_config)
    assert type(unet.down_blocks[0].attentions[0].proj_in).__name__ == "Linear"
    rng = np.random.default_rng(1)
    sample = rng.standard_normal((1, 8, 8, 8)).astype(np.float32)
    context = rng.standard_normal((1, 5, 24)).astype(np.float32)
    with torch.no_grad():
        ref = ref_model(nchw(sample), 250, torch.from_numpy(context)).sample
    assert_close(jax.jit(lambda m, x, c: m(x, 250, c))(unet, sample, context), nhwc(ref))


def test_unet_norm_eps_reaches_only_what_diffusers_gives_it(tmp_path):
    """norm_eps = 1e-2 (far from every default): diffusers passes it to the resnets and
    conv_norm_out, never to the transformer blocks' LayerNorms (they keep 1e-5) nor to
    Transformer2DModel's GroupNorm (1e-6). Passing it there too was off by ~1e-2 relative."""
    from diffusers import UNet2DConditionModel

    from jaxedit.models.layers import LayerNorm
    torch.manual_seed(6)
    ref_model = perturb(UNet2DConditionModel(**{**TINY_UNET, "block_out_channels": (16, 16)},
                                             norm_eps=1e-2), 7)
    ref_model.save_pretrained(tmp_path / "unet")
    unet = load_module(tmp_path / "unet", UNet2DCondition.from_config)
    block = unet.down_blocks[0].attentions[0]
    is_ln = lambda x: isinstance(x, LayerNorm)  # noqa: E731
    assert {n.eps for n in jax.tree_util.tree_leaves(unet, is_leaf=is_ln) if is_ln(n)} == {1e-5}
    assert block.norm.eps == 1e-6 and unet.conv_norm_out.eps == 1e-2
    assert unet.down_blocks[0].resnets[0].norm1.eps == 1e-2
    rng = np.random.default_rng(5)
    sample = rng.standard_normal((1, 8, 8, 8)).astype(np.float32)
    context = rng.standard_normal((1, 5, 24)).astype(np.float32)
    with torch.no_grad():
        ref = ref_model(nchw(sample), 420, torch.from_numpy(context)).sample
    assert_close(jax.jit(lambda m, x, c: m(x, 420, c))(unet, sample, context), nhwc(ref))


def test_vae_matches_diffusers(tiny, models):
    from diffusers import AutoencoderKL as TorchVAE
    ref_model = TorchVAE.from_pretrained(tiny / "vae").eval()
    rng = np.random.default_rng(2)
    image = rng.uniform(-1, 1, (2, 32, 24, 3)).astype(np.float32)
    latent = rng.standard_normal((2, 4, 3, 4)).astype(np.float32)
    with torch.no_grad():
        posterior = ref_model.encode(nchw(image)).latent_dist
        decoded = ref_model.decode(nchw(latent)).sample
    mean, logvar = eqx.filter_jit(lambda m, x: m.encode(x))(models.vae, image)
    assert mean.shape == (2, 8, 6, 4)
    assert_close(mean, nhwc(posterior.mean))
    assert_close(logvar, nhwc(posterior.logvar))
    assert_close(eqx.filter_jit(lambda m, z: m.decode(z))(models.vae, latent), nhwc(decoded))
    assert models.vae.scaling_factor == ref_model.config.scaling_factor


def test_text_encoder_and_tokenizer_match_transformers(tiny, models):
    from transformers import CLIPTextModel
    from transformers import CLIPTokenizer as TorchTokenizer
    ref_tok = TorchTokenizer.from_pretrained(tiny / "tokenizer")
    ref_ids = ref_tok(PROMPTS, padding="max_length", max_length=77, truncation=True,
                      return_tensors="np").input_ids
    ids = models.tokenizer.ids(PROMPTS)
    assert ids.dtype == np.int32 and ids.shape == (len(PROMPTS), 77)
    np.testing.assert_array_equal(ids, ref_ids)
    ref_model = CLIPTextModel.from_pretrained(tiny / "text_encoder").eval()
    with torch.no_grad():
        ref = ref_model(torch.from_numpy(ref_ids).long()).last_hidden_state.numpy()
    assert_close(jax.jit(lambda m, i: m(i))(models.text_encoder, ids), ref)


def test_tokenizer_from_vocab_and_merges_matches_transformers(tmp_path):
    """Without tokenizer.json the BPE is built from vocab.json + merges.txt; a pad token
    other than eos (as SD 2.x's "!") comes from special_tokens_map.json."""
    from transformers import CLIPTokenizer as TorchTokenizer
    folder = write_tokenizer_files(tmp_path / "tok")
    ref = TorchTokenizer(vocab=str(folder / "vocab.json"), merges=str(folder / "merges.txt"))
    want = ref(PROMPTS, padding="max_length", max_length=77, truncation=True).input_ids
    np.testing.assert_array_equal(CLIPTokenizer.from_folder(folder).ids(PROMPTS), want)
    # Unknown characters: a single-letter vocabulary without the byte symbols maps them to unk.
    (folder / "special_tokens_map.json").write_text(json.dumps({"pad_token": "!"}))
    ref = TorchTokenizer(vocab=str(folder / "vocab.json"), merges=str(folder / "merges.txt"),
                         pad_token="!")
    want = ref(PROMPTS, padding="max_length", max_length=77, truncation=True).input_ids
    np.testing.assert_array_equal(CLIPTokenizer.from_folder(folder).ids(PROMPTS), want)
    assert want[0][-1] == ref.convert_tokens_to_ids("!")


def test_tokenizer_unknown_symbols(tmp_path):
    """A vocabulary lacking most byte symbols: what is not in it becomes the unk token."""
    from transformers import CLIPTokenizer as TorchTokenizer
    folder = tmp_path / "tok"
    folder.mkdir()
    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for c in "abcdefghijklmnopqrstuvwxyz":
        vocab[c], vocab[c + "</w>"] = len(vocab), len(vocab) + 1
    vocab["th"], vocab["the</w>"] = len(vocab), len(vocab) + 1
    (folder / "vocab.json").write_text(json.dumps(vocab))
    (folder / "merges.txt").write_text("#version: 0.2\nt h\nth e</w>\n")
    ref = TorchTokenizer(vocab=str(folder / "vocab.json"), merges=str(folder / "merges.txt"))
    want = ref(PROMPTS, padding="max_length", max_length=77, truncation=True).input_ids
    np.testing.assert_array_equal(CLIPTokenizer.from_folder(folder).ids(PROMPTS), want)


def test_schedule_matches_diffusers(models, tiny):
    from diffusers import DDIMScheduler
    ref = DDIMScheduler.from_pretrained(tiny / "scheduler")
    s = models.scheduler
    assert (s.num_train_timesteps, s.beta_schedule, s.prediction_type) == (1000, "scaled_linear", "epsilon")
    np.testing.assert_allclose(s.alphas_cumprod, ref.alphas_cumprod.numpy(), rtol=2e-6)


def test_cast_bf16_runs_and_tracks_fp32(tiny, models, unet_fn):
    """bf16 weights compute in bf16 (norm statistics and softmax in fp32): same answer to bf16
    accuracy. Loading in bf16 gives the cast networks."""
    half = cast(models, jnp.bfloat16)
    assert half.unet.conv_in.weight.dtype == jnp.bfloat16
    assert half.tokenizer is models.tokenizer
    loaded = load_ip2p(tiny, dtype=jnp.bfloat16)
    assert jax.tree_util.tree_structure(loaded) == jax.tree_util.tree_structure(half)
    for a, b in zip(jax.tree_util.tree_leaves(loaded), jax.tree_util.tree_leaves(half)):
        assert a.dtype == b.dtype == jnp.bfloat16
        np.testing.assert_array_equal(np.asarray(a, np.float32), np.asarray(b, np.float32))
    rng = np.random.default_rng(3)
    sample = rng.standard_normal((2, 8, 8, 8)).astype(np.float32)
    context = rng.standard_normal((2, 7, 24)).astype(np.float32)
    t = np.array([300, 700], np.int32)
    full = np.asarray(unet_fn(models.unet, sample, t, context))
    low = unet_fn(half.unet, sample, t, context)
    assert low.dtype == jnp.bfloat16
    err = np.abs(np.asarray(low, np.float32) - full).max()
    assert err < 0.05 * np.abs(full).max()


def test_query_chunks_change_only_memory(models):
    """Attention over query chunks (with a remainder) equals attention over all queries, and
    set_query_chunk reaches every attention of the networks."""
    rng = np.random.default_rng(4)
    q, k, v = (rng.standard_normal((2, n, 3, 8)).astype(np.float32) for n in (23, 11, 11))
    attend = jax.jit(attention, static_argnames="query_chunk")
    np.testing.assert_allclose(attend(q, k, v, query_chunk=5), attend(q, k, v), rtol=1e-6, atol=1e-6)
    chunked = set_query_chunk(models, 64)
    is_attention = lambda x: isinstance(x, Attention)  # noqa: E731
    found = [a.query_chunk for a in jax.tree_util.tree_leaves(chunked, is_leaf=is_attention)
             if is_attention(a)]
    # UNet: (self, cross) x (2 down + 1 mid + 3 up transformers); VAE: one per mid block.
    assert len(found) == 2 * (2 + 1 + 3) + 2 and set(found) == {64}


def test_models_jit_as_arguments(models):
    """The whole IP2PModels pytree (static tokenizer and schedule) goes through jax.jit."""
    ids = models.tokenizer.ids(["a cat"])
    f = jax.jit(lambda m, i: m.text_encoder(i))
    np.testing.assert_allclose(f(models, ids), models.text_encoder(ids), rtol=1e-5, atol=1e-5)


# ----------------------------------------------------------------------------- loader errors

def _copy_component(tiny: Path, tmp_path: Path, sub: str) -> tuple[Path, Path]:
    folder = tmp_path / sub
    shutil.copytree(tiny / sub, folder)
    return folder, next(folder.glob("*.safetensors"))


def _edit_weights(path: Path, change) -> None:
    tensors = load_file(str(path))
    change(tensors)
    save_file(tensors, str(path))


def test_missing_tensor_is_named(tiny, tmp_path):
    folder, path = _copy_component(tiny, tmp_path, "unet")
    _edit_weights(path, lambda t: t.pop("down_blocks.0.attentions.1.proj_in.weight"))
    with pytest.raises(DataError,
                       match=r"missing tensor 'down_blocks\.0\.attentions\.1\.proj_in\.weight'") as e:
        load_module(folder, UNet2DCondition.from_config)
    assert e.value.where == str(path) and "\n" not in str(e.value)


def test_unexpected_tensors_are_named_and_counted(tiny, tmp_path):
    folder, path = _copy_component(tiny, tmp_path, "vae")

    def add(t):
        for i in range(5):
            t[f"decoder.extra.{i}.weight"] = np.zeros(3, np.float32)
    _edit_weights(path, add)
    with pytest.raises(DataError, match=r"unexpected tensors 'decoder\.extra\.0\.weight', .* and 2 more"):
        load_module(folder, AutoencoderKL.from_config)


def test_wrong_shape_is_named(tiny, tmp_path):
    folder, path = _copy_component(tiny, tmp_path, "text_encoder")
    # Names carry "text_model." in SD's checkpoints, not in what transformers 5 saves.
    name = next(k for k in load_file(str(path)) if k.endswith("encoder.layers.1.mlp.fc1.weight"))
    _edit_weights(path, lambda t: t.__setitem__(name, t[name][:-1]))
    with pytest.raises(DataError, match=f"'{name}' has shape "
                                        r"\[36, 24\], expected \[37, 24\]"):
        load_module(folder, CLIPTextEncoder.from_config, prefix="text_model.")


LEGACY_NAMES = (("to_q", "query"), ("to_k", "key"), ("to_v", "value"), ("to_out.0", "proj_attn"))


def test_loading_builds_no_program_per_weight_shape(tiny):
    """Weights go to the device by transfer: jnp.asarray of a NumPy array would build a copy
    program per shape (52 here; hundreds in SD 1.5), and a cast a conversion per shape.
    float16, which no other test loads in: every weight shape is new to this process."""
    from jaxedit.compilation import compile_stats

    before = compile_stats()
    loaded = load_ip2p(tiny, dtype=jnp.float16)
    built = compile_stats(since=before)
    shapes = {(leaf.shape, leaf.dtype) for leaf in jax.tree_util.tree_leaves(loaded)}
    assert len(shapes) > 40
    assert built["count"] + built["cache_hits"] <= 3, built["programs"]  # the build key's


def test_legacy_vae_attention_names_load(tiny, tmp_path, models):
    """VAE checkpoints from before diffusers 0.14 name the mid-block attention query/key/value/
    proj_attn, some with 1x1-conv shaped weights; they load to the same module."""
    folder, path = _copy_component(tiny, tmp_path, "vae")

    def rename(t):
        for name in [k for k in t if ".attentions.0." in k]:
            for new, old in LEGACY_NAMES:
                if f".{new}." in name:
                    value = t.pop(name)
                    as_conv = value[..., None, None] if value.ndim == 2 else value
                    t[name.replace(f".{new}.", f".{old}.")] = as_conv
    _edit_weights(path, rename)
    vae = load_module(folder, AutoencoderKL.from_config)
    for a, b in zip(jax.tree_util.tree_leaves(vae), jax.tree_util.tree_leaves(models.vae)):
        np.testing.assert_array_equal(a, b)


def test_torch_bin_checkpoint_loads_without_running_code(tiny, tmp_path, models):
    """A legacy pytorch_model.bin loads to the same module; a pickle calling anything but
    tensor rebuilding is refused, naming what it tried."""
    folder, path = _copy_component(tiny, tmp_path, "text_encoder")
    torch.save({k: torch.from_numpy(v) for k, v in load_file(str(path)).items()},
               folder / "pytorch_model.bin")
    path.unlink()
    enc = load_module(folder, CLIPTextEncoder.from_config, prefix="text_model.")
    for a, b in zip(jax.tree_util.tree_leaves(enc), jax.tree_util.tree_leaves(models.text_encoder)):
        np.testing.assert_array_equal(a, b)
    torch.save({"weight": torch.zeros(2), "payload": Exploit()}, folder / "pytorch_model.bin")
    with pytest.raises(DataError, match=r"pytorch_model\.bin: refused to unpickle global "
                                        r"(__builtin__|builtins)\.print"):
        load_module(folder, CLIPTextEncoder.from_config, prefix="text_model.")
    (folder / "pytorch_model.bin").unlink()
    with pytest.raises(DataError, match="no weights file"):
        load_module(folder, CLIPTextEncoder.from_config, prefix="text_model.")


@pytest.mark.parametrize("batch, h, w, c_in, c_out, kernel, stride, padding", [
    (3, 2, 2, 16, 8, 3, 1, 1),    # SD's lowest UNet level at 128 px
    (2, 4, 3, 8, 8, 3, 2, 1),     # a downsampling conv, odd width
    (1, 3, 3, 8, 4, 1, 1, 0),     # a 1x1 projection
    (2, 5, 3, 4, 4, 3, 2, 0),     # no padding
])
def test_small_maps_convolve_as_a_patch_matmul(batch, h, w, c_in, c_out, kernel, stride, padding):
    """Maps of at most SMALL_CONV_POSITIONS positions take the patch-matmul path (XLA:CPU's
    convolution is 18x slower than torch's there); it is the same convolution."""
    from jaxedit.models.layers import SMALL_CONV_POSITIONS, Conv2d

    assert h * w <= SMALL_CONV_POSITIONS
    conv = Conv2d.init(jax.random.key(0), c_in, c_out, kernel, stride=stride, padding=padding)
    x = jax.random.normal(jax.random.key(1), (batch, h, w, c_in))
    want = jax.lax.conv_general_dilated(x, conv.weight, (stride, stride),
                                        ((padding, padding), (padding, padding)),
                                        dimension_numbers=("NHWC", "HWIO", "NHWC")) + conv.bias
    np.testing.assert_allclose(conv(x), want, rtol=1e-5, atol=1e-5)


def test_torch_checkpoint_reader_rebuilds_views_and_dtypes(tmp_path):
    """Transposed and offset views of a shared storage, fp16, bf16 (widened to fp32), ints,
    empty tensors: each as torch holds it."""
    from jaxedit.io.weights import load_torch_checkpoint
    a = torch.randn(3, 4)
    state = {"a": a, "t": torch.randn(4, 3).t(), "view": a[1:, 1:], "h": torch.randn(5).half(),
             "bf": torch.randn(2).bfloat16(), "i": torch.arange(3), "empty": torch.zeros(0, 3)}
    torch.save(state, tmp_path / "x.bin")
    got = load_torch_checkpoint(tmp_path / "x.bin")
    assert sorted(got) == sorted(state)
    for name, t in state.items():
        want = t.float().numpy() if t.dtype == torch.bfloat16 else t.numpy()
        assert got[name].dtype == want.dtype, name
        np.testing.assert_array_equal(got[name], want)


def test_safetensors_reader_matches_the_safetensors_package(tmp_path):
    """The one safetensors reader (memory-mapped) against the files safetensors.torch writes:
    fp32, fp16, bf16 (widened, as NumPy lacks it), ints, empty and 0-d tensors, metadata;
    a truncated file is a one-line DataError naming it."""
    from safetensors.torch import save_file as torch_save_file

    from jaxedit.io.weights import read_safetensors
    state = {"f": torch.randn(3, 4), "h": torch.randn(5).half(), "bf": torch.randn(2, 2).bfloat16(),
             "i": torch.arange(3), "u": torch.arange(4, dtype=torch.uint8),
             "empty": torch.zeros(0, 3), "scalar": torch.tensor(2.5)}
    path = tmp_path / "w.safetensors"
    torch_save_file(state, str(path), metadata={"format": "pt"})
    got, meta = read_safetensors(path)
    assert meta == {"format": "pt"} and sorted(got) == sorted(state)
    for name, t in state.items():
        want = t.float().numpy() if t.dtype == torch.bfloat16 else t.numpy()
        assert got[name].dtype == want.dtype and got[name].shape == want.shape, name
        np.testing.assert_array_equal(got[name], want)
    path.write_bytes(path.read_bytes()[:-3])
    with pytest.raises(DataError, match=r"w\.safetensors: tensor '\w+' lies outside the file"):
        read_safetensors(path)


class Exploit:
    """Unpickling this would call print: stands for any code a pickle can run."""

    def __reduce__(self):
        return (print, ("a pickle ran code",))


def test_fp16_variant_loads(tiny, tmp_path, models):
    folder, path = _copy_component(tiny, tmp_path, "text_encoder")
    tensors = {k: v.astype(np.float16) for k, v in load_file(str(path)).items()}
    path.unlink()
    save_file(tensors, str(folder / "model.fp16.safetensors"))
    enc = load_module(folder, CLIPTextEncoder.from_config, prefix="text_model.")
    w = enc.encoder.layers[0].mlp.fc1.weight
    assert w.dtype == jnp.float32
    np.testing.assert_array_equal(w, np.asarray(models.text_encoder.encoder.layers[0].mlp.fc1.weight)
                                  .astype(np.float16).astype(np.float32))


def test_incomplete_folder_names_what_is_missing(tiny, tmp_path):
    shutil.copytree(tiny, tmp_path / "p")
    shutil.rmtree(tmp_path / "p" / "scheduler")
    with pytest.raises(DataError, match=r"missing scheduler/scheduler_config\.json"):
        load_ip2p(tmp_path / "p")


# ----------------------------------------------------------------------------- no torch

def test_models_import_and_load_without_torch(tiny):
    """jaxedit.models needs none of torch / diffusers / transformers: a child process where
    importing them fails loads the tiny folder and runs the text encoder."""
    out = run_without_torch(f"""
        import jaxedit.models as m
        models = m.load_ip2p({str(tiny)!r})
        ids = models.tokenizer.ids(["turn him into a clown"])
        print(ids.shape, models.text_encoder(ids).shape)
    """, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "(1, 77) (1, 77, 24)" in out.stdout
