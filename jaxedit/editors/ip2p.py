"""InstructPix2Pix in torch (extra ``jaxedit[ip2p]``): the reference editor, IN2N's edit.

``encode`` gives NumPy float32 [77, D] and ``edit`` NumPy float32 [H, W, 3], so the framework
stays free of torch; T comes from the JAX key, both noises from a 63-bit seed of a CPU
``torch.Generator``, the same on every device.
"""

from __future__ import annotations

import logging
import os
import warnings
from pathlib import Path

try:
    import torch
    import torch.nn.functional as F
    from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
    from transformers import CLIPTextModel, CLIPTokenizer
except ImportError as e:  # pragma: no cover - exercised by a test that hides torch
    raise ImportError(
        f"jaxedit.editors.ip2p needs the optional extra 'ip2p' (torch, diffusers, transformers, "
        f"safetensors); {e.name or 'a dependency'} is missing. Install it with "
        f"`pip install torch==2.13.0` (CPU) or a CUDA build of torch, then "
        f"`pip install 'jaxedit[ip2p]'`.") from e

import jax
import numpy as np

from ..errors import DataError
from .base import editor_guidance
from .bundled import recommended_guidance
from .diffusion import (DDIM_STEPS, DEFAULT_MODEL, HOW_TO_GET, IP2P_GUIDANCE,  # noqa: F401
                        check_guidance, check_timestep_range, ddim_overrides, ddim_step, draw_timestep,
                        dtype_name, dual_guidance, model_size, resolve_weights,
                        timestep_schedule)

log = logging.getLogger(__name__)

__all__ = ["InstructPix2PixEditor", "load_editor", "DEFAULT_MODEL", "HOW_TO_GET", "ddim_step",
           "draw_timestep", "dual_guidance", "model_size", "resolve_weights", "seed_from_key",
           "timestep_schedule"]


def seed_from_key(key: jax.Array) -> tuple[jax.Array, int]:
    """Split a JAX key into (key for the timestep draw, 63-bit torch seed)."""
    k_t, k_n = jax.random.split(key)
    hi, lo = (int(v) for v in np.asarray(jax.random.bits(k_n, (2,), np.uint32)))
    return k_t, ((hi << 32) | lo) & ((1 << 63) - 1)


