"""Stable Diffusion 1.x's building blocks as equinox modules (NHWC), pytree paths the
checkpoint's names; computing in the weights' dtype, norms and softmax in float32."""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp

Array = jax.Array

__all__ = [
    "ParamLayer", "Linear", "Conv2d", "GroupNorm", "LayerNorm", "Embedding", "Attention",
    "FeedForward", "GEGLU", "BasicTransformerBlock", "Transformer2DModel", "ResnetBlock2D",
    "Downsample2D", "Upsample2D", "TimestepEmbedding", "timestep_embedding", "activation",
    "upsample_nearest", "attention", "set_query_chunk", "standard_normal",
]


@functools.partial(jax.jit, static_argnums=(1, 2))
def _standard_normal_flat(key, length: int, dtype):
    return jax.random.normal(key, (length,), dtype)


def standard_normal(key, shape: tuple[int, ...], dtype=jnp.float32) -> Array:
    """``jax.random.normal(key, shape, dtype)``, compiled once per power-of-two length, not
    per shape (partitionable Threefry: a prefix of a longer draw has the same bits)."""
    if not jax.config.jax_threefry_partitionable:
        return jax.random.normal(key, shape, dtype)
    n = math.prod(shape)
    flat = _standard_normal_flat(key, 1 << max(n - 1, 0).bit_length(), jnp.dtype(dtype))
    return flat[:n].reshape(shape)


def _normal(key, shape, fan_in, dtype):
    """Random init, N(0, 1/fan_in): only for modules built without a checkpoint."""
    return standard_normal(key, shape, dtype) / math.sqrt(max(fan_in, 1))


def activation(name: str) -> Callable[[Array], Array]:
    """An activation function by its diffusers / transformers config name."""
    table = {
        "silu": jax.nn.silu, "swish": jax.nn.silu,
        "gelu": lambda x: jax.nn.gelu(x, approximate=False),
        "gelu_new": lambda x: jax.nn.gelu(x, approximate=True),
        "gelu_pytorch_tanh": lambda x: jax.nn.gelu(x, approximate=True),
        "quick_gelu": lambda x: x * jax.nn.sigmoid(1.702 * x),
        "relu": jax.nn.relu,
    }
    if name not in table:
        from ..errors import DataError
        raise DataError("config", f"unsupported activation {name!r} (supported: {sorted(table)})")
    return table[name]


class ParamLayer(eqx.Module):
    """A layer whose array fields are checkpoint tensors (see :meth:`torch_layout`)."""

    def torch_layout(self) -> dict[str, tuple[tuple[int, ...], Callable]]:
        """field name -> (the tensor's shape in a torch checkpoint, checkpoint array -> field)."""
        raise NotImplementedError


def _same(a):
    return a


class Linear(ParamLayer):
    """y = x W + b, W: [in, out] (the transpose of torch's Linear.weight)."""

    weight: Array
    bias: Array | None

    @staticmethod
    def init(key, d_in: int, d_out: int, *, bias: bool = True, dtype=jnp.float32) -> "Linear":
        return Linear(_normal(key, (d_in, d_out), d_in, dtype),
                      jnp.zeros((d_out,), dtype) if bias else None)

    def __call__(self, x: Array) -> Array:
        """[..., in] -> [..., out]"""
        y = x.astype(self.weight.dtype) @ self.weight
        return y if self.bias is None else y + self.bias

    def torch_layout(self):
        d_in, d_out = self.weight.shape
        # Old checkpoints store some attention projections as 1x1 convolutions [out, in, 1, 1].
        layout = {"weight": ((d_out, d_in), lambda w: w.reshape(w.shape[:2]).T)}
        if self.bias is not None:
            layout["bias"] = ((d_out,), _same)
        return layout


#: Maps of at most this many positions convolve as a patch matmul (XLA:CPU is slow on them).
SMALL_CONV_POSITIONS = 16


def _conv_as_matmul(x: Array, weight: Array, stride: int, padding: int) -> Array:
    """The convolution of ``x`` [B, H, W, C] by ``weight`` [kh, kw, C, O] as
    patches [B, H', W', kh * kw * C] @ weight [kh * kw * C, O] (HWIO order)."""
    kh, kw, c, o = weight.shape
    xp = jnp.pad(x, ((0, 0), (padding, padding), (padding, padding), (0, 0)))
    ho = (xp.shape[1] - kh) // stride + 1
    wo = (xp.shape[2] - kw) // stride + 1
    patches = jnp.concatenate(
        [xp[:, i: i + stride * (ho - 1) + 1: stride, j: j + stride * (wo - 1) + 1: stride]
         for i in range(kh) for j in range(kw)], axis=-1)
    return patches @ weight.reshape(kh * kw * c, o)


