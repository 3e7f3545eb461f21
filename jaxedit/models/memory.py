"""Memory of the networks without holding them: parameter bytes of abstract modules and
XLA's compiled memory analysis; timbrooks/instruct-pix2pix's configurations."""

from __future__ import annotations

from typing import Any, Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["SD15_UNET_IP2P", "SD15_VAE", "CLIP_L14_TEXT", "abstract", "abstract_ip2p",
           "param_count", "param_bytes", "compiled_memory", "is_array_like"]

# Stable Diffusion 1.5 as timbrooks/instruct-pix2pix ships it (unet/vae/text_encoder config.json).
SD15_UNET_IP2P = dict(
    sample_size=64, in_channels=8, out_channels=4, layers_per_block=2,
    block_out_channels=(320, 640, 1280, 1280),
    down_block_types=("CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D",
                      "DownBlock2D"),
    up_block_types=("UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"),
    cross_attention_dim=768, attention_head_dim=8, norm_num_groups=32, flip_sin_to_cos=True,
    freq_shift=0)
SD15_VAE = dict(
    in_channels=3, out_channels=3, latent_channels=4, block_out_channels=(128, 256, 512, 512),
    layers_per_block=2, down_block_types=("DownEncoderBlock2D",) * 4,
    up_block_types=("UpDecoderBlock2D",) * 4, norm_num_groups=32, sample_size=512,
    scaling_factor=0.18215)
CLIP_L14_TEXT = dict(
    vocab_size=49408, hidden_size=768, intermediate_size=3072, num_hidden_layers=12,
    num_attention_heads=12, max_position_embeddings=77, hidden_act="quick_gelu",
    bos_token_id=49406, eos_token_id=49407, pad_token_id=1, projection_dim=768)


def is_array_like(x) -> bool:
    """A JAX or NumPy array, or an abstract one (``jax.ShapeDtypeStruct``)."""
    return isinstance(x, (jax.Array, np.ndarray, jax.ShapeDtypeStruct))


def abstract(build: Callable[..., Any], config: dict, dtype=jnp.float32):
    """``build(config, key=..., dtype=dtype)`` with ``jax.ShapeDtypeStruct`` leaves."""
    return eqx.filter_eval_shape(build, config, key=jax.random.key(0), dtype=dtype)


def abstract_ip2p(dtype=jnp.bfloat16, *, unet: dict = SD15_UNET_IP2P, vae: dict = SD15_VAE,
                  text: dict = CLIP_L14_TEXT) -> dict:
    """{"unet", "vae", "text_encoder"}: the three networks, abstract, in ``dtype``."""
    from .clip_text import CLIPTextEncoder
    from .unet import UNet2DCondition
    from .vae import AutoencoderKL

    return {"unet": abstract(UNet2DCondition.from_config, unet, dtype),
            "vae": abstract(AutoencoderKL.from_config, vae, dtype),
            "text_encoder": abstract(CLIPTextEncoder.from_config, text, dtype)}


def _leaves(tree) -> list:
    return [x for x in jax.tree_util.tree_leaves(tree) if is_array_like(x)]


def param_count(tree) -> int:
    """Number of values in the arrays (concrete or abstract) of ``tree``."""
    return int(sum(int(np.prod(x.shape)) for x in _leaves(tree)))


def param_bytes(tree, dtype=None) -> int:
    """Bytes of the arrays of ``tree``: each in its own dtype, or, with ``dtype``, its floating
    arrays in ``dtype`` (integer arrays keep theirs)."""
    total = 0
    for x in _leaves(tree):
        d = jnp.dtype(x.dtype)
        if dtype is not None and jnp.issubdtype(d, jnp.floating):
            d = jnp.dtype(dtype)
        total += int(np.prod(x.shape)) * d.itemsize
    return int(total)


def compiled_memory(fn: Callable, *args, donate: Sequence[int] = ()) -> dict:
    """XLA's memory analysis of ``fn(*args)`` (leaves may be abstract; ``donate``: donated
    positions): bytes ``argument``, ``output``, ``alias`` (in donated buffers), ``temp``,
    ``peak`` = argument + output - alias + temp, and ``compile_s``."""
    import time

    dynamic, static = eqx.partition(args, is_array_like)

    def run(*dyn):
        return fn(*eqx.combine(dyn, static))

    def spec(x):
        return x if isinstance(x, jax.ShapeDtypeStruct) else jax.ShapeDtypeStruct(x.shape, x.dtype)

    shapes = jax.tree_util.tree_map(spec, dynamic, is_leaf=is_array_like)
    t0 = time.perf_counter()
    compiled = jax.jit(run, donate_argnums=tuple(donate)).lower(*shapes).compile()
    seconds = time.perf_counter() - t0
    m = compiled.memory_analysis()
    out = {"argument": int(m.argument_size_in_bytes), "output": int(m.output_size_in_bytes),
           "alias": int(m.alias_size_in_bytes), "temp": int(m.temp_size_in_bytes)}
    out["peak"] = out["argument"] + out["output"] - out["alias"] + out["temp"]
    out["compile_s"] = round(seconds, 1)
    return out
