"""The memory measures of the JAX InstructPix2Pix editor and the estimate behind
benchmarks/memory.py, on tiny configurations (fast).

- The estimate's parameter bytes (abstract modules, no weights) are the real modules'.
- The VAE in chunks of views (encode and decode) gives the whole batch's result.
- A released text encoder ("host", "reload") gives the kept one's embeddings, for the null
  prompt encoded at construction and for a new prompt encoded afterwards.
- An edit whose images buffer is donated gives the same result as one that is not.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from ip2p_standins import sd_schedule, standin_networks, tokenize

from jaxedit.editors import jax_ip2p as jx
from jaxedit.errors import DataError
from jaxedit.models import AutoencoderKL, CLIPTextEncoder, UNet2DCondition, set_query_chunk
from jaxedit.models.memory import (abstract, abstract_ip2p, compiled_memory, param_bytes,
                                   param_count)

TINY_UNET = dict(in_channels=8, out_channels=4, layers_per_block=1, block_out_channels=(16, 32),
                 down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
                 up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"), cross_attention_dim=32,
                 attention_head_dim=4, norm_num_groups=8)
TINY_VAE = dict(in_channels=3, out_channels=3, latent_channels=4, block_out_channels=(8, 8, 16),
                layers_per_block=1, norm_num_groups=4)
TINY_TEXT = dict(vocab_size=60, hidden_size=32, intermediate_size=37, num_hidden_layers=2,
                 num_attention_heads=4, max_position_embeddings=77)
BUILD = {"unet": (UNet2DCondition.from_config, TINY_UNET),
         "vae": (AutoencoderKL.from_config, TINY_VAE),
         "text_encoder": (CLIPTextEncoder.from_config, TINY_TEXT)}


@pytest.fixture(scope="module")
def vae():
    return AutoencoderKL.from_config(TINY_VAE, key=jax.random.key(0))


def test_estimated_parameter_bytes_are_the_real_ones():
    nets = abstract_ip2p(jnp.bfloat16, unet=TINY_UNET, vae=TINY_VAE, text=TINY_TEXT)
    for name, (build, config) in BUILD.items():
        real = build(config, key=jax.random.key(0))  # concrete float32 weights
        leaves = [x for x in jax.tree_util.tree_leaves(real) if isinstance(x, jax.Array)]
        count = sum(x.size for x in leaves)
        assert param_count(nets[name]) == param_count(real) == count > 0, name
        assert param_bytes(real) == sum(x.nbytes for x in leaves) == 4 * count
        assert param_bytes(nets[name]) == 2 * count  # built in bfloat16
        assert param_bytes(nets[name], jnp.float32) == 4 * count
        assert param_bytes(abstract(build, config, jnp.float16)) == 2 * count


def test_compiled_memory_counts_the_arguments(vae):
    z = jax.ShapeDtypeStruct((2, 4, 4, 4), jnp.float32)
    m = compiled_memory(lambda v, z: v.decode(z), vae, z)
    # XLA drops the arguments a program does not read: the decode has no encoder weights.
    assert m["argument"] == param_bytes((vae.decoder, vae.post_quant_conv)) + 2 * 4 * 4 * 4 * 4
    assert m["output"] == 2 * 16 * 16 * 3 * 4
    assert m["temp"] > 0 and m["alias"] == 0
    assert m["peak"] == m["argument"] + m["output"] + m["temp"]
    # A donated argument of the output's shape holds the output.
    x = jax.ShapeDtypeStruct((64, 64), jnp.float32)
    donated = compiled_memory(lambda a: a * 2, x, donate=(0,))
    assert donated["alias"] == donated["output"] == 64 * 64 * 4


@pytest.mark.parametrize("chunk", [1, 2])
def test_chunked_vae_decode_is_the_whole_decode(vae, chunk):
    """3 views in chunks of 1 and of 2 (the last chunk padded) == all at once."""
    z = jax.random.normal(jax.random.key(1), (3, 4, 4, 4)) * 5
    whole = jax.jit(lambda v, z: jx.decode(v, z, jx.SamplerConfig(vae_chunk=None)))(vae, z)
    chunked = jax.jit(lambda v, z: jx.decode(v, z, jx.SamplerConfig(vae_chunk=chunk)))(vae, z)
    assert chunked.shape == whole.shape == (3, 16, 16, 3)
    np.testing.assert_allclose(np.asarray(chunked), np.asarray(whole), rtol=0, atol=1e-5)
    assert np.abs(np.asarray(whole[0]) - np.asarray(whole[1])).max() > 1e-3


@pytest.mark.parametrize("chunk", [1, 2])
def test_chunked_vae_encode_is_the_whole_encode(vae, chunk):
    rng = np.random.default_rng(0)
    images, originals = (jnp.asarray(rng.uniform(0, 1, (3, 16, 16, 3)), jnp.float32)
                         for _ in range(2))
    noise = jax.random.normal(jax.random.key(2), (3, 4, 4, 4))

    def run(c):
        cfg = jx.SamplerConfig(vae_chunk=c)
        return jax.jit(lambda v, *a: jx.encode_latents(v, *a, cfg))(vae, images, originals, noise)

    for got, want in zip(run(chunk), run(None)):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=0, atol=1e-5)


def test_in_chunks_keeps_order_and_pads():
    x = jnp.arange(7.0)[:, None]
    out = jx.in_chunks(lambda v: (v * 2, v + 1), x, 3)
    np.testing.assert_array_equal(np.asarray(out[0]), np.asarray(x * 2))
    np.testing.assert_array_equal(np.asarray(out[1]), np.asarray(x + 1))


def _editor(residency, **kw):
    unet, vae, text = standin_networks(0)
    load = (lambda: standin_networks(0)[2]) if residency != "device" else None
    return jx.JaxIP2PEditor(unet, vae, text, tokenize, sd_schedule(), size=32, steps=2,
                            text_encoder_residency=residency, load_text_encoder=load, **kw)


def test_released_text_encoder_encodes_the_same():
    kept = _editor("device")
    assert kept.text_encoder_residency == "device" and kept._text_encoder is not None
    for residency in ("host", "reload"):
        ed = _editor(residency)
        assert ed._text_encoder is None, residency  # released after the null prompt
        assert ed.text_encoder_residency == residency
        np.testing.assert_array_equal(ed.encode(""), kept.encode(""))
        np.testing.assert_array_equal(ed.encode("make it snow"), kept.encode("make it snow"))
        assert ed._text_encoder is None  # a new prompt's encoder was not kept
        assert ed.describe()["text_encoder_residency"] == residency
    # "auto" on the CPU: reload when the editor can, else keep it.
    assert _editor("auto").text_encoder_residency == "reload"
    unet, vae, text = standin_networks(0)
    assert jx.JaxIP2PEditor(unet, vae, text, tokenize, sd_schedule()).text_encoder_residency \
        == "device"
    with pytest.raises(DataError, match="load_text_encoder"):
        jx.JaxIP2PEditor(unet, vae, text, tokenize, sd_schedule(),
                         text_encoder_residency="reload")
    with pytest.raises(DataError, match="vae_chunk"):
        _editor("device", vae_chunk=0)


def test_donated_images_give_the_same_edit():
    """NumPy images (an own copy, donated) and the caller's device array (not donated) give
    the same edit; the caller's array is left intact."""
    ed = _editor("device")
    rng = np.random.default_rng(3)
    images = rng.uniform(0, 1, (2, 24, 20, 3)).astype(np.float32)
    emb = ed.encode("make it snow")
    keys = jax.random.split(jax.random.key(0), 2)
    from_host = ed.edit_many(images, images, emb, keys)
    on_device = jnp.asarray(images)
    from_device = ed.edit_many(on_device, on_device, emb, keys)
    np.testing.assert_array_equal(np.asarray(from_host), np.asarray(from_device))
    np.testing.assert_array_equal(np.asarray(on_device), images)  # not donated


def test_attention_chunk_reaches_the_networks():
    unet = UNet2DCondition.from_config(TINY_UNET, key=jax.random.key(0))
    vae = AutoencoderKL.from_config(TINY_VAE, key=jax.random.key(0))
    text = CLIPTextEncoder.from_config(TINY_TEXT, key=jax.random.key(0))
    ed = jx.JaxIP2PEditor(unet, vae, text, tokenize, sd_schedule(), size=32, steps=1,
                          attention_chunk=8)
    from jaxedit.models.layers import Attention
    is_attention = lambda x: isinstance(x, Attention)  # noqa: E731
    chunks = {a.query_chunk for a in jax.tree_util.tree_leaves(ed.nets, is_leaf=is_attention)
              if is_attention(a)}
    assert chunks == {8}
    assert set_query_chunk(ed.nets, None) is not ed.nets
    assert dataclasses.asdict(ed.config())["vae_chunk"] == jx.VAE_CHUNK
