"""Stable Diffusion 1.x's conditional UNet (diffusers' ``UNet2DConditionModel``), NHWC;
SD 1.x's ``attention_head_dim`` is the number of heads, as diffusers reads it."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..errors import DataError
from .layers import (Conv2d, Downsample2D, GroupNorm, ResnetBlock2D, TimestepEmbedding,
                     Transformer2DModel, Upsample2D, timestep_embedding)

Array = jax.Array

__all__ = ["UNet2DCondition"]

_DOWN = ("CrossAttnDownBlock2D", "DownBlock2D")
_UP = ("CrossAttnUpBlock2D", "UpBlock2D")


class DownBlock(eqx.Module):
    """CrossAttnDownBlock2D (with ``attentions``) or DownBlock2D (``attentions == ()``)."""

    resnets: tuple[ResnetBlock2D, ...]
    attentions: tuple[Transformer2DModel, ...]
    downsamplers: tuple[Downsample2D, ...]

    def __call__(self, x: Array, temb: Array, context: Array) -> tuple[Array, list[Array]]:
        """-> (output, the skips: one per resnet, plus the downsampled output)"""
        skips = []
        for i, resnet in enumerate(self.resnets):
            x = resnet(x, temb)
            if self.attentions:
                x = self.attentions[i](x, context)
            skips.append(x)
        for d in self.downsamplers:
            x = d(x)
            skips.append(x)
        return x, skips


class UpBlock(eqx.Module):
    """CrossAttnUpBlock2D (with ``attentions``) or UpBlock2D (``attentions == ()``)."""

    resnets: tuple[ResnetBlock2D, ...]
    attentions: tuple[Transformer2DModel, ...]
    upsamplers: tuple[Upsample2D, ...]

    def __call__(self, x: Array, skips: list[Array], temb: Array, context: Array,
                 size: tuple[int, int] | None) -> Array:
        """``skips``: this block's, last-used first; ``size``: the upsampled size."""
        for i, resnet in enumerate(self.resnets):
            x = resnet(jnp.concatenate([x, skips[i].astype(x.dtype)], axis=-1), temb)
            if self.attentions:
                x = self.attentions[i](x, context)
        for u in self.upsamplers:
            x = u(x, size)
        return x


class MidBlock(eqx.Module):
    """UNetMidBlock2DCrossAttn: resnet, then (transformer, resnet) per layer."""

    resnets: tuple[ResnetBlock2D, ...]
    attentions: tuple[Transformer2DModel, ...]

    def __call__(self, x: Array, temb: Array, context: Array) -> Array:
        x = self.resnets[0](x, temb)
        for attn, resnet in zip(self.attentions, self.resnets[1:]):
            x = resnet(attn(x, context), temb)
        return x


def _per_block(value, n: int, name: str) -> list:
    values = list(value) if isinstance(value, (list, tuple)) else [value] * n
    if len(values) != n:
        raise DataError("unet/config.json", f"{name} has {len(values)} entries for {n} blocks")
    return values


