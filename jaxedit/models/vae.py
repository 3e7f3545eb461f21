"""Stable Diffusion's VAE (diffusers' ``AutoencoderKL``), NHWC, pytree paths its tensor names."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..errors import DataError
from .layers import Attention, Conv2d, Downsample2D, GroupNorm, ResnetBlock2D, Upsample2D

Array = jax.Array

__all__ = ["AutoencoderKL"]

_EPS = 1e-6  # diffusers' VAE uses eps 1e-6 in every norm


class MidBlock2D(eqx.Module):
    """resnet, (attention, resnet) — diffusers' UNetMidBlock2D without a time embedding."""

    resnets: tuple[ResnetBlock2D, ...]
    attentions: tuple[Attention, ...]

    @staticmethod
    def init(key, channels: int, groups: int, attention: bool, dtype) -> "MidBlock2D":
        k0, k1, k2 = jax.random.split(key, 3)
        res = lambda k: ResnetBlock2D.init(k, channels, channels, temb=None, groups=groups,  # noqa: E731
                                           eps=_EPS, dtype=dtype)
        attn = (Attention.init(k1, channels, 1, channels, qkv_bias=True, norm_groups=groups,
                               norm_eps=_EPS, residual=True, dtype=dtype),) if attention else ()
        return MidBlock2D((res(k0), res(k2)), attn)

    def __call__(self, x: Array) -> Array:
        """[B, H, W, C] -> same"""
        x = self.resnets[0](x)
        for attn in self.attentions:  # zero or one
            b, h, w, c = x.shape
            x = attn(x.reshape(b, h * w, c)).reshape(b, h, w, c)
        return self.resnets[-1](x)


class EncoderBlock(eqx.Module):
    resnets: tuple[ResnetBlock2D, ...]
    downsamplers: tuple[Downsample2D, ...]  # () at the last level

    def __call__(self, x: Array) -> Array:
        for r in self.resnets:
            x = r(x)
        for d in self.downsamplers:
            x = d(x)
        return x


class DecoderBlock(eqx.Module):
    resnets: tuple[ResnetBlock2D, ...]
    upsamplers: tuple[Upsample2D, ...]  # () at the last level

    def __call__(self, x: Array) -> Array:
        for r in self.resnets:
            x = r(x)
        for u in self.upsamplers:
            x = u(x)
        return x


class Encoder(eqx.Module):
    conv_in: Conv2d
    down_blocks: tuple[EncoderBlock, ...]
    mid_block: MidBlock2D
    conv_norm_out: GroupNorm
    conv_out: Conv2d

    def __call__(self, x: Array) -> Array:
        x = self.conv_in(x)
        for block in self.down_blocks:
            x = block(x)
        x = self.mid_block(x)
        return self.conv_out(jax.nn.silu(self.conv_norm_out(x)))


class Decoder(eqx.Module):
    conv_in: Conv2d
    mid_block: MidBlock2D
    up_blocks: tuple[DecoderBlock, ...]
    conv_norm_out: GroupNorm
    conv_out: Conv2d

    def __call__(self, z: Array) -> Array:
        x = self.mid_block(self.conv_in(z))
        for block in self.up_blocks:
            x = block(x)
        return self.conv_out(jax.nn.silu(self.conv_norm_out(x)))


