"""InstructPix2Pix in JAX: the edit of :mod:`jaxedit.editors.ip2p`, as one jit-compiled pure function.

The edit is the torch reference's, step for step (see :mod:`jaxedit.editors.ip2p`): resize to
the model size, VAE-encode the render (posterior sample x ``scaling_factor``) and the
original (posterior mode, unscaled), draw T in ``timestep_range`` from the key, noise the
latent to T (SDEdit), deterministic DDIM (eta = 0) over :func:`timestep_schedule`'s steps
with three-branch dual classifier-free guidance, decode, resize back, clamp. The shared
arithmetic lives in :mod:`jaxedit.editors.diffusion`.

The core, :func:`edit_with_noise`, is pure in (networks, images, originals, embeddings,
T, noises) and batched: B views in one call, each with its own T. Its number of DDIM
steps is static while T is traced: slot k of the schedule holds round(T (steps - k) /
steps) and slots that repeat or reach 0 (T < steps) leave the latent as it is
(:func:`jaxedit.editors.diffusion.timestep_table`), so one compiled program serves every
T. :func:`edit_batch` only draws T and the noises from per-view keys.

Randomness: view key -> (k_t, k_n) by ``jax.random.split`` exactly as the torch editor
splits it, so both draw the same T from the same key; the two standard normal latents
(posterior sample, SDEdit noise) are drawn from k_n with ``jax.random.normal``, on the
device.

Devices and precision: the editor runs on ``devices`` (default: the first JAX device). With
several, a :class:`jax.sharding.Mesh` over them shards a batch of views along its first
axis (``NamedSharding(mesh, P("views"))``) with the networks replicated; every view's
arithmetic is independent, so a sharded batch gives a one-device batch's results. The
networks run in bfloat16 on accelerators (float32's range: no fp16 VAE overflow; pass
``dtype="float16"`` for torch's choice) and float32 on the CPU; the latents, the DDIM
arithmetic and the output are float32. Images go in as NumPy or JAX arrays and the result
is a JAX array on the editor's device: the trainer takes it from there with
``jax.device_put`` (:mod:`jaxedit.edit.buffer`), never through the host.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
from typing import Any, Callable, NamedTuple, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ..errors import DataError
from .base import editor_guidance
from .diffusion import (DDIM_STEPS, DEFAULT_MODEL, IP2P_GUIDANCE, check_guidance, ddim_step,
                        dtype_name, dual_guidance, model_size, timestep_bounds, timestep_table)
from .masks import relevance_mask

log = logging.getLogger(__name__)

__all__ = ["DiffusionSchedule", "EditConfig", "JaxIP2PEditor", "Networks", "decode",
           "denoise", "draw_noise", "edit_batch", "edit_with_noise", "encode_latents",
           "default_batch", "in_chunks", "latent_factor", "load_bundled", "load_editor",
           "load_text_encoder", "resize_images"]

#: Name of the mesh axis a batch of views is sharded along.
VIEWS = "views"


class Networks(eqx.Module):
    """The two networks an edit runs: the 8-channel conditional UNet and the VAE.

    ``unet(sample [B, h, w, 8], timestep [B], context [B, 77, D]) -> eps [B, h, w, 4]``;
    ``vae.encode(x [B, H, W, 3] in [-1, 1]) -> (mean, logvar)`` [B, H/f, W/f, 4] each;
    ``vae.decode(z) -> [B, H, W, 3]`` (see :mod:`jaxedit.models`), f the VAE's downsampling
    factor (:func:`latent_factor`: 8 for Stable Diffusion's VAE, 4 for a 3-level one).
    """

    unet: Any
    vae: Any


class DiffusionSchedule(NamedTuple):
    """The noise schedule, as the DDIM update reads it.

    alphas_cumprod: float32 [N] (N = num_train_timesteps), cumulative alpha per timestep.
    final_alpha: the alpha the last DDIM step lands on (alpha_0, or 1 with
      ``set_alpha_to_one``).
    """

    alphas_cumprod: jax.Array
    final_alpha: jax.Array


@dataclasses.dataclass(frozen=True)
class EditConfig:
    """Static settings of a compiled edit (hashable: a change recompiles).

    steps: DDIM slots; prediction_type: "epsilon", "v_prediction" or "sample";
    clip_sample: x0 clamp (None: none, SD 1.x); scaling_factor: the VAE latent scale;
    dtype: the networks' dtype name; guidance: (text, image) scales; vae_chunk: views per
    VAE pass (encode and decode run over the batch in chunks of this many, one after
    another, so their activations are one chunk's; None: the whole batch at once). Every
    view's VAE pass is independent of the others', so chunking changes memory, not results.
    """

    steps: int = DDIM_STEPS
    prediction_type: str = "epsilon"
    clip_sample: float | None = None
    scaling_factor: float = 0.18215
    dtype: str = "float32"
    guidance: tuple[float, float] = IP2P_GUIDANCE
    vae_chunk: int | None = None


# ----------------------------------------------------------------------------- pure pieces

def latent_factor(vae) -> int:
    """The VAE's downsampling factor f (image side / latent side): its ``downsample_factor``
    (:class:`jaxedit.models.AutoencoderKL`: 2^(levels-1) from its blocks, as diffusers'
    ``vae_scale_factor`` is from ``block_out_channels``); 8, Stable Diffusion's, for a VAE
    that does not state one. Static: it is read from the module's structure, never traced."""
    return int(getattr(vae, "downsample_factor", 8))


def resize_images(images: jax.Array, hw: tuple[int, int]) -> jax.Array:
    """[B, H, W, C] -> [B, h, w, C]: bilinear, antialiased when shrinking (as torch's
    ``interpolate(mode="bilinear", antialias=True)``); the same size is returned as is."""
    if tuple(images.shape[1:3]) == tuple(hw):
        return images
    return jax.image.resize(images, (images.shape[0], *hw, images.shape[3]), method="linear",
                            antialias=True)


def in_chunks(fn: Callable, x: jax.Array, chunk: int | None):
    """``fn(x)`` for a batch-wise ``fn`` (each example's output depends on that example
    only), evaluated over chunks of ``chunk`` examples one after another (``lax.map``), so
    the temporaries held at once are one chunk's. The batch is padded to a multiple of
    ``chunk`` (with copies of its last example, dropped after). None, or a chunk not
    smaller than the batch: one call."""
    b = x.shape[0]
    if chunk is None or chunk >= b:
        return fn(x)
    chunk = max(int(chunk), 1)
    pad = -b % chunk
    if pad:
        x = jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)])
    out = jax.lax.map(fn, x.reshape(-1, chunk, *x.shape[1:]))
    return jax.tree_util.tree_map(lambda y: y.reshape(-1, *y.shape[2:])[:b], out)