def _load(root: Path, sub: str, loader):
    try:
        return loader()
    except (OSError, ValueError, EnvironmentError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise DataError(root / sub, f"cannot load ({first}); needs {HOW_TO_GET}") from None


def _from_jax(x: jax.Array) -> "torch.Tensor":
    """JAX array -> torch tensor, zero-copy by DLPack where this torch takes it."""
    try:
        return torch.from_dlpack(x)
    except (RuntimeError, TypeError, BufferError, ValueError):
        return torch.from_numpy(np.array(x))


def _dtype(dtype):
    """None, a torch dtype, or its name ("float16", "fp16", "bfloat16", "float32")."""
    if dtype is None or isinstance(dtype, torch.dtype):
        return dtype
    value = getattr(torch, dtype_name(dtype), None)
    if not isinstance(value, torch.dtype) or not value.is_floating_point:
        raise DataError("dtype", f"unknown floating point dtype {dtype!r}")
    return value


def _default_device() -> str:
    return "cuda:0" if torch.cuda.is_available() else "cpu"


class InstructPix2PixEditor:
    """InstructPix2Pix implementing :class:`jaxedit.editors.Editor` (see the module docstring)."""

    name = "ip2p"

    def __init__(self, unet, vae, text_encoder, tokenizer, scheduler, *, device=None, dtype=None,
                 size: int | None = 512, steps: int = DDIM_STEPS, source: str = "",
                 guidance: tuple[float, float] = IP2P_GUIDANCE):
        self.device = torch.device(device or _default_device())
        #: (text, image) scales of an edit that names none (from_pretrained: the folder's).
        self.guidance = check_guidance(guidance)
        on_cpu = self.device.type == "cpu"
        self.dtype = _dtype(dtype) or (torch.float32 if on_cpu else torch.float16)
        if unet.config.in_channels != 8:
            raise DataError(f"{source or 'unet'}", f"UNet has in_channels="
                            f"{unet.config.in_channels}, not 8: not an InstructPix2Pix model; "
                            f"needs {HOW_TO_GET}")
        self.unet = self._place(unet)
        self.vae = self._place(vae)
        self.text_encoder = self._place(text_encoder)
        self.tokenizer = tokenizer
        self.scheduler = scheduler
        self.vae_factor = 2 ** (len(self.vae.config.block_out_channels) - 1)
        if size is not None and size % self.vae_factor:
            raise DataError("size", f"model size {size} is not a multiple of {self.vae_factor}")
        self.size = size
        self.steps = int(steps)
        self.source = source
        self.scaling_factor = float(getattr(self.vae.config, "scaling_factor", 0.18215))
        self.alphas_cumprod = scheduler.alphas_cumprod.double().cpu().numpy()
        self.final_alpha = float(scheduler.final_alpha_cumprod)
        self.num_train_timesteps = int(scheduler.config.num_train_timesteps)
        self.prediction_type = scheduler.config.prediction_type
        if getattr(scheduler.config, "thresholding", False):
            raise DataError(f"{source or 'scheduler'}", "dynamic thresholding schedulers are not "
                            "supported by the SDEdit loop")
        self.clip_sample = (float(scheduler.config.clip_sample_range)
                            if getattr(scheduler.config, "clip_sample", False) else None)
        self._embeddings: dict[str, np.ndarray] = {}

    def _place(self, module):
        # Cast only when needed: diffusers warns on every dtype-carrying .to() call.
        if module.dtype != self.dtype:
            module = module.to(dtype=self.dtype)
        return module.to(self.device).eval().requires_grad_(False)

    @classmethod
    def from_pretrained(cls, path: str | os.PathLike = DEFAULT_MODEL, *, device=None, dtype=None,
                        size: int | None = 512, steps: int = DDIM_STEPS,
                        variant: str | None = None):
        """Load a diffusers folder (unet/ vae/ text_encoder/ tokenizer/ scheduler/) or cached
        Hub id, no network. ``device``: default ``cuda:0`` if available, else ``cpu``; ``dtype``:
        default fp16 off the CPU; ``size``: model side, a multiple of ``vae_factor`` (None: the
        view's); ``steps``: DDIM steps; ``variant``: diffusers weight variant."""
        root = resolve_weights(path)
        device = torch.device(device or _default_device())
        dtype = _dtype(dtype) or (torch.float32 if device.type == "cpu" else torch.float16)
        kw = {"local_files_only": True}
        unet = _load(root, "unet", lambda: UNet2DConditionModel.from_pretrained(
            root, subfolder="unet", variant=variant, torch_dtype=dtype, **kw))
        vae = _load(root, "vae", lambda: AutoencoderKL.from_pretrained(
            root, subfolder="vae", variant=variant, torch_dtype=dtype, **kw))
        text_encoder = _load(root, "text_encoder", lambda: CLIPTextModel.from_pretrained(
            root, subfolder="text_encoder", variant=variant, **kw))
        tokenizer = _load(root, "tokenizer", lambda: CLIPTokenizer.from_pretrained(
            root, subfolder="tokenizer", **kw))
        scheduler = _load(root, "scheduler", lambda: DDIMScheduler.from_pretrained(
            root, subfolder="scheduler", **ddim_overrides(root / "scheduler"), **kw))
        editor = cls(unet, vae, text_encoder, tokenizer, scheduler, device=device, dtype=dtype,
                     size=size, steps=steps, source=str(root),
                     guidance=recommended_guidance(root))
        log.info("InstructPix2Pix loaded from %s on %s (%s), size %s, %d DDIM steps, "
                 "guidance %s", root, editor.device, editor.dtype, size, steps, editor.guidance)
        return editor

    def __repr__(self):
        return (f"InstructPix2PixEditor({self.source!r}, device={self.device}, dtype={self.dtype}, "
                f"size={self.size}, steps={self.steps})")

    @torch.inference_mode()
    def encode(self, prompt: str) -> np.ndarray:
        """CLIP text embedding E(prompt): NumPy float32 [77, D]; E("") is the null embedding."""
        if not isinstance(prompt, str):
            raise DataError("prompt", f"must be a string, got {type(prompt).__name__}")
        if prompt not in self._embeddings:
            n = self.tokenizer.model_max_length
            ids = self.tokenizer(prompt, padding="max_length", max_length=n, truncation=True,
                                 return_tensors="pt").input_ids
            if len(self.tokenizer(prompt).input_ids) > n:
                log.warning("prompt truncated to %d CLIP tokens: %r", n, prompt)
            hidden = self.text_encoder(ids.to(self.device))[0][0]
            self._embeddings[prompt] = hidden.float().cpu().numpy()
        return self._embeddings[prompt].copy()

    def _image(self, image, field: str) -> "torch.Tensor":
        """float [H, W, 3] (NumPy, JAX, torch) -> float32 [1, 3, H, W] on the editor's device."""
        if isinstance(image, torch.Tensor):
            t = image
        elif isinstance(image, jax.Array):
            t = _from_jax(image)
        else:
            array = np.ascontiguousarray(image)
            with warnings.catch_warnings():
                # Read-only arrays (e.g. from JAX) are shared, not copied; nothing writes to them.
                warnings.simplefilter("ignore", UserWarning)
                t = torch.from_numpy(array)
        if t.ndim != 3 or t.shape[-1] != 3:
            raise DataError(field, f"expected an image [H, W, 3], got shape {tuple(t.shape)}")
        if not torch.is_floating_point(t):
            raise DataError(field, f"expected float values in [0, 1], got {t.dtype}")
        t = t.to(self.device, torch.float32, non_blocking=True)
        return t.permute(2, 0, 1)[None]

    def _embedding(self, embedding) -> "torch.Tensor":
        if isinstance(embedding, torch.Tensor):
            e = embedding
        elif isinstance(embedding, jax.Array):
            e = _from_jax(embedding)
        else:
            e = torch.from_numpy(np.ascontiguousarray(embedding, dtype=np.float32))
        null = self.encode("")
        if tuple(e.shape) != null.shape:
            raise DataError("embedding", f"expected shape {null.shape} (from encode), got "
                            f"{tuple(e.shape)}")
        return torch.stack([e.to(self.device, self.dtype),
                            torch.from_numpy(null).to(self.device, self.dtype)])

    @staticmethod
    def _resize(x: "torch.Tensor", hw: tuple[int, int]) -> "torch.Tensor":
        if tuple(x.shape[-2:]) == tuple(hw):
            return x
        return F.interpolate(x, size=hw, mode="bilinear", align_corners=False, antialias=True)

    @torch.inference_mode()
    def edit(self, image, original, embedding, key: jax.Array, *,
             timestep_range: tuple[float, float] = (0.02, 0.98),
             guidance: tuple[float, float] | None = None) -> np.ndarray:
        """Edit one view: float32 [H, W, 3] in [0, 1] at ``image``'s size (see module docstring)."""
        check_timestep_range(timestep_range)
        hw = model_size(*self._image(image, "image").shape[-2:], self.size, self.vae_factor)
        k_t, seed = seed_from_key(key)
        t_start = draw_timestep(k_t, timestep_range, self.num_train_timesteps)
        gen = torch.Generator("cpu").manual_seed(seed)
        latent_shape = (1, 4, hw[0] // self.vae_factor, hw[1] // self.vae_factor)
        vae_noise = torch.randn(latent_shape, generator=gen)
        sde_noise = torch.randn(latent_shape, generator=gen)
        return self.edit_with_noise(image, original, embedding, t_start, vae_noise, sde_noise,
                                    guidance=guidance)

    @torch.inference_mode()
    def edit_with_noise(self, image, original, embedding, t_start: int, vae_noise, sde_noise, *,
                        guidance: tuple[float, float] | None = None) -> np.ndarray:
        """:meth:`edit` with its draws given: timestep ``t_start``,
        standard normals ``vae_noise`` and ``sde_noise`` [1, 4, h/f, w/f] at the model size."""
        guidance = editor_guidance(self, guidance)
        render = self._image(image, "image")
        orig = self._image(original, "original")
        height, width = render.shape[-2:]
        hw = model_size(height, width, self.size, self.vae_factor)
        pair = torch.cat([self._resize(render, hw), self._resize(orig, hw)]) * 2 - 1

        # One VAE pass for both images: posterior sample of the render, mode of the original.
        posterior = self.vae.encode(pair.to(self.dtype)).latent_dist
        mean, std = posterior.mean.float(), posterior.std.float()
        latents = (mean[:1] + std[:1] * torch.as_tensor(vae_noise).to(self.device)
                   ) * self.scaling_factor
        cond = mean[1:]
        cond3 = torch.cat([cond, cond, torch.zeros_like(cond)]).to(self.dtype)

        e = self._embedding(embedding)
        emb3 = torch.stack([e[0], e[1], e[1]])       # text+image, image only, unconditional

        a = self.alphas_cumprod
        noise = torch.as_tensor(sde_noise).to(self.device)
        latents = a[t_start] ** 0.5 * latents + (1 - a[t_start]) ** 0.5 * noise

        ts = timestep_schedule(t_start, self.steps)
        for i, t in enumerate(ts):
            inp = torch.cat([torch.cat([latents] * 3).to(self.dtype), cond3], dim=1)
            out = self.unet(inp, t, encoder_hidden_states=emb3).sample.float()
            eps = dual_guidance(out, *guidance)
            a_prev = a[ts[i + 1]] if i + 1 < len(ts) else self.final_alpha
            latents = ddim_step(latents, eps, a[t], a_prev, self.prediction_type, self.clip_sample)

        decoded = self.vae.decode((latents / self.scaling_factor).to(self.dtype)).sample.float()
        decoded = ((decoded + 1) / 2).clamp(0, 1)
        result = self._resize(decoded, (height, width)).clamp(0, 1)
        return result[0].permute(1, 2, 0).contiguous().cpu().numpy()

    def describe(self) -> dict:
        """What a run log / report records about this editor."""
        return {"editor": self.name, "weights": self.source, "device": str(self.device),
                "dtype": str(self.dtype).replace("torch.", ""), "size": self.size,
                "steps": self.steps, "guidance": list(self.guidance),
                "scheduler": type(self.scheduler).__name__,
                "clip_sample": self.clip_sample, "prediction_type": self.prediction_type,
                "unet_in_channels": int(self.unet.config.in_channels)}



#: The CLI's factory: :meth:`InstructPix2PixEditor.from_pretrained`, so its defaults have one owner.
load_editor = InstructPix2PixEditor.from_pretrained