class Conv2d(ParamLayer):
    """2D convolution on NHWC images, kernel HWIO, symmetric zero padding."""

    weight: Array  # [kh, kw, in, out]
    bias: Array | None
    stride: int = eqx.field(static=True, default=1)
    padding: int = eqx.field(static=True, default=0)

    @staticmethod
    def init(key, c_in: int, c_out: int, kernel: int, *, stride: int = 1, padding: int = 0,
             bias: bool = True, dtype=jnp.float32) -> "Conv2d":
        w = _normal(key, (kernel, kernel, c_in, c_out), kernel * kernel * c_in, dtype)
        return Conv2d(w, jnp.zeros((c_out,), dtype) if bias else None, stride, padding)

    def __call__(self, x: Array) -> Array:
        """[B, H, W, in] -> [B, H', W', out]"""
        p, s = self.padding, self.stride
        x = x.astype(self.weight.dtype)
        if x.shape[1] * x.shape[2] <= SMALL_CONV_POSITIONS:
            y = _conv_as_matmul(x, self.weight, s, p)
        else:
            y = jax.lax.conv_general_dilated(x, self.weight, (s, s), ((p, p), (p, p)),
                                             dimension_numbers=("NHWC", "HWIO", "NHWC"))
        return y if self.bias is None else y + self.bias

    def torch_layout(self):
        kh, kw, c_in, c_out = self.weight.shape
        layout = {"weight": ((c_out, c_in, kh, kw), lambda w: w.transpose(2, 3, 1, 0))}
        if self.bias is not None:
            layout["bias"] = ((c_out,), _same)
        return layout