def encode_latents(vae, images: jax.Array, originals: jax.Array, vae_noise: jax.Array,
                   cfg: EditConfig) -> tuple[jax.Array, jax.Array]:
    """(latents, cond), float32 [B, h/f, w/f, 4] each, from images in [0, 1] at model size
    (f: :func:`latent_factor`).

    One VAE pass over both: the render's posterior sample mean + std * ``vae_noise`` times
    the scaling factor, and the original's posterior mode (its mean), unscaled. With
    ``cfg.vae_chunk`` = c, c views (their renders and originals, 2c images) per pass
    (:func:`in_chunks`).
    """
    b = images.shape[0]
    if cfg.vae_chunk is None or cfg.vae_chunk >= b:
        pair = jnp.concatenate([images, originals]) * 2 - 1
        mean, logvar = vae.encode(pair.astype(cfg.dtype))
    else:  # views [B, 2, H, W, 3]: each chunk encodes its renders and originals together
        pairs = (jnp.stack([images, originals], 1) * 2 - 1).astype(cfg.dtype)
        flat = lambda v: v.reshape(-1, *v.shape[2:])  # noqa: E731 - [c, 2, ...] -> [2c, ...]
        both = in_chunks(lambda v: jax.tree_util.tree_map(
            lambda y: y.reshape(v.shape[0], 2, *y.shape[1:]), vae.encode(flat(v))),
            pairs, cfg.vae_chunk)
        mean, logvar = (jnp.concatenate([y[:, 0], y[:, 1]]) for y in both)
    mean, logvar = mean.astype(jnp.float32), logvar.astype(jnp.float32)
    std = jnp.exp(0.5 * jnp.clip(logvar, -30.0, 20.0))  # diffusers' posterior clamps logvar
    latents = (mean[:b] + std[:b] * vae_noise) * cfg.scaling_factor
    return latents, mean[b:]


def denoise(unet, latents: jax.Array, cond: jax.Array, embeddings: jax.Array, null: jax.Array,
            t_start: jax.Array, sde_noise: jax.Array, schedule: DiffusionSchedule,
            cfg: EditConfig) -> jax.Array:
    """SDEdit to T then DDIM back to the clean latent, float32 [B, h, w, 4].

    Args:
      latents, cond, sde_noise: float32 [B, h, w, 4].
      embeddings: float [B, 77, D] the edit's embeddings e; null: float [77, D], E("").
      t_start: int32 [B], T per view.
    Each step evaluates the UNet once on 3B samples ordered (text+image: e with cond;
    image: E("") with cond; unconditional: E("") with zeros) and combines them with
    :func:`dual_guidance`.
    """
    a = schedule.alphas_cumprod
    b = latents.shape[0]
    expand = lambda v: v[:, None, None, None]  # noqa: E731 - [B] -> broadcast over a latent
    a_start = expand(a[t_start])
    x = a_start ** 0.5 * latents + (1 - a_start) ** 0.5 * sde_noise
    ts, t_next, valid = timestep_table(t_start, cfg.steps)  # [B, steps] each
    nulls = jnp.broadcast_to(null, (2 * b, *null.shape))
    context = jnp.concatenate([embeddings, nulls]).astype(cfg.dtype)
    cond3 = jnp.concatenate([cond, cond, jnp.zeros_like(cond)]).astype(cfg.dtype)

    def step(x, slot):
        t, t_n, ok = slot
        sample = jnp.concatenate([jnp.concatenate([x] * 3).astype(cfg.dtype), cond3], axis=-1)
        eps = unet(sample, jnp.concatenate([t] * 3), context).astype(jnp.float32)
        eps = dual_guidance(eps, *cfg.guidance)
        a_prev = jnp.where(t_n > 0, a[t_n], schedule.final_alpha)
        new = ddim_step(x, eps, expand(a[t]), expand(a_prev), cfg.prediction_type,
                        cfg.clip_sample)
        return jnp.where(expand(ok), new, x), None

    x, _ = jax.lax.scan(step, x, (ts.T, t_next.T, valid.T))
    return x


def decode(vae, latents: jax.Array, cfg: EditConfig) -> jax.Array:
    """Latents [B, h, w, 4] -> images float32 [B, f h, f w, 3] in [0, 1] (f:
    :func:`latent_factor`), decoded ``cfg.vae_chunk`` views at a time (:func:`in_chunks`)."""
    decoded = in_chunks(vae.decode, (latents / cfg.scaling_factor).astype(cfg.dtype),
                        cfg.vae_chunk).astype(jnp.float32)
    return jnp.clip((decoded + 1) / 2, 0, 1)


