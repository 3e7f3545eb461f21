"""InstructPix2Pix in JAX: the torch reference's edit (:mod:`jaxedit.editors.ip2p`) as one pure jit.

Batched with a traced T per view (drawn as the torch editor draws it), sharded along ``views``;
networks in bfloat16 on accelerators (no fp16 VAE overflow), float32 on the CPU.
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

__all__ = ["DiffusionSchedule", "SamplerConfig", "JaxIP2PEditor", "Networks", "decode",
           "denoise", "draw_noise", "edit_batch", "edit_with_noise", "encode_latents",
           "default_batch", "in_chunks", "latent_factor", "load_bundled", "load_editor",
           "load_text_encoder", "resize_images"]

#: Name of the mesh axis a batch of views is sharded along.
VIEWS = "views"


class Networks(eqx.Module):
    """The 8-channel UNet, ``(sample [B, h, w, 8], t [B], context [B, 77, D]) -> eps
    [B, h, w, 4]``, and the VAE, ``encode(x [B, H, W, 3] in [-1, 1]) -> (mean, logvar)``."""

    unet: Any
    vae: Any


class DiffusionSchedule(NamedTuple):
    """alphas_cumprod float32 [N]; final_alpha, the alpha the last DDIM step lands on."""

    alphas_cumprod: jax.Array
    final_alpha: jax.Array


@dataclasses.dataclass(frozen=True)
class SamplerConfig:
    """Static settings of a compiled edit (hashable: a change recompiles): DDIM ``steps``;
    ``prediction_type`` "epsilon", "v_prediction" or "sample"; ``clip_sample`` (None: no x0
    clamp); the VAE's ``scaling_factor``; the networks' ``dtype`` name; (text, image)
    ``guidance``; ``vae_chunk`` views per VAE pass (None: all)."""

    steps: int = DDIM_STEPS
    prediction_type: str = "epsilon"
    clip_sample: float | None = None
    scaling_factor: float = 0.18215
    dtype: str = "float32"
    guidance: tuple[float, float] = IP2P_GUIDANCE
    vae_chunk: int | None = None


def latent_factor(vae) -> int:
    """Static image side / latent side f of the VAE: its ``downsample_factor``, else 8."""
    return int(getattr(vae, "downsample_factor", 8))


def resize_images(images: jax.Array, hw: tuple[int, int]) -> jax.Array:
    """[B, H, W, C] -> [B, h, w, C], bilinear, antialiased when shrinking (as torch's)."""
    if tuple(images.shape[1:3]) == tuple(hw):
        return images
    return jax.image.resize(images, (images.shape[0], *hw, images.shape[3]), method="linear",
                            antialias=True)


def in_chunks(fn: Callable, x: jax.Array, chunk: int | None):
    """Per-example ``fn(x)`` over chunks of ``chunk`` examples by ``lax.map`` (the batch padded
    with its last example), so one chunk's temporaries are live; None: one call."""
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
                   cfg: SamplerConfig) -> tuple[jax.Array, jax.Array]:
    """(latents, cond), float32 [B, h/f, w/f, 4]: the render's scaled posterior
    sample (noise ``vae_noise``) and the original's posterior mean; images in [0, 1]."""
    b = images.shape[0]
    if cfg.vae_chunk is None or cfg.vae_chunk >= b:
        pair = jnp.concatenate([images, originals]) * 2 - 1
        mean, logvar = vae.encode(pair.astype(cfg.dtype))
    else:
        pairs = (jnp.stack([images, originals], 1) * 2 - 1).astype(cfg.dtype)
        flat = lambda v: v.reshape(-1, *v.shape[2:])  # noqa: E731
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
            cfg: SamplerConfig) -> jax.Array:
    """SDEdit to ``t_start`` (int32 [B]) then DDIM back: float32 [B, h, w, 4]. ``latents``,
    ``cond``, ``sde_noise``: [B, h, w, 4]; ``embeddings``: [B, 77, D]; ``null``: [77, D]."""
    a = schedule.alphas_cumprod
    b = latents.shape[0]
    expand = lambda v: v[:, None, None, None]  # noqa: E731
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