class UNet2DCondition(eqx.Module):
    """eps(sample, timestep, text) of diffusers' UNet2DConditionModel (SD 1.x / 2.x / IP2P)."""

    conv_in: Conv2d
    time_embedding: TimestepEmbedding
    down_blocks: tuple[DownBlock, ...]
    mid_block: MidBlock
    up_blocks: tuple[UpBlock, ...]
    conv_norm_out: GroupNorm
    conv_out: Conv2d
    flip_sin_to_cos: bool = eqx.field(static=True, default=True)
    freq_shift: float = eqx.field(static=True, default=0.0)

    @staticmethod
    def from_config(config: dict, *, key: jax.Array, dtype=jnp.float32) -> "UNet2DCondition":
        """Random weights in the architecture of a diffusers ``unet/config.json`` dict."""
        where = "unet/config.json"
        unsupported = {
            "class_embed_type": None, "addition_embed_type": None, "encoder_hid_dim": None,
            "time_cond_proj_dim": None, "timestep_post_act": None, "time_embedding_type": "positional",
            "resnet_time_scale_shift": "default", "mid_block_type": "UNetMidBlock2DCrossAttn",
            "only_cross_attention": False, "dual_cross_attention": False, "conv_in_kernel": 3,
            "conv_out_kernel": 3, "act_fn": "silu", "center_input_sample": False,
            "num_class_embeds": None, "cross_attention_norm": None, "attention_type": "default",
            "reverse_transformer_layers_per_block": None, "resnet_skip_time_act": False,
            "resnet_out_scale_factor": 1.0, "mid_block_only_cross_attention": None,
            "time_embedding_act_fn": None, "time_embedding_dim": None,
            "projection_class_embeddings_input_dim": None,
            "class_embeddings_concat": False,
        }
        for name, default in unsupported.items():
            value = config.get(name, default)
            if value != default and not (isinstance(value, (list, tuple)) and set(value) == {default}):
                raise DataError(where, f"{name}={value!r} is not supported (Stable Diffusion 1.x/2.x "
                                "UNets only)")
        channels = list(config.get("block_out_channels", (320, 640, 1280, 1280)))
        n = len(channels)
        down_types = list(config.get("down_block_types", _DOWN[:1] * 3 + _DOWN[1:]))
        up_types = list(config.get("up_block_types", _UP[1:] + _UP[:1] * 3))
        if len(down_types) != n or len(up_types) != n:
            raise DataError(where, "down_block_types, up_block_types and block_out_channels differ "
                            "in length")
        for t in down_types + up_types:
            if t not in _DOWN + _UP:
                raise DataError(where, f"unsupported block type {t!r} (supported: {_DOWN + _UP})")
        heads = _per_block(config.get("num_attention_heads") or config.get("attention_head_dim", 8),
                           n, "attention_head_dim")
        tlayers = _per_block(config.get("transformer_layers_per_block", 1), n,
                             "transformer_layers_per_block")
        layers = _per_block(config.get("layers_per_block", 2), n, "layers_per_block")
        context = config.get("cross_attention_dim", 1280)
        context = _per_block(context, n, "cross_attention_dim")
        groups, eps = int(config.get("norm_num_groups", 32)), float(config.get("norm_eps", 1e-5))
        linear = bool(config.get("use_linear_projection", False))
        c_in, c_out = int(config.get("in_channels", 4)), int(config.get("out_channels", 4))
        temb = 4 * channels[0]
        keys = iter(jax.random.split(key, 16 + 8 * n * (max(layers) + 3)))
        nk = lambda: next(keys)  # noqa: E731
        res = lambda a, b, scale=1.0: ResnetBlock2D.init(  # noqa: E731
            nk(), a, b, temb=temb, groups=groups, eps=eps, output_scale=scale, dtype=dtype)
        # norm_eps reaches the resnets and conv_norm_out only: diffusers' Transformer2DModel
        # keeps its default epsilons whatever the config says.
        xf = lambda c, i, nl: Transformer2DModel.init(  # noqa: E731
            nk(), c, heads[i], context[i], groups=groups, layers=nl, linear_projection=linear,
            dtype=dtype)
        pad = int(config.get("downsample_padding", 1))
        if pad != 1:
            raise DataError(where, f"downsample_padding={pad} is not supported (SD uses 1)")

        downs, c = [], channels[0]
        for i, (kind, c_block) in enumerate(zip(down_types, channels)):
            resnets = tuple(res(c if j == 0 else c_block, c_block) for j in range(layers[i]))
            attns = (tuple(xf(c_block, i, tlayers[i]) for _ in range(layers[i]))
                     if kind == "CrossAttnDownBlock2D" else ())
            dsamp = () if i == n - 1 else (Downsample2D.init(nk(), c_block, asymmetric=False, dtype=dtype),)
            downs.append(DownBlock(resnets, attns, dsamp))
            c = c_block

        mid_scale = float(config.get("mid_block_scale_factor", 1.0))
        c_mid = channels[-1]
        mid = MidBlock((res(c_mid, c_mid, mid_scale), res(c_mid, c_mid, mid_scale)),
                       (xf(channels[-1], n - 1, tlayers[-1]),))

        ups, rev = [], channels[::-1]
        rev_heads, rev_ctx, rev_layers, rev_tl = heads[::-1], context[::-1], layers[::-1], tlayers[::-1]
        out_c = rev[0]
        for i, kind in enumerate(up_types):
            prev_c, out_c = out_c, rev[i]
            in_c = rev[min(i + 1, n - 1)]
            nl = rev_layers[i] + 1
            resnets = tuple(res((prev_c if j == 0 else out_c) + (in_c if j == nl - 1 else out_c), out_c)
                            for j in range(nl))
            attns = (tuple(Transformer2DModel.init(nk(), out_c, rev_heads[i], rev_ctx[i], groups=groups,
                                                   layers=rev_tl[i], linear_projection=linear,
                                                   dtype=dtype) for _ in range(nl))
                     if kind == "CrossAttnUpBlock2D" else ())
            usamp = () if i == n - 1 else (Upsample2D.init(nk(), out_c, dtype),)
            ups.append(UpBlock(resnets, attns, usamp))

        return UNet2DCondition(
            Conv2d.init(nk(), c_in, channels[0], 3, padding=1, dtype=dtype),
            TimestepEmbedding.init(nk(), channels[0], temb, dtype), tuple(downs), mid, tuple(ups),
            GroupNorm.init(groups, channels[0], eps, dtype),
            Conv2d.init(nk(), channels[0], c_out, 3, padding=1, dtype=dtype),
            bool(config.get("flip_sin_to_cos", True)), float(config.get("freq_shift", 0)))

    def __call__(self, sample: Array, timestep: Array | float, context: Array) -> Array:
        """sample [B, H, W, Cin], timestep [B] or scalar, context [B, L, D] -> eps [B, H, W, Cout];
        H, W need not be multiples of 2^(levels-1)."""
        b = sample.shape[0]
        t = jnp.broadcast_to(jnp.asarray(timestep, jnp.float32).reshape(-1), (b,))
        t_emb = timestep_embedding(t, self.conv_in.weight.shape[-1],
                                   flip_sin_to_cos=self.flip_sin_to_cos, freq_shift=self.freq_shift)
        temb = self.time_embedding(t_emb.astype(self.conv_in.weight.dtype))
        context = context.astype(self.conv_in.weight.dtype)

        x = self.conv_in(sample)
        skips = [x]
        for block in self.down_blocks:
            x, block_skips = block(x, temb, context)
            skips.extend(block_skips)
        x = self.mid_block(x, temb, context)
        for block in self.up_blocks:
            n = len(block.resnets)
            mine, skips = skips[-n:][::-1], skips[:-n]
            size = tuple(skips[-1].shape[1:3]) if block.upsamplers else None
            x = block(x, mine, temb, context, size)
        return self.conv_out(jax.nn.silu(self.conv_norm_out(x)))