def edit_with_noise(nets: Networks, images: jax.Array, originals: jax.Array,
                    embeddings: jax.Array, null: jax.Array, t_start: jax.Array,
                    vae_noise: jax.Array, sde_noise: jax.Array, schedule: DiffusionSchedule,
                    cfg: EditConfig) -> jax.Array:
    """The whole edit with its random draws given (pure; the torch editor's
    ``edit_with_noise``).

    Args:
      images, originals: float [B, H, W, 3] in [0, 1], renders and original photos.
      embeddings: float [B, 77, D] or [77, D] (one for all views); null: [77, D].
      t_start: int32 [B]; vae_noise, sde_noise: float32 [B, h/f, w/f, 4] standard normals
        at the model size (h, w) = latent size x f, f the VAE's :func:`latent_factor`.
    Returns:
      float32 [B, H, W, 3] in [0, 1].
    """
    b, height, width = images.shape[:3]
    f = latent_factor(nets.vae)
    hw = (vae_noise.shape[1] * f, vae_noise.shape[2] * f)
    embeddings = jnp.broadcast_to(embeddings, (b, *null.shape))
    latents, cond = encode_latents(nets.vae, resize_images(images.astype(jnp.float32), hw),
                                   resize_images(originals.astype(jnp.float32), hw),
                                   vae_noise.astype(jnp.float32), cfg)
    latents = denoise(nets.unet, latents, cond, embeddings, null, t_start,
                      sde_noise.astype(jnp.float32), schedule, cfg)
    return jnp.clip(resize_images(decode(nets.vae, latents, cfg), (height, width)), 0, 1)


def draw_noise(keys: jax.Array, t_bounds: jax.Array, latent_hw: tuple[int, int]):
    """(t_start int32 [B], vae_noise, sde_noise float32 [B, h, w, 4]) from keys [B].

    ``t_bounds``: int32 [2], T's inclusive range (:func:`timestep_bounds`). Each key splits
    into (k_t, k_n) as in the torch editor (same T from the same key); k_n gives the noises.
    """
    def one(key):
        k_t, k_n = jax.random.split(key)
        t = jax.random.randint(k_t, (), t_bounds[0], t_bounds[1] + 1)
        k_vae, k_sde = jax.random.split(k_n)
        shape = (*latent_hw, 4)
        return (t.astype(jnp.int32), jax.random.normal(k_vae, shape, jnp.float32),
                jax.random.normal(k_sde, shape, jnp.float32))

    return jax.vmap(one)(keys)


