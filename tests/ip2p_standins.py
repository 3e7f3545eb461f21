"""Small stand-in networks with the call signatures of jaxedit.models' Stable Diffusion pieces.

They let the JAX editor's own logic (SDEdit, the DDIM schedule, dual guidance, batching,
sharding) be tested against an independent reference without the real architectures:
every output depends non-linearly on every input the real one reads (sample, timestep,
context; pixels), so a wrong branch, timestep or embedding changes the result.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxedit.editors.jax_ip2p import DiffusionSchedule, JaxIP2PEditor

D = 16  # embedding width


def _conv(x, w):
    """NHWC 3x3 'same' convolution, w [3, 3, C_in, C_out]."""
    return jax.lax.conv_general_dilated(x, w, (1, 1), "SAME",
                                        dimension_numbers=("NHWC", "HWIO", "NHWC"))


class StandInUNet(eqx.Module):
    w1: jax.Array
    w2: jax.Array
    w_ctx: jax.Array
    w_t: jax.Array

    def __call__(self, sample, timestep, context):
        """sample [B, h, w, 8], timestep [B], context [B, 77, D] -> eps [B, h, w, 4]."""
        t = jnp.broadcast_to(jnp.asarray(timestep, jnp.float32), sample.shape[:1])
        emb = jnp.sin(t[:, None] * jnp.linspace(0.001, 0.05, 8)) @ self.w_t  # [B, 8]
        ctx = jnp.tanh(context.astype(jnp.float32).mean(1) @ self.w_ctx)     # [B, 8]
        h = jnp.tanh(_conv(sample, self.w1) + (emb + ctx)[:, None, None, :].astype(sample.dtype))
        return _conv(h, self.w2)


class StandInVAE(eqx.Module):
    w_enc: jax.Array
    w_dec: jax.Array
    scaling_factor: float = eqx.field(static=True, default=0.18215)

    def encode(self, x):
        """[B, H, W, 3] -> (mean, logvar) [B, H/8, W/8, 4] each."""
        b, h, w, _ = x.shape
        pooled = x.reshape(b, h // 8, 8, w // 8, 8, 3).mean((2, 4))
        moments = jnp.tanh(_conv(pooled, self.w_enc))
        return moments[..., :4] * 3, moments[..., 4:] * 2 - 1

    def decode(self, z):
        """[B, h, w, 4] -> [B, 8h, 8w, 3]."""
        out = jnp.tanh(_conv(z, self.w_dec))
        return jnp.repeat(jnp.repeat(out, 8, axis=1), 8, axis=2)


class StandInText(eqx.Module):
    table: jax.Array
    pos: jax.Array

    def __call__(self, ids):
        """int32 [B, 77] -> [B, 77, D]."""
        return jnp.tanh(self.table[ids] + self.pos)


def tokenize(prompts):
    """Characters -> ids (0 start, 1 end/padding), int32 [B, 77]."""
    out = np.ones((len(prompts), 77), np.int32)
    for i, p in enumerate(prompts):
        ids = [0] + [2 + (ord(c) % 60) for c in p][:75] + [1]
        out[i, :len(ids)] = ids
    return out


def standin_networks(seed: int = 0):
    """(unet, vae, text_encoder) with random weights."""
    k = jax.random.split(jax.random.key(seed), 6)
    unet = StandInUNet(jax.random.normal(k[0], (3, 3, 8, 8)) * 0.3,
                       jax.random.normal(k[1], (3, 3, 8, 4)) * 0.5,
                       jax.random.normal(k[2], (D, 8)), jax.random.normal(k[3], (8, 8)))
    vae = StandInVAE(jax.random.normal(k[4], (3, 3, 3, 8)),
                     jax.random.normal(k[5], (3, 3, 4, 3)) * 0.5)
    text = StandInText(jax.random.normal(jax.random.key(seed + 1), (64, D)),
                       jax.random.normal(jax.random.key(seed + 2), (77, D)) * 0.1)
    return unet, vae, text


def sd_schedule() -> DiffusionSchedule:
    """Stable Diffusion 1.x's scaled-linear betas, final alpha = alpha_0."""
    betas = np.linspace(0.00085 ** 0.5, 0.012 ** 0.5, 1000, dtype=np.float64) ** 2
    alphas = np.cumprod(1 - betas)
    return DiffusionSchedule(alphas, alphas[0])


def standin_editor(*, size=32, steps=2, devices=None, seed=0) -> JaxIP2PEditor:
    unet, vae, text = standin_networks(seed)
    return JaxIP2PEditor(unet, vae, text, tokenize, sd_schedule(), size=size, steps=steps,
                         devices=devices, source="stand-in")