class GroupNorm(ParamLayer):
    """GroupNorm over the channels (last axis) of NHWC or [B, L, C] inputs, in float32."""

    weight: Array
    bias: Array
    groups: int = eqx.field(static=True)
    eps: float = eqx.field(static=True)

    @staticmethod
    def init(groups: int, channels: int, eps: float, dtype=jnp.float32) -> "GroupNorm":
        return GroupNorm(jnp.ones((channels,), dtype), jnp.zeros((channels,), dtype), groups, eps)

    def __call__(self, x: Array) -> Array:
        """[B, ..., C] -> same; statistics per (sample, group) over all positions."""
        b, c = x.shape[0], x.shape[-1]
        g = x.astype(jnp.float32).reshape(b, -1, self.groups, c // self.groups)
        mean = g.mean(axis=(1, 3), keepdims=True)
        var = jnp.square(g - mean).mean(axis=(1, 3), keepdims=True)
        y = ((g - mean) * jax.lax.rsqrt(var + self.eps)).reshape(x.shape)
        y = y * self.weight.astype(jnp.float32) + self.bias.astype(jnp.float32)
        return y.astype(self.weight.dtype)

    def torch_layout(self):
        (c,) = self.weight.shape
        return {"weight": ((c,), _same), "bias": ((c,), _same)}


class LayerNorm(ParamLayer):
    """LayerNorm over the last axis, in float32."""

    weight: Array
    bias: Array
    eps: float = eqx.field(static=True)

    @staticmethod
    def init(dim: int, eps: float, dtype=jnp.float32) -> "LayerNorm":
        return LayerNorm(jnp.ones((dim,), dtype), jnp.zeros((dim,), dtype), eps)

    def __call__(self, x: Array) -> Array:
        """[..., D] -> [..., D]"""
        xf = x.astype(jnp.float32)
        mean = xf.mean(-1, keepdims=True)
        var = jnp.square(xf - mean).mean(-1, keepdims=True)
        y = (xf - mean) * jax.lax.rsqrt(var + self.eps)
        y = y * self.weight.astype(jnp.float32) + self.bias.astype(jnp.float32)
        return y.astype(self.weight.dtype)

    def torch_layout(self):
        (d,) = self.weight.shape
        return {"weight": ((d,), _same), "bias": ((d,), _same)}


class Embedding(ParamLayer):
    """A lookup table [N, D] (same layout as torch)."""

    weight: Array

    @staticmethod
    def init(key, n: int, dim: int, dtype=jnp.float32) -> "Embedding":
        return Embedding(0.02 * standard_normal(key, (n, dim), dtype))

    def __call__(self, ids: Array) -> Array:
        """int [...] -> [..., D]"""
        return jnp.take(self.weight, ids, axis=0)

    def torch_layout(self):
        return {"weight": (tuple(self.weight.shape), _same)}


def attention(q: Array, k: Array, v: Array, *, causal: bool = False,
              query_chunk: int | None = None) -> Array:
    """softmax(q k^T / sqrt(Dh)) v per head, in float32: q [B, L, N, Dh], k and v
    [B, S, N, Dh] -> [B, L, N, Dh]; ``query_chunk`` queries at a time (same results)."""
    length = q.shape[1]
    if query_chunk is None or query_chunk >= length or causal:
        return jax.nn.dot_product_attention(q, k, v, is_causal=causal)
    n_full, rest = divmod(length, query_chunk)
    head = q[:, : n_full * query_chunk].reshape(q.shape[0], n_full, query_chunk, *q.shape[2:])
    out = jax.lax.map(lambda qc: jax.nn.dot_product_attention(qc, k, v), jnp.moveaxis(head, 1, 0))
    out = jnp.moveaxis(out, 0, 1).reshape(q.shape[0], n_full * query_chunk, *q.shape[2:])
    if rest:
        out = jnp.concatenate([out, jax.nn.dot_product_attention(q[:, n_full * query_chunk:], k, v)], 1)
    return out


class Attention(eqx.Module):
    """diffusers' ``Attention`` (self-attention when ``context`` is None); ``group_norm`` and
    ``residual`` are the VAE's variant."""

    to_q: Linear
    to_k: Linear
    to_v: Linear
    to_out: tuple[Linear]
    group_norm: GroupNorm | None
    heads: int = eqx.field(static=True)
    residual: bool = eqx.field(static=True, default=False)
    query_chunk: int | None = eqx.field(static=True, default=None)

    @staticmethod
    def init(key, query_dim: int, heads: int, head_dim: int, *, context_dim: int | None = None,
             qkv_bias: bool = False, norm_groups: int | None = None, norm_eps: float = 1e-6,
             residual: bool = False, dtype=jnp.float32) -> "Attention":
        kq, kk, kv, ko = jax.random.split(key, 4)
        inner, ctx = heads * head_dim, context_dim or query_dim
        return Attention(
            Linear.init(kq, query_dim, inner, bias=qkv_bias, dtype=dtype),
            Linear.init(kk, ctx, inner, bias=qkv_bias, dtype=dtype),
            Linear.init(kv, ctx, inner, bias=qkv_bias, dtype=dtype),
            (Linear.init(ko, inner, query_dim, dtype=dtype),),
            None if norm_groups is None else GroupNorm.init(norm_groups, query_dim, norm_eps, dtype),
            heads, residual)

    def __call__(self, x: Array, context: Array | None = None) -> Array:
        """x [B, L, D], context [B, S, Dc] or None -> [B, L, D]"""
        h = x if self.group_norm is None else self.group_norm(x)
        ctx = h if context is None else context
        q, k, v = self.to_q(h), self.to_k(ctx), self.to_v(ctx)
        split = lambda t: t.reshape(*t.shape[:2], self.heads, -1)  # noqa: E731 - [B, L, N, Dh]
        out = attention(split(q), split(k), split(v), query_chunk=self.query_chunk)
        out = self.to_out[0](out.reshape(*out.shape[:2], -1))
        return out + x if self.residual else out


class GEGLU(eqx.Module):
    """proj: D -> 2F; value * gelu(gate) (exact gelu), diffusers' GEGLU."""

    proj: Linear

    def __call__(self, x: Array) -> Array:
        value, gate = jnp.split(self.proj(x), 2, axis=-1)
        return value * jax.nn.gelu(gate, approximate=False)


class FeedForward(eqx.Module):
    """diffusers' FeedForward, ``net = (GEGLU, None for dropout, Linear)`` (checkpoint names)."""

    net: tuple[GEGLU, None, Linear]

    @staticmethod
    def init(key, dim: int, mult: int = 4, dtype=jnp.float32) -> "FeedForward":
        k1, k2 = jax.random.split(key)
        inner = dim * mult
        return FeedForward((GEGLU(Linear.init(k1, dim, 2 * inner, dtype=dtype)), None,
                            Linear.init(k2, inner, dim, dtype=dtype)))

    def __call__(self, x: Array) -> Array:
        return self.net[2](self.net[0](x))


class BasicTransformerBlock(eqx.Module):
    """Pre-LN self-attention, cross-attention on the text, GEGLU feed-forward; each residual."""

    norm1: LayerNorm
    attn1: Attention
    norm2: LayerNorm
    attn2: Attention
    norm3: LayerNorm
    ff: FeedForward

    @staticmethod
    def init(key, dim: int, heads: int, head_dim: int, context_dim: int, *, eps: float = 1e-5,
             dtype=jnp.float32) -> "BasicTransformerBlock":
        k1, k2, k3 = jax.random.split(key, 3)
        return BasicTransformerBlock(
            LayerNorm.init(dim, eps, dtype), Attention.init(k1, dim, heads, head_dim, dtype=dtype),
            LayerNorm.init(dim, eps, dtype),
            Attention.init(k2, dim, heads, head_dim, context_dim=context_dim, dtype=dtype),
            LayerNorm.init(dim, eps, dtype), FeedForward.init(k3, dim, dtype=dtype))

    def __call__(self, x: Array, context: Array) -> Array:
        """x [B, L, D], context [B, S, Dc] -> [B, L, D]"""
        x = x + self.attn1(self.norm1(x))
        x = x + self.attn2(self.norm2(x), context)
        return x + self.ff(self.norm3(x))


class Transformer2DModel(eqx.Module):
    """GroupNorm, proj_in (1x1 conv, or linear in SD 2.x), transformer blocks over the H*W
    tokens, proj_out, plus the input; ``eps``: the blocks' LayerNorm epsilon."""

    norm: GroupNorm
    proj_in: Conv2d | Linear
    transformer_blocks: tuple[BasicTransformerBlock, ...]
    proj_out: Conv2d | Linear

    @staticmethod
    def init(key, channels: int, heads: int, context_dim: int, *, groups: int, layers: int = 1,
             linear_projection: bool = False, eps: float = 1e-5,
             dtype=jnp.float32) -> "Transformer2DModel":
        keys = jax.random.split(key, layers + 2)
        head_dim = channels // heads
        proj = ((lambda k: Linear.init(k, channels, channels, dtype=dtype)) if linear_projection
                else (lambda k: Conv2d.init(k, channels, channels, 1, dtype=dtype)))
        blocks = tuple(BasicTransformerBlock.init(k, channels, heads, head_dim, context_dim,
                                                  eps=eps, dtype=dtype) for k in keys[2:])
        return Transformer2DModel(GroupNorm.init(groups, channels, 1e-6, dtype), proj(keys[0]),
                                  blocks, proj(keys[1]))

    def __call__(self, x: Array, context: Array) -> Array:
        """x [B, H, W, C], context [B, S, Dc] -> [B, H, W, C]"""
        b, h, w, c = x.shape
        proj = lambda layer, t: (layer(t) if isinstance(layer, Linear)  # noqa: E731
                                 else layer(t.reshape(b, h, w, -1)).reshape(b, h * w, -1))
        t = proj(self.proj_in, self.norm(x).reshape(b, h * w, c))
        for block in self.transformer_blocks:
            t = block(t, context)
        return proj(self.proj_out, t).reshape(b, h, w, c) + x


class ResnetBlock2D(eqx.Module):
    """norm-SiLU-conv, + time embedding projection, norm-SiLU-conv, + (1x1-projected) input."""

    norm1: GroupNorm
    conv1: Conv2d
    time_emb_proj: Linear | None
    norm2: GroupNorm
    conv2: Conv2d
    conv_shortcut: Conv2d | None
    output_scale: float = eqx.field(static=True, default=1.0)

    @staticmethod
    def init(key, c_in: int, c_out: int, *, temb: int | None, groups: int, eps: float,
             output_scale: float = 1.0, dtype=jnp.float32) -> "ResnetBlock2D":
        k1, k2, k3, k4 = jax.random.split(key, 4)
        return ResnetBlock2D(
            GroupNorm.init(groups, c_in, eps, dtype), Conv2d.init(k1, c_in, c_out, 3, padding=1, dtype=dtype),
            None if temb is None else Linear.init(k2, temb, c_out, dtype=dtype),
            GroupNorm.init(groups, c_out, eps, dtype),
            Conv2d.init(k3, c_out, c_out, 3, padding=1, dtype=dtype),
            None if c_in == c_out else Conv2d.init(k4, c_in, c_out, 1, dtype=dtype), output_scale)

    def __call__(self, x: Array, temb: Array | None = None) -> Array:
        """x [B, H, W, Cin], temb [B, T] or None -> [B, H, W, Cout]"""
        h = self.conv1(jax.nn.silu(self.norm1(x)))
        if self.time_emb_proj is not None:
            h = h + self.time_emb_proj(jax.nn.silu(temb))[:, None, None, :]
        h = self.conv2(jax.nn.silu(self.norm2(h)))
        skip = x if self.conv_shortcut is None else self.conv_shortcut(x)
        out = skip.astype(h.dtype) + h
        return out if self.output_scale == 1.0 else out / self.output_scale


class Downsample2D(eqx.Module):
    """Stride-2 3x3 convolution; ``asymmetric``: pad bottom/right by one only (the VAE's)."""

    conv: Conv2d
    asymmetric: bool = eqx.field(static=True, default=False)

    @staticmethod
    def init(key, channels: int, *, asymmetric: bool, dtype=jnp.float32) -> "Downsample2D":
        conv = Conv2d.init(key, channels, channels, 3, stride=2, padding=0 if asymmetric else 1,
                           dtype=dtype)
        return Downsample2D(conv, asymmetric)

    def __call__(self, x: Array) -> Array:
        """[B, H, W, C] -> [B, ceil(H/2), ceil(W/2), C]"""
        if self.asymmetric:
            x = jnp.pad(x, ((0, 0), (0, 1), (0, 1), (0, 0)))
        return self.conv(x)


def upsample_nearest(x: Array, size: tuple[int, int]) -> Array:
    """NHWC ``x`` resized to ``size``, nearest pixel floor(i * in / out) as torch picks it."""
    h, w = x.shape[1:3]
    rows = (jnp.arange(size[0]) * h) // size[0]
    cols = (jnp.arange(size[1]) * w) // size[1]
    return x[:, rows][:, :, cols]


class Upsample2D(eqx.Module):
    """Nearest x2 (or to a given size) then a 3x3 convolution."""

    conv: Conv2d

    @staticmethod
    def init(key, channels: int, dtype=jnp.float32) -> "Upsample2D":
        return Upsample2D(Conv2d.init(key, channels, channels, 3, padding=1, dtype=dtype))

    def __call__(self, x: Array, size: tuple[int, int] | None = None) -> Array:
        """[B, H, W, C] -> [B, 2H, 2W, C] (or [B, *size, C])"""
        h, w = x.shape[1:3]
        if size is None or tuple(size) == (2 * h, 2 * w):
            x = jnp.repeat(jnp.repeat(x, 2, axis=1), 2, axis=2)
        else:
            x = upsample_nearest(x, size)
        return self.conv(x)


def timestep_embedding(timesteps: Array, dim: int, *, flip_sin_to_cos: bool = True,
                       freq_shift: float = 0.0, max_period: float = 10000.0) -> Array:
    """Sinusoidal embedding of timesteps [B] -> float32 [B, dim], as diffusers'
    ``get_timestep_embedding`` (``flip_sin_to_cos``: [cos | sin]; odd ``dim``: a zero column)."""
    half = dim // 2
    exponent = -math.log(max_period) * jnp.arange(half, dtype=jnp.float32) / (half - freq_shift)
    args = jnp.asarray(timesteps, jnp.float32)[:, None] * jnp.exp(exponent)[None, :]
    emb = jnp.concatenate([jnp.sin(args), jnp.cos(args)], axis=-1)
    if flip_sin_to_cos:
        emb = jnp.concatenate([emb[:, half:], emb[:, :half]], axis=-1)
    if dim % 2:
        emb = jnp.pad(emb, ((0, 0), (0, 1)))
    return emb


class TimestepEmbedding(eqx.Module):
    """linear_1, SiLU, linear_2: the sinusoidal embedding -> the resnets' time embedding."""

    linear_1: Linear
    linear_2: Linear

    @staticmethod
    def init(key, d_in: int, d_out: int, dtype=jnp.float32) -> "TimestepEmbedding":
        k1, k2 = jax.random.split(key)
        return TimestepEmbedding(Linear.init(k1, d_in, d_out, dtype=dtype),
                                 Linear.init(k2, d_out, d_out, dtype=dtype))

    def __call__(self, x: Array) -> Array:
        return self.linear_2(jax.nn.silu(self.linear_1(x)))


def set_query_chunk(model, query_chunk: int | None):
    """``model`` (a pytree) with every :class:`Attention`'s ``query_chunk`` set (None: all)."""
    is_attention = lambda x: isinstance(x, Attention)  # noqa: E731
    return jax.tree_util.tree_map(
        lambda a: dataclasses.replace(a, query_chunk=query_chunk) if is_attention(a) else a,
        model, is_leaf=is_attention)