def decode(vae, latents: jax.Array, cfg: SamplerConfig) -> jax.Array:
    """Latents [B, h, w, 4] -> float32 [B, f h, f w, 3] in [0, 1]."""
    decoded = in_chunks(vae.decode, (latents / cfg.scaling_factor).astype(cfg.dtype),
                        cfg.vae_chunk).astype(jnp.float32)
    return jnp.clip((decoded + 1) / 2, 0, 1)


def edit_with_noise(nets: Networks, images: jax.Array, originals: jax.Array,
                    embeddings: jax.Array, null: jax.Array, t_start: jax.Array,
                    vae_noise: jax.Array, sde_noise: jax.Array, schedule: DiffusionSchedule,
                    cfg: SamplerConfig) -> jax.Array:
    """The whole edit with its random draws given (pure): float32 [B, H, W, 3] in [0, 1].

    ``images``, ``originals``: float [B, H, W, 3] in [0, 1]; ``embeddings``: [B, 77, D] or
    [77, D]; ``null``: [77, D], E(""); ``t_start``: int32 [B]; ``vae_noise``, ``sde_noise``:
    float32 [B, h/f, w/f, 4], (h, w) the model size.
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
    """(t_start int32 [B], vae_noise, sde_noise float32 [B, h, w, 4]) from keys [B];
    ``t_bounds``: int32 [2], T's inclusive range (:func:`timestep_bounds`)."""
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
               schedule: DiffusionSchedule, cfg: SamplerConfig, model_hw: tuple[int, int]):
    """Edit B views, float32 [B, H, W, 3], drawing from typed ``keys`` [B]; ``model_hw``: the
    networks' (h, w), multiples of :func:`latent_factor` (:func:`model_size`)."""
    f = latent_factor(nets.vae)
    t_start, vae_noise, sde_noise = draw_noise(keys, t_bounds, (model_hw[0] // f,
                                                                model_hw[1] // f))
    return edit_with_noise(nets, images, originals, embeddings, null, t_start, vae_noise,
                           sde_noise, schedule, cfg)


#: Compiled: everything but the networks' arrays, the inputs and the schedule is static.
edit_with_noise_jit = eqx.filter_jit(edit_with_noise)


def _edit_batch_into(kept: tuple, images: jax.Array, cfg: SamplerConfig, model_hw: tuple[int, int]):
    nets, originals, embeddings, null, keys, t_bounds, schedule = kept
    return edit_batch(nets, images, originals, embeddings, null, keys, t_bounds, schedule, cfg,
                      model_hw)


#: :func:`edit_batch` jitted with ``images`` donated: pass a buffer the caller no longer holds.
edit_batch_donating_jit = eqx.filter_jit(_edit_batch_into, donate="all-except-first")


#: Noise draws (each with its own timestep) averaged per view by ``relevance``.
RELEVANCE_DRAWS = 4


def noise_difference(nets, images, originals, embedding, null, keys, t_bounds, schedule,
                     cfg, model_hw: tuple[int, int], draws: int = RELEVANCE_DRAWS) -> jax.Array:
    """Mean over channels and draws of |eps(x_t, c, e) - eps(x_t, c, E(""))|: float32
    [B, h/f, w/f]. ``images``, ``originals``: float [B, H, W, 3] in [0, 1]; ``embedding``,
    ``null``: [77, D]; ``keys``: B typed keys, each drawing ``draws`` timesteps and noises."""
    b = images.shape[0]
    f = latent_factor(nets.vae)
    lat_hw = (model_hw[0] // f, model_hw[1] // f)
    sub = jax.vmap(lambda k: jax.random.split(k, draws))(keys).reshape(-1)  # [B * draws]
    t, vae_noise, sde_noise = draw_noise(sub, t_bounds, lat_hw)
    rep = lambda x: jnp.repeat(x, draws, 0)  # noqa: E731
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


def check_prompt(prompt) -> str:
    """``prompt`` if it is a valid UTF-8 string, else DataError naming the bad
    character's position (a command line's stray bytes arrive as lone surrogates)."""
    if not isinstance(prompt, str):
        raise DataError("prompt", f"must be a string, got {type(prompt).__name__}")
    try:
        prompt.encode("utf-8")
    except UnicodeEncodeError as e:
        raise DataError("prompt", f"is not valid UTF-8 text (a stray byte "
                                  f"{os.fsencode(prompt[e.start])!r} at character {e.start}); "
                                  f"give the instruction as UTF-8") from None
    return prompt


#: Feature maps of the UNet's first level held at once per sample (:func:`edit_memory_at_least`).
HELD_MAPS = 8


def edit_memory_at_least(size: int, steps: int, batch: int, factor: int, width: int,
                         itemsize: int) -> float:
    """Lower bound on the bytes one batch of edits holds: timestep tables, the
    images at model size, and :data:`HELD_MAPS` first-level UNet maps per guidance branch."""
    latent = (size / factor) ** 2
    return (3 * batch * steps * 4 + 4 * batch * size * size * 3 * 4
            + 3 * batch * latent * width * itemsize * HELD_MAPS)


def first_level_width(unet) -> int:
    """Channels of the UNet's ``conv_in`` output; 0 for a network without one."""
    conv_in = getattr(unet, "conv_in", None)
    return 0 if conv_in is None else int(conv_in.weight.shape[-1])


def check_edit_sizes(size: int | None, steps: int, batch: int, timesteps: int, factor: int,
                     width: int, itemsize: int) -> None:
    """Raise DataError for more DDIM steps than schedule timesteps, or for an edit
    that cannot fit in free memory (:func:`jaxedit.memory.require_memory`; ``size`` None skips)."""
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


#: Queries per attention chunk (:class:`JaxIP2PEditor`'s ``attention_chunk``).
ATTENTION_CHUNK = 1024
#: Views per VAE pass (:attr:`SamplerConfig.vae_chunk`).
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
    """InstructPix2Pix in JAX, a :class:`jaxedit.editors.Editor`.

    Args:
      unet, vae, text_encoder: equinox modules; the UNet's dtype is the compute dtype.
      tokenize: ``list[str] -> int32 [B, 77]`` CLIP token ids.
      schedule, prediction_type, clip_sample: the DDIM update's.
      devices: default the first JAX device; several shard batches.
      size: model resolution of the longer side (None: the view's own); steps: DDIM steps.
      batch: most views per :meth:`edit_many` call; guidance: default (text, image) scales.
      attention_chunk, vae_chunk: queries per attention chunk, views per VAE pass (None: all).
      text_encoder_residency: where the text encoder lives after E("") is encoded ("device",
        "host", "reload" or "auto"); load_text_encoder: ``() -> module``, for "reload".
    Raises:
      DataError: a bad setting, or an edit too large for free memory.
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
        #: image side / latent side of the VAE (:func:`latent_factor`).
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
        """Load a local diffusers folder (or cached Hub id), cast to ``dtype`` as read; ``size``
        "native": :func:`.bundled.native_size`; ``memory``: the constructor's keywords."""
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
        del models
        log.info("InstructPix2Pix (JAX) loaded from %s on %s (%s), size %s, %d DDIM steps, "
                 "batches of %d, guidance %s", root, editor.devices, editor.dtype, size, steps,
                 editor.batch, editor.guidance)
        return editor

    @classmethod
    def bundled(cls, *, devices=None, steps: int = DDIM_STEPS, **kwargs) -> "JaxIP2PEditor":
        """The bundled InstructPix2Pix at its native size; arguments as :meth:`from_pretrained`."""
        from .bundled import bundled_editor, native_size

        folder = bundled_editor()
        return cls.from_pretrained(folder, devices=devices, size=native_size(folder),
                                   steps=steps, **kwargs)

    @property
    def calls_side_by_side(self) -> int:
        """Edit calls :func:`jaxedit.editors.edit_views` makes at once: one per core (up to
        :data:`CPU_CALLS`) on one CPU device, where an edit uses about one core; else 1."""
        if len(self.devices) > 1 or self.devices[0].platform != "cpu":
            return 1
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
        return max(1, min(int(cores or 1), CPU_CALLS))

    def __repr__(self):
        return (f"JaxIP2PEditor({self.source!r}, devices={self.devices}, dtype={self.dtype}, "
                f"size={self.size}, steps={self.steps}, batch={self.batch})")

    def config(self, guidance: tuple[float, float] | None = None) -> SamplerConfig:
        """The :class:`SamplerConfig` at ``guidance`` (None: :attr:`guidance`)."""
        return SamplerConfig(steps=self.steps, prediction_type=self.prediction_type,
                          clip_sample=self.clip_sample, scaling_factor=self.scaling_factor,
                          dtype=self.dtype, guidance=editor_guidance(self, guidance),
                          vae_chunk=self.vae_chunk)

    def encode(self, prompt: str) -> np.ndarray:
        """CLIP text embedding E(prompt), NumPy float32 [77, D], cached per prompt."""
        check_prompt(prompt)
        if prompt not in self._embeddings:
            ids = jnp.asarray(np.asarray(self.tokenize([prompt]), np.int32))
            encoder = self.text_encoder  # a released one is fetched for this prompt only
            hidden = self._encode(encoder, jax.device_put(ids, self.replicated))
            self._embeddings[prompt] = np.asarray(hidden[0], np.float32)
            del encoder
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
        """The text encoder on the devices; once released, uploaded or reloaded per access."""
        if self._text_encoder is not None:
            return self._text_encoder
        source = (self._text_encoder_host if self.text_encoder_residency == "host"
                  else self._load_text_encoder())
        return jax.device_put(source, self.replicated)

    def model_hw(self, height: int, width: int) -> tuple[int, int]:
        return model_size(height, width, self.size, self.latent_factor)

    def edit_many(self, images, originals, embeddings, keys: jax.Array, *,
                  timestep_range: tuple[float, float] = (0.02, 0.98),
                  guidance: tuple[float, float] | None = None) -> jax.Array:
        """Edit B views: float32 [B, H, W, 3] on the editor's devices. ``embeddings``:
        [B, 77, D] or [77, D]; ``keys``: B typed keys (or uint32 [B, 2])."""
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
        # The images' buffer is donated, so it must be a copy made here; one donating
        # program for every caller (a second one would compile the UNet again).
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
        """Edit one view: float32 [H, W, 3] in [0, 1] on the editor's device."""
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
        """Where ``embedding`` changes the view [H, W, 3], float32 [H, W] in {0, 1} ("Watch Your
        Steps"): :func:`noise_difference` through :func:`.masks.relevance_mask`."""
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
        """What a run log records about this editor."""
        return {"editor": self.name, "framework": "jax", "weights": self.source,
                "devices": [str(d) for d in self.devices], "dtype": self.dtype,
                "size": self.size, "steps": self.steps, "batch": self.batch,
                "guidance": list(self.guidance), "clip_sample": self.clip_sample,
                "prediction_type": self.prediction_type,
                "attention_chunk": self.attention_chunk, "vae_chunk": self.vae_chunk,
                "text_encoder_residency": self.text_encoder_residency}


#: Views per device in one edit on an accelerator.
ACCELERATOR_BATCH = 8
#: Most edit calls made at once on a CPU (:attr:`JaxIP2PEditor.calls_side_by_side`).
CPU_CALLS = 8


def padded_batch(views: int, devices: int) -> int:
    """The batch a call of ``views`` runs at: the next power of two, rounded up to a
    multiple of ``devices``, so a handful of UNet programs serve every call."""
    size = 1 << max(int(views) - 1, 0).bit_length()
    return -(-size // devices) * devices


def default_batch(devices: Sequence[jax.Device]) -> int:
    """Views per :meth:`JaxIP2PEditor.edit_many` call: :data:`ACCELERATOR_BATCH` per
    accelerator, one per CPU device."""
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


#: The CLI's factory: :meth:`JaxIP2PEditor.from_pretrained`, so its defaults have one owner.
load_editor = JaxIP2PEditor.from_pretrained
load_bundled = JaxIP2PEditor.bundled