class AutoencoderKL(eqx.Module):
    """diffusers' AutoencoderKL: images in [-1, 1] <-> latents at 1/2^(levels-1) resolution."""

    encoder: Encoder
    decoder: Decoder
    quant_conv: Conv2d | None
    post_quant_conv: Conv2d | None
    #: latents are multiplied by this before diffusion (SD 1.x: 0.18215).
    scaling_factor: float = eqx.field(static=True, default=0.18215)

    @staticmethod
    def from_config(config: dict, *, key: jax.Array, dtype=jnp.float32) -> "AutoencoderKL":
        """Random weights in the architecture of a diffusers ``vae/config.json`` dict."""
        where = "vae/config.json"
        channels = list(config.get("block_out_channels", (64,)))
        n = len(channels)
        down = list(config.get("down_block_types", ("DownEncoderBlock2D",) * n))
        up = list(config.get("up_block_types", ("UpDecoderBlock2D",) * n))
        if any(t != "DownEncoderBlock2D" for t in down) or any(t != "UpDecoderBlock2D" for t in up):
            raise DataError(where, f"unsupported block types {down} / {up} (only DownEncoderBlock2D"
                            " / UpDecoderBlock2D, as Stable Diffusion's VAE)")
        if len(down) != n or len(up) != n:
            raise DataError(where, "down_block_types, up_block_types and block_out_channels differ "
                            "in length")
        if config.get("norm_type", "group") != "group" or not config.get("double_z", True):
            raise DataError(where, "only norm_type 'group' with double_z is supported")
        layers, groups = int(config.get("layers_per_block", 1)), int(config.get("norm_num_groups", 32))
        c_img, c_out = int(config.get("in_channels", 3)), int(config.get("out_channels", 3))
        latent = int(config.get("latent_channels", 4))
        attention = bool(config.get("mid_block_add_attention", True))
        keys = iter(jax.random.split(key, 64 + 4 * n * (layers + 2)))
        nk = lambda: next(keys)  # noqa: E731
        res = lambda a, b: ResnetBlock2D.init(nk(), a, b, temb=None, groups=groups, eps=_EPS,  # noqa: E731
                                              dtype=dtype)

        enc_blocks, c = [], channels[0]
        for i, c_block in enumerate(channels):
            resnets = tuple(res(c if j == 0 else c_block, c_block) for j in range(layers))
            downs = () if i == n - 1 else (Downsample2D.init(nk(), c_block, asymmetric=True, dtype=dtype),)
            enc_blocks.append(EncoderBlock(resnets, downs))
            c = c_block
        encoder = Encoder(
            Conv2d.init(nk(), c_img, channels[0], 3, padding=1, dtype=dtype), tuple(enc_blocks),
            MidBlock2D.init(nk(), channels[-1], groups, attention, dtype),
            GroupNorm.init(groups, channels[-1], _EPS, dtype),
            Conv2d.init(nk(), channels[-1], 2 * latent, 3, padding=1, dtype=dtype))

        dec_blocks, rev = [], channels[::-1]
        c = rev[0]
        for i, c_block in enumerate(rev):
            resnets = tuple(res(c if j == 0 else c_block, c_block) for j in range(layers + 1))
            ups = () if i == n - 1 else (Upsample2D.init(nk(), c_block, dtype),)
            dec_blocks.append(DecoderBlock(resnets, ups))
            c = c_block
        decoder = Decoder(
            Conv2d.init(nk(), latent, channels[-1], 3, padding=1, dtype=dtype),
            MidBlock2D.init(nk(), channels[-1], groups, attention, dtype), tuple(dec_blocks),
            GroupNorm.init(groups, channels[0], _EPS, dtype),
            Conv2d.init(nk(), channels[0], c_out, 3, padding=1, dtype=dtype))
        quant = (Conv2d.init(nk(), 2 * latent, 2 * latent, 1, dtype=dtype)
                 if config.get("use_quant_conv", True) else None)
        post = (Conv2d.init(nk(), latent, latent, 1, dtype=dtype)
                if config.get("use_post_quant_conv", True) else None)
        scaling = config.get("scaling_factor", 0.18215)
        return AutoencoderKL(encoder, decoder, quant, post, float(scaling))

    @property
    def downsample_factor(self) -> int:
        """f = 2^(levels-1), image side / latent side (diffusers' ``vae_scale_factor``)."""
        return 2 ** (len(self.encoder.down_blocks) - 1)

    def encode(self, x: Array) -> tuple[Array, Array]:
        """Images [B, H, W, C] in [-1, 1] -> the posterior's (mean, logvar), each
        [B, H/f, W/f, latent], logvar clamped to [-30, 20] as diffusers does."""
        moments = self.encoder(x)
        if self.quant_conv is not None:
            moments = self.quant_conv(moments)
        mean, logvar = jnp.split(moments, 2, axis=-1)
        return mean, jnp.clip(logvar, -30.0, 20.0)

    def decode(self, z: Array) -> Array:
        """Latents [B, h, w, latent] (unscaled: divide diffusion latents by scaling_factor)
        -> images [B, h f, w f, C], nominally in [-1, 1] (not clamped)."""
        if self.post_quant_conv is not None:
            z = self.post_quant_conv(z)
        return self.decoder(z)