def edit_batch(nets: Networks, images: jax.Array, originals: jax.Array, embeddings: jax.Array,
               null: jax.Array, keys: jax.Array, t_bounds: jax.Array,
               schedule: DiffusionSchedule, cfg: EditConfig, model_hw: tuple[int, int]):
    """Edit B views, float32 [B, H, W, 3], T and noises drawn from ``keys`` [B] (typed keys).

    ``model_hw``: the networks' (h, w), multiples of the VAE's :func:`latent_factor` f
    (:func:`model_size`); the latents are (h/f, w/f).
    """
    f = latent_factor(nets.vae)
    t_start, vae_noise, sde_noise = draw_noise(keys, t_bounds, (model_hw[0] // f,
                                                                model_hw[1] // f))
    return edit_with_noise(nets, images, originals, embeddings, null, t_start, vae_noise,
                           sde_noise, schedule, cfg)


#: Compiled: everything but the networks' arrays, the inputs and the schedule is static.
edit_with_noise_jit = eqx.filter_jit(edit_with_noise)


def _edit_batch_into(kept: tuple, images: jax.Array, cfg: EditConfig, model_hw: tuple[int, int]):
    nets, originals, embeddings, null, keys, t_bounds, schedule = kept
    return edit_batch(nets, images, originals, embeddings, null, keys, t_bounds, schedule, cfg,
                      model_hw)


#: :func:`edit_batch`, jitted with ``images`` donated: the output (float32, the images'
#: shape) is written into the images' buffer instead of a new one. Only for an images
#: buffer the caller no longer holds (:meth:`JaxIP2PEditor.edit_many` gives it a copy).
edit_batch_donating_jit = eqx.filter_jit(_edit_batch_into, donate="all-except-first")


#: Noise draws (each with its own timestep) averaged per view by ``relevance``.
RELEVANCE_DRAWS = 4


def noise_difference(nets, images, originals, embedding, null, keys, t_bounds, schedule,
                     cfg, model_hw: tuple[int, int], draws: int = RELEVANCE_DRAWS) -> jax.Array:
    """Mean |eps(x_t, c, e) - eps(x_t, c, E(""))| per latent pixel, float32 [B, h, w].

    Args:
      nets: :class:`jaxedit.editors.jax_ip2p.Networks`.
      images, originals: float [B, H, W, 3] in [0, 1] (render, original photo).
      embedding: float [77, D], the instruction's; null: [77, D], E("").
      keys: B typed keys; each draws ``draws`` timesteps in ``t_bounds`` (int32 [2])
        and noises.
      schedule, cfg: the editor's :class:`DiffusionSchedule` and :class:`EditConfig`.
      model_hw: the networks' (h, w), multiples of the VAE's factor f.
    Returns:
      float32 [B, h/f, w/f], averaged over channels and draws.
    """
    b = images.shape[0]
    f = latent_factor(nets.vae)
    lat_hw = (model_hw[0] // f, model_hw[1] // f)
    sub = jax.vmap(lambda k: jax.random.split(k, draws))(keys).reshape(-1)  # [B * draws]
    t, vae_noise, sde_noise = draw_noise(sub, t_bounds, lat_hw)
    rep = lambda x: jnp.repeat(x, draws, 0)  # noqa: E731 - [B, ...] -> [B * draws, ...]
    latents, cond = encode_latents(
        nets.vae, rep(resize_images(images.astype(jnp.float32), model_hw)),
        rep(resize_images(originals.astype(jnp.float32), model_hw)), vae_noise, cfg)
    a = schedule.alphas_cumprod[t][:, None, None, None]
    x = a ** 0.5 * latents + (1 - a) ** 0.5 * sde_noise
    n = b * draws
    context = jnp.concatenate([jnp.broadcast_to(embedding, (n, *null.shape)),
                               jnp.broadcast_to(null, (n, *null.shape))]).astype(cfg.dtype)
    sample = jnp.concatenate([jnp.concatenate([x, x]), jnp.concatenate([cond, cond])], -1)
    eps = nets.unet(sample.astype(cfg.dtype), jnp.concatenate([t, t]), context)
    eps = eps.astype(jnp.float32)
    diff = jnp.mean(jnp.abs(eps[:n] - eps[n:]), -1)  # [B * draws, h, w]
    return jnp.mean(diff.reshape(b, draws, *diff.shape[1:]), 1)


noise_difference_jit = eqx.filter_jit(noise_difference)


# ----------------------------------------------------------------------------- the editor

def check_prompt(prompt) -> str:
    """``prompt`` when it is text the tokenizer takes: a string of valid UTF-8 (a command
    line's stray bytes arrive as lone surrogates, on which the tokenizer fails). The
    message shows where, not the prompt: a prompt may be pages long."""
    if not isinstance(prompt, str):
        raise DataError("prompt", f"must be a string, got {type(prompt).__name__}")
    try:
        prompt.encode("utf-8")
    except UnicodeEncodeError as e:
        raise DataError("prompt", f"is not valid UTF-8 text (a stray byte "
                                  f"{os.fsencode(prompt[e.start])!r} at character {e.start}); "
                                  f"give the instruction as UTF-8") from None
    return prompt


#: Feature maps of the UNet's first level an edit holds at once (its skips, attention and
#: resnet temporaries), per sample: the factor of :func:`edit_memory_at_least`.
HELD_MAPS = 8


def edit_memory_at_least(size: int, steps: int, batch: int, factor: int, width: int,
                         itemsize: int) -> float:
    """Bytes one batch of edits holds at least: its timestep tables (int32 [3, batch, steps]),
    the images and their float32 copies at model size, and the UNet's first-level feature
    maps of its three guidance branches (:data:`HELD_MAPS` of them)."""
    latent = (size / factor) ** 2
    return (3 * batch * steps * 4 + 4 * batch * size * size * 3 * 4
            + 3 * batch * latent * width * itemsize * HELD_MAPS)


def first_level_width(unet) -> int:
    """Channels of the UNet's first level (its ``conv_in`` outputs); 0 for a network without
    Stable Diffusion's ``conv_in`` (the tests' stand-ins), whose maps the bound then leaves out:
    :func:`edit_memory_at_least` stays a lower bound."""
    conv_in = getattr(unet, "conv_in", None)
    return 0 if conv_in is None else int(conv_in.weight.shape[-1])


def check_edit_sizes(size: int | None, steps: int, batch: int, timesteps: int, factor: int,
                     width: int, itemsize: int) -> None:
    """Refuse, before any edit, DDIM steps beyond the schedule's timesteps (every step past
    them repeats a timestep and changes nothing, at the cost of a UNet call) and a model size,
    step count and batch whose edit cannot fit in the free memory
    (:func:`jaxedit.memory.require_memory`). ``size`` None: the views' own size, unknown
    until they come."""
    from ..memory import require_memory

    if steps > timesteps:
        raise DataError("--ip2p-steps", f"{steps} DDIM steps, but the schedule has {timesteps} "
                                      f"timesteps (at most one step each)")
    if size is not None:
        require_memory("--ip2p-size/--ip2p-steps/--ip2p-batch",
                       edit_memory_at_least(size, steps, batch, factor, width, itemsize),
                       f"editing {batch} view(s) at {size} px")


def default_dtype(device: jax.Device) -> str:
    """float32 on the CPU, bfloat16 on accelerators."""
    return "float32" if device.platform == "cpu" else "bfloat16"


def _float_dtype_name(dtype) -> str:
    """``dtype``'s name (an alias spelled out) if JAX has it as a floating dtype."""
    name = dtype_name(dtype)
    try:
        ok = jnp.issubdtype(jnp.dtype(name), jnp.floating)
    except TypeError:
        ok = False
    if not ok:
        raise DataError("dtype", f"unknown floating point dtype {dtype!r}")
    return jnp.dtype(name).name


def _as_batch(x, field: str, ndim: int) -> jax.Array:
    """An array of ``ndim`` dims (a single view gets a batch axis of 1), float, last axis 3."""
    x = x if isinstance(x, jax.Array) else np.asarray(x)
    if x.ndim == ndim - 1:
        x = x[None]
    if x.ndim != ndim or x.shape[-1] != 3:
        raise DataError(field, f"expected images [B, H, W, 3] or [H, W, 3], got shape "
                        f"{tuple(x.shape)}")
    if not jnp.issubdtype(x.dtype, jnp.floating):
        raise DataError(field, f"expected float values in [0, 1], got {x.dtype}")
    return x


#: Queries per attention chunk (:class:`JaxIP2PEditor`'s ``attention_chunk``): SD's first
#: level at 512 px has 4096 positions, so 4 chunks there; 256 px and below, one.
ATTENTION_CHUNK = 1024
#: Views per VAE pass (:attr:`EditConfig.vae_chunk`): one 512 px view's decode already
#: fills an accelerator, and a batch of 8 at once would hold 8 views' activations.
VAE_CHUNK = 1
#: Where the text encoder may live once the null prompt is encoded (:class:`JaxIP2PEditor`).
TEXT_ENCODER_RESIDENCY = ("auto", "device", "host", "reload")


def _residency(value: str, device: jax.Device, load: Callable | None) -> str:
    if value not in TEXT_ENCODER_RESIDENCY:
        raise DataError("text_encoder_residency", f"must be one of {TEXT_ENCODER_RESIDENCY}, "
                        f"got {value!r}")
    if value == "reload" and load is None:
        raise DataError("text_encoder_residency", "'reload' needs load_text_encoder")
    if value != "auto":
        return value
    if device.platform != "cpu":
        return "host"
    return "reload" if load is not None else "device"



class JaxIP2PEditor:
    """InstructPix2Pix in JAX implementing :class:`jaxedit.editors.Editor` (module docstring).

    Args:
      unet, vae, text_encoder: equinox modules (:mod:`jaxedit.models`); the UNet's parameter
        dtype is the networks' compute dtype (:meth:`from_pretrained` loads them in the
        device's default: float32 on the CPU, bfloat16 on accelerators).
      tokenize: ``list[str] -> int32 [B, 77]`` CLIP token ids.
      schedule: :class:`DiffusionSchedule`; prediction_type, clip_sample: the DDIM update's.
      devices: the editor's devices (default: the first JAX device); several shard batches.
      size: model resolution of the longer side (a multiple of the VAE's downsampling factor,
        ``latent_factor``: 8 for Stable Diffusion; None keeps the view's size).
      steps: DDIM steps from T to 0.
      batch: most views per :meth:`edit_many` call when several are due at once (a
        subtask's initial sweep, the difficulty's views; :func:`jaxedit.editors.edit_views`).
        Default: :func:`default_batch` of the devices.
      guidance: the (text, image) scales of an edit that names none (:meth:`from_pretrained`:
        the folder's :func:`jaxedit.editors.bundled.recommended_guidance`).

    Memory (what an edit at 512 px holds; ``benchmarks/memory.py`` measures it):
      attention_chunk: queries per attention chunk in the UNet and the VAE
        (:func:`jaxedit.models.set_query_chunk`): the float32 logits held at once are
        [3B, heads, chunk, L] instead of [3B, heads, L, L] (L = 4096 at SD's first level at
        512 px: 1.6 GB per view at once). Same results. None: no chunking.
      vae_chunk: views per VAE pass (:attr:`EditConfig.vae_chunk`); same results. Default
        :data:`VAE_CHUNK`; None: the whole batch at once.
      text_encoder_residency: where the text encoder lives once the null prompt is
        encoded (embeddings are cached per prompt, so it runs only for a new prompt):
        "device" (kept on the editor's devices), "host" (a NumPy copy in host memory,
        uploaded for a new prompt and freed after), "reload" (dropped; reloaded from
        ``load_text_encoder`` for a new prompt) or "auto": "host" on accelerators, and on
        the CPU (where host memory is the device's) "reload" when ``load_text_encoder`` is
        given, else "device".
      load_text_encoder: ``() -> module``, the text encoder as loaded (from_pretrained:
        from the weights folder).
    """

    name = "ip2p"

    def __init__(self, unet, vae, text_encoder, tokenize: Callable[[list[str]], np.ndarray],
                 schedule: DiffusionSchedule, *, prediction_type: str = "epsilon",
                 clip_sample: float | None = None, scaling_factor: float = 0.18215,
                 devices: Sequence[jax.Device] | None = None,
                 size: int | None = 512, steps: int = DDIM_STEPS, source: str = "",
                 batch: int | None = None,
                 guidance: tuple[float, float] = IP2P_GUIDANCE,
                 attention_chunk: int | None = ATTENTION_CHUNK,
                 vae_chunk: int | None = VAE_CHUNK, text_encoder_residency: str = "auto",
                 load_text_encoder: Callable[[], Any] | None = None):
        self.devices = list(devices) if devices else [jax.devices()[0]]
        self.batch = default_batch(self.devices) if batch is None else int(batch)
        if self.batch < 1:
            raise DataError("batch", f"must be >= 1, got {batch}")
        self.dtype = _float_dtype(unet)
        #: image side / latent side of the VAE (:func:`latent_factor`): model sizes are
        #: multiples of it.
        self.latent_factor = latent_factor(vae)
        if size is not None and size % self.latent_factor:
            raise DataError("size", f"model size {size} is not a multiple of "
                            f"{self.latent_factor} (the VAE's downsampling factor)")
        if int(steps) < 1:
            raise DataError("steps", f"must be >= 1, got {steps}")
        check_edit_sizes(size, int(steps), self.batch, int(np.shape(schedule.alphas_cumprod)[0]),
                         self.latent_factor, first_level_width(unet),
                         jnp.dtype(self.dtype).itemsize)
        self.size, self.steps, self.source = size, int(steps), source
        self.guidance = check_guidance(guidance)
        for name, value in (("attention_chunk", attention_chunk), ("vae_chunk", vae_chunk)):
            if value is not None and int(value) < 1:
                raise DataError(name, f"must be >= 1 or None, got {value}")
        self.attention_chunk = None if attention_chunk is None else int(attention_chunk)
        self.vae_chunk = None if vae_chunk is None else int(vae_chunk)
        self.mesh = Mesh(np.array(self.devices), (VIEWS,))
        self.replicated = NamedSharding(self.mesh, PartitionSpec())
        self.by_view = NamedSharding(self.mesh, PartitionSpec(VIEWS))
        from ..models import set_query_chunk
        # A device_put to the device the weights are on shares their buffers (no copy).
        self.nets = jax.device_put(set_query_chunk(Networks(unet, vae), self.attention_chunk),
                                   self.replicated)
        self.text_encoder_residency = _residency(text_encoder_residency, self.devices[0],
                                                 load_text_encoder)
        self._load_text_encoder = load_text_encoder
        self._text_encoder = jax.device_put(text_encoder, self.replicated)
        self._text_encoder_host = None
        self.tokenize = tokenize
        self.schedule = jax.device_put(DiffusionSchedule(
            jnp.asarray(schedule.alphas_cumprod, jnp.float32),
            jnp.asarray(schedule.final_alpha, jnp.float32)), self.replicated)
        self.num_train_timesteps = int(np.shape(schedule.alphas_cumprod)[0])
        self.prediction_type = prediction_type
        self.clip_sample = clip_sample
        self.scaling_factor = float(scaling_factor)
        self._embeddings: dict[str, np.ndarray] = {}
        self._encode = eqx.filter_jit(lambda enc, ids: enc(ids).astype(jnp.float32))
        if self.text_encoder_residency != "device":
            self.encode("")  # the null prompt, always needed, while the encoder is at hand
            if self.text_encoder_residency == "host":
                self._text_encoder_host = jax.device_get(self._text_encoder)
            self._text_encoder = None

    @classmethod
    def from_pretrained(cls, path: str | os.PathLike = DEFAULT_MODEL, *, devices=None,
                        dtype=None, size: int | None | str = "native", steps: int = DDIM_STEPS,
                        batch: int | None = None, **memory) -> "JaxIP2PEditor":
        """Load a local diffusers folder (or a Hub id in the local cache) into JAX, no torch.

        ``path`` as :func:`jaxedit.editors.diffusion.resolve_weights`; the scheduler config is
        read as Stable Diffusion 1.x's DDIM (:func:`jaxedit.editors.diffusion.ddim_settings`).
        Each tensor is cast to ``dtype`` as it is read (a bfloat16 load never holds the
        float32 networks). ``memory``: the constructor's ``attention_chunk``, ``vae_chunk``,
        ``text_encoder_residency``; the text encoder is reloaded from ``path`` when released.
        ``size`` "native" (the default): the folder's own, as diffusers defaults to it
        (:func:`jaxedit.editors.bundled.native_size`: 64 px for the bundled model, 512 for SD).
        """
        from ..models import load_ip2p
        from .bundled import native_size, recommended_guidance
        from .diffusion import ddim_settings, resolve_weights

        root = resolve_weights(path)
        size = native_size(root) if size == "native" else size
        devices = list(devices) if devices else [jax.devices()[0]]
        name = _float_dtype_name(dtype) if dtype is not None else default_dtype(devices[0])
        models = load_ip2p(root, dtype=jnp.dtype(name))
        settings = ddim_settings(root / "scheduler", models.scheduler.alphas_cumprod)
        editor = cls(models.unet, models.vae, models.text_encoder, models.tokenizer.ids,
                     DiffusionSchedule(np.asarray(models.scheduler.alphas_cumprod),
                                       settings["final_alpha"]),
                     prediction_type=str(models.scheduler.prediction_type),
                     clip_sample=settings["clip_sample"],
                     scaling_factor=float(models.vae.scaling_factor), devices=devices,
                     size=size, steps=steps, source=str(root), batch=batch,
                     guidance=recommended_guidance(root),
                     load_text_encoder=functools.partial(load_text_encoder, root,
                                                         jnp.dtype(name)), **memory)
        del models  # the editor holds the networks (on its devices) and no second copy
        log.info("InstructPix2Pix (JAX) loaded from %s on %s (%s), size %s, %d DDIM steps, "
                 "batches of %d, guidance %s", root, editor.devices, editor.dtype, size, steps,
                 editor.batch, editor.guidance)
        return editor

    @classmethod
    def bundled(cls, *, devices=None, steps: int = DDIM_STEPS, **kwargs) -> "JaxIP2PEditor":
        """The small InstructPix2Pix shipped in the package
        (:func:`jaxedit.editors.bundled_editor`) at the size it was trained at;
        ``devices``, ``steps`` and ``kwargs`` as :meth:`from_pretrained`."""
        from .bundled import bundled_editor, native_size

        folder = bundled_editor()
        return cls.from_pretrained(folder, devices=devices, size=native_size(folder),
                                   steps=steps, **kwargs)

    @property
    def calls_side_by_side(self) -> int:
        """Edit calls :func:`jaxedit.editors.edit_views` makes at once: on one CPU device, one
        per core (up to :data:`CPU_CALLS`); else 1 (a batch fills an accelerator, and several
        devices share one call). XLA runs the bundled editor's program on about one core of
        a CPU: 16 single-view edits took 1.67 s one after another and 0.95 s two at a time
        on a 2-core CPU (three or four at a time: the same)."""
        if len(self.devices) > 1 or self.devices[0].platform != "cpu":
            return 1
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
        return max(1, min(int(cores or 1), CPU_CALLS))

    def __repr__(self):
        return (f"JaxIP2PEditor({self.source!r}, devices={self.devices}, dtype={self.dtype}, "
                f"size={self.size}, steps={self.steps}, batch={self.batch})")

    def config(self, guidance: tuple[float, float] | None = None) -> EditConfig:
        """The compiled edit's static settings at ``guidance`` (None: :attr:`guidance`)."""
        return EditConfig(steps=self.steps, prediction_type=self.prediction_type,
                          clip_sample=self.clip_sample, scaling_factor=self.scaling_factor,
                          dtype=self.dtype, guidance=editor_guidance(self, guidance),
                          vae_chunk=self.vae_chunk)

    # -- embeddings -----------------------------------------------------------------------

    def encode(self, prompt: str) -> np.ndarray:
        """CLIP text embedding E(prompt): NumPy float32 [77, D]; E("") is the null embedding."""
        check_prompt(prompt)
        if prompt not in self._embeddings:
            ids = jnp.asarray(np.asarray(self.tokenize([prompt]), np.int32))
            encoder = self.text_encoder  # a released one is fetched for this prompt only
            hidden = self._encode(encoder, jax.device_put(ids, self.replicated))
            self._embeddings[prompt] = np.asarray(hidden[0], np.float32)
            del encoder  # a released encoder's device copy goes with it
        return self._embeddings[prompt].copy()

    def _embedding(self, embedding) -> jax.Array:
        null = self.encode("")
        e = embedding if isinstance(embedding, jax.Array) else np.asarray(embedding, np.float32)
        if tuple(e.shape[-2:]) != null.shape or e.ndim not in (2, 3):
            raise DataError("embedding", f"expected shape {null.shape} or [B, *{null.shape}] "
                            f"(from encode), got {tuple(e.shape)}")
        return e

    @property
    def text_encoder(self):
        """The text encoder on the editor's devices. Once released
        (``text_encoder_residency`` "host" or "reload") each access uploads the host copy or
        reloads it, and the editor keeps no reference: the caller's goes when it is done."""
        if self._text_encoder is not None:
            return self._text_encoder
        source = (self._text_encoder_host if self.text_encoder_residency == "host"
                  else self._load_text_encoder())
        return jax.device_put(source, self.replicated)

    # -- the edit -------------------------------------------------------------------------

    def model_hw(self, height: int, width: int) -> tuple[int, int]:
        return model_size(height, width, self.size, self.latent_factor)

    def edit_many(self, images, originals, embeddings, keys: jax.Array, *,
                  timestep_range: tuple[float, float] = (0.02, 0.98),
                  guidance: tuple[float, float] | None = None) -> jax.Array:
        """Edit B views in one call: float32 [B, H, W, 3] on the editor's devices.

        ``images``, ``originals``: [B, H, W, 3]; ``embeddings``: [B, 77, D] or one [77, D];
        ``keys``: B typed keys (or raw uint32 [B, 2]). The batch is padded (repeats of the
        last view, dropped from the result) to :func:`padded_batch`'s size, a power of two
        and a multiple of the devices, over which it is sharded.
        """
        images = _as_batch(images, "image", 4)
        originals = _as_batch(originals, "original", 4)
        if images.shape != originals.shape:
            raise DataError("original", f"shape {tuple(originals.shape)} differs from the "
                            f"image's {tuple(images.shape)}")
        keys = keys if jnp.issubdtype(keys.dtype, jax.dtypes.prng_key) else \
            jax.random.wrap_key_data(jnp.asarray(keys, jnp.uint32))
        keys = keys.reshape(-1)
        b = images.shape[0]
        if keys.shape[0] != b:
            raise DataError("keys", f"{keys.shape[0]} keys for {b} views")
        emb = self._embedding(embeddings)
        if emb.ndim == 3 and emb.shape[0] != b:
            raise DataError("embedding", f"{emb.shape[0]} embeddings for {b} views")
        t_bounds = np.asarray(timestep_bounds(timestep_range, self.num_train_timesteps), np.int32)
        pad = padded_batch(b, len(self.devices)) - b
        # The images' buffer is donated to the output, so it must be a copy made here, never
        # the caller's own device array (copied when nothing else made one). One program for
        # every caller: a second, non-donating one would be a second compile of the UNet.
        copied = not isinstance(images, jax.Array) or bool(pad) or images.dtype != jnp.float32
        images = images.astype(jnp.float32) if copied else jnp.copy(images)
        batched = [images, originals, keys] + ([emb] if emb.ndim == 3 else [])
        if pad:  # repeat the last view; its copies are dropped below
            batched = [jnp.concatenate([x, jnp.repeat(x[-1:], pad, 0)]) for x in batched]
        batched = [jax.device_put(x, self.by_view) for x in batched]
        if emb.ndim == 2:
            batched.append(jax.device_put(emb, self.replicated))
        images, originals, keys, emb = batched
        null = jax.device_put(self.encode(""), self.replicated)
        kept = (self.nets, originals, emb, null, keys, jax.device_put(t_bounds, self.replicated),
                self.schedule)
        cfg, hw = self.config(guidance), self.model_hw(*images.shape[1:3])
        out = edit_batch_donating_jit(kept, images, cfg, hw)
        return out[:b] if pad else out

    def edit(self, image, original, embedding, key: jax.Array, *,
             timestep_range: tuple[float, float] = (0.02, 0.98),
             guidance: tuple[float, float] | None = None) -> jax.Array:
        """Edit one view: float32 [H, W, 3] in [0, 1] (a JAX array on the editor's device)."""
        image = _as_batch(image, "image", 3 + 1)
        if image.shape[0] != 1:
            raise DataError("image", f"expected one image [H, W, 3], got {tuple(image.shape)}")
        key = key if jnp.issubdtype(key.dtype, jax.dtypes.prng_key) else \
            jax.random.wrap_key_data(jnp.asarray(key, jnp.uint32))
        return self.edit_many(image, original, embedding, key.reshape(1),
                              timestep_range=timestep_range, guidance=guidance)[0]

    def relevance(self, image, original, embedding, key: jax.Array, *,
                  timestep_range: tuple[float, float] = (0.02, 0.98),
                  guidance: tuple[float, float] | None = None, draws: int = RELEVANCE_DRAWS,
                  sigma: float = 1.5, threshold: float = 0.3) -> jax.Array:
        """Where ``embedding`` changes the view, float32 [H, W] in {0, 1} (the Editor
        protocol's relevance, "Watch Your Steps", ICCV 2023).

        ``image``, ``original``: [H, W, 3] in [0, 1]; ``embedding``: [77, D] (e.g. e(r));
        ``key``: one typed key (timesteps and noises). :func:`noise_difference` on one
        batched UNet call, resized to the view and put through
        :func:`jaxedit.editors.masks.relevance_mask`.
        """
        image = jnp.asarray(image, jnp.float32)
        original = jnp.asarray(original, jnp.float32)
        if image.ndim != 3 or image.shape != original.shape:
            raise DataError("image", f"need [H, W, 3] image and original of one shape, got "
                            f"{tuple(image.shape)} and {tuple(original.shape)}")
        emb = self._embedding(embedding)
        if emb.ndim != 2:
            raise DataError("embedding", f"need one [77, D] embedding, got {tuple(emb.shape)}")
        key = key if jnp.issubdtype(key.dtype, jax.dtypes.prng_key) else \
            jax.random.wrap_key_data(jnp.asarray(key, jnp.uint32))
        height, width = image.shape[:2]
        t_bounds = jnp.asarray(np.asarray(timestep_bounds(timestep_range,
                                                          self.num_train_timesteps), np.int32))
        diff = noise_difference_jit(self.nets, image[None], original[None], jnp.asarray(emb),
                                    jnp.asarray(self.encode("")), key.reshape(1), t_bounds,
                                    self.schedule, self.config(guidance),
                                    self.model_hw(height, width), draws)
        diff = jax.image.resize(diff[..., None], (1, height, width, 1), "linear")[0, ..., 0]
        return relevance_mask(diff, sigma=sigma, threshold=threshold)

    def describe(self) -> dict:
        """What a run log / report records about this editor."""
        return {"editor": self.name, "framework": "jax", "weights": self.source,
                "devices": [str(d) for d in self.devices], "dtype": self.dtype,
                "size": self.size, "steps": self.steps, "batch": self.batch,
                "guidance": list(self.guidance), "clip_sample": self.clip_sample,
                "prediction_type": self.prediction_type,
                "attention_chunk": self.attention_chunk, "vae_chunk": self.vae_chunk,
                "text_encoder_residency": self.text_encoder_residency}


#: Views per device in one edit on an accelerator (512 px, bf16: a few GB of activations
#: with the three guidance branches; one view leaves an H100 mostly idle).
ACCELERATOR_BATCH = 8
#: Most edit calls made at once on a CPU (:attr:`JaxIP2PEditor.calls_side_by_side`).
CPU_CALLS = 8


def padded_batch(views: int, devices: int) -> int:
    """The batch a call of ``views`` views runs at: the next power of two, then a multiple of
    the devices. A sweep's remainder (20 views in batches of 8 end with 4) or a single view
    would otherwise be a UNet program of its own, about 45 s of compiling at SD 1.5's size;
    so at most log2(batch) + 1 programs, for at most twice the work of a rare short call."""
    size = 1 << max(int(views) - 1, 0).bit_length()
    return -(-size // devices) * devices


def default_batch(devices: Sequence[jax.Device]) -> int:
    """Views per :meth:`JaxIP2PEditor.edit_many` call: :data:`ACCELERATOR_BATCH` per
    accelerator; one per CPU device (a batch there costs memory and saves little time)."""
    per_device = 1 if devices[0].platform == "cpu" else ACCELERATOR_BATCH
    return per_device * len(devices)


def _float_dtype(module) -> str:
    """The dtype of a module's floating point parameters (float32 if it has none)."""
    leaves = [x for x in jax.tree_util.tree_leaves(eqx.filter(module, eqx.is_array))
              if jnp.issubdtype(x.dtype, jnp.floating)]
    return jnp.dtype(leaves[0].dtype).name if leaves else "float32"


def load_text_encoder(root: str | os.PathLike, dtype=jnp.float32):
    """The text encoder of a diffusers folder, alone (a released encoder's reload)."""
    from pathlib import Path

    from ..models import CLIPTextEncoder, load_module

    return load_module(Path(root) / "text_encoder", CLIPTextEncoder.from_config,
                       prefix=CLIPTextEncoder.CHECKPOINT_PREFIX, dtype=dtype)


#: The CLI's factory (``--editor ip2p --ip2p-weights DIR``):
#: :meth:`JaxIP2PEditor.from_pretrained` itself, so its defaults have one owner.
load_editor = JaxIP2PEditor.from_pretrained
load_bundled = JaxIP2PEditor.bundled

