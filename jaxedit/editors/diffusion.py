"""The diffusion arithmetic both InstructPix2Pix editors share (timestep draw, DDIM schedule,
model size, dual guidance, DDIM update), on torch tensors and JAX arrays alike."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import DataError
from ..models.load import HOW_TO_GET  # noqa: F401 - re-exported
from ..models.load import check_layout as resolve_weights  # noqa: F401 - re-exported

DEFAULT_MODEL = "timbrooks/instruct-pix2pix"
#: The diffusion timesteps Stable Diffusion is trained with.
NUM_TRAIN_TIMESTEPS = 1000
#: DDIM steps per edit, both editors' default (IN2N's).
DDIM_STEPS = 20
#: The short names both editors' ``dtype`` takes for float16, bfloat16 and float32.
DTYPE_ALIASES = {"fp16": "float16", "half": "float16", "fp32": "float32", "float": "float32",
                 "bf16": "bfloat16"}


def dtype_name(dtype) -> str:
    """``dtype`` with a :data:`DTYPE_ALIASES` alias spelled out ("fp16" -> "float16")."""
    return DTYPE_ALIASES.get(str(dtype), str(dtype))


def check_timestep_range(timestep_range) -> tuple[float, float]:
    lo, hi = (float(v) for v in timestep_range)
    if not (0.0 <= lo <= hi <= 1.0):
        raise DataError("timestep_range", f"must satisfy 0 <= t_min <= t_max <= 1, got {(lo, hi)}")
    return lo, hi


def timestep_bounds(timestep_range, num_train: int = NUM_TRAIN_TIMESTEPS) -> tuple[int, int]:
    """Integer bounds [t_lo, t_hi] of the draw: round(lo N), round(hi N) within [1, N - 1]."""
    lo, hi = check_timestep_range(timestep_range)
    t_lo = min(max(int(round(lo * num_train)), 1), num_train - 1)
    t_hi = min(max(int(round(hi * num_train)), t_lo), num_train - 1)
    return t_lo, t_hi


def draw_timestep(key: jax.Array, timestep_range: tuple[float, float],
                  num_train: int = NUM_TRAIN_TIMESTEPS) -> int:
    """Integer T uniform in [round(lo * N), round(hi * N)] (N = num_train), within [1, N - 1]."""
    t_lo, t_hi = timestep_bounds(timestep_range, num_train)
    return int(jax.random.randint(key, (), t_lo, t_hi + 1))


def timestep_schedule(t_start: int, steps: int) -> list[int]:
    """DDIM timesteps round(T (steps - k) / steps), k < steps, repeats and zeros dropped."""
    if steps < 1:
        raise DataError("steps", f"must be >= 1, got {steps}")
    ts = [int(round(t_start * (steps - k) / steps)) for k in range(steps)]
    return sorted({t for t in ts if t > 0}, reverse=True)


def timestep_table(t_start: jax.Array, steps: int) -> tuple[jax.Array, jax.Array, jax.Array]:
    """:func:`timestep_schedule` of traced ``t_start`` int [...] in ``steps`` static slots:
    (t, t_next, valid), each [..., steps]; the valid slots of ``t`` are the schedule, ``t_next``
    the next valid timestep (0 after the last)."""
    t_start = jnp.asarray(t_start, jnp.int32)
    # Integer arithmetic: XLA may compute a quotient as a product with 1 / steps and round
    # a half the wrong way.
    num = t_start[..., None] * (steps - jnp.arange(steps, dtype=jnp.int32))
    q, r = num // steps, num % steps
    t = q + ((2 * r > steps) | ((2 * r == steps) & (q % 2 == 1))).astype(jnp.int32)
    prev = jnp.concatenate([jnp.full(t.shape[:-1] + (1,), -1, jnp.int32), t[..., :-1]], -1)
    valid = (t > 0) & (t != prev)
    smaller = jnp.where(t[..., None, :] < t[..., :, None], t[..., None, :], 0)
    return t, jnp.max(smaller, axis=-1), valid


def model_size(height: int, width: int, size: int | None, factor: int = 8) -> tuple[int, int]:
    """(h, w) the networks see: longer side -> ``size`` (None: keep), multiples of ``factor``."""
    scale = 1.0 if size is None else size / max(height, width)
    return (max(factor, int(round(height * scale / factor)) * factor),
            max(factor, int(round(width * scale / factor)) * factor))


#: InstructPix2Pix's (text, image) guidance scales, unless a folder recommends its own.
IP2P_GUIDANCE = (7.5, 1.5)


def check_guidance(guidance, field: str = "guidance") -> tuple[float, float]:
    """``guidance`` as finite (text >= 0, image > 0) floats, else DataError naming ``field``."""
    try:
        text, image = (float(g) for g in guidance)
    except (TypeError, ValueError):
        raise DataError(field, f"need two scales (text, image), got {guidance!r}") from None
    if not (np.isfinite(text) and np.isfinite(image) and text >= 0 and image > 0):
        raise DataError(field, f"need text >= 0 and image > 0 scales, got {guidance!r}")
    return text, image


def dual_guidance(eps, text_scale: float, image_scale: float):
    """UNet output [3B, ...] ordered (text+image, image, uncond) -> [B, ...]:
    eps_u + s_t (eps_ti - eps_i) + s_i (eps_i - eps_u)."""
    b = eps.shape[0] // 3
    eps_ti, eps_i, eps_u = eps[:b], eps[b:2 * b], eps[2 * b:]
    return eps_u + text_scale * (eps_ti - eps_i) + image_scale * (eps_i - eps_u)


def ddim_step(sample, model_output, alpha_t, alpha_prev, prediction_type: str = "epsilon",
              clip_sample: float | None = None):
    """One DDIM update (eta = 0) from cumulative alpha ``alpha_t`` to ``alpha_prev`` (floats,
    or arrays broadcastable to ``sample``), x0 clamped to +-``clip_sample`` when given."""
    a_t, a_p = alpha_t, alpha_prev
    if isinstance(a_t, (int, float, np.floating)):  # host scalars stay Python floats (torch)
        a_t, a_p = float(a_t), float(a_p)
    if prediction_type == "epsilon":
        eps = model_output
        x0 = (sample - (1 - a_t) ** 0.5 * eps) / a_t ** 0.5
    elif prediction_type == "v_prediction":
        x0 = a_t ** 0.5 * sample - (1 - a_t) ** 0.5 * model_output
        eps = a_t ** 0.5 * model_output + (1 - a_t) ** 0.5 * sample
    elif prediction_type == "sample":
        x0 = model_output
        eps = (sample - a_t ** 0.5 * x0) / (1 - a_t) ** 0.5
    else:
        raise DataError("scheduler.prediction_type", f"unsupported {prediction_type!r}")
    if clip_sample is not None:
        x0 = x0.clamp(-clip_sample, clip_sample) if hasattr(x0, "clamp") else jnp.clip(
            x0, -clip_sample, clip_sample)
    return a_p ** 0.5 * x0 + (1 - a_p) ** 0.5 * eps


def ddim_overrides(folder: Path) -> dict:
    """SD 1.x's DDIM setup for a scheduler of another class, as IN2N reads IP2P's
    Euler-ancestral config; {} for a DDIM config."""
    from ..models.load import read_scheduler_config

    config = read_scheduler_config(folder / "scheduler_config.json")
    if config.get("_class_name") == "DDIMScheduler":
        return {}
    return {"clip_sample": False, "set_alpha_to_one": False}


def ddim_settings(folder: Path, alphas_cumprod) -> dict:
    """{"final_alpha": float, "clip_sample": float | None} of a scheduler folder
    (:func:`ddim_overrides`; DDIMScheduler's defaults for keys left out)."""
    from ..models.load import read_scheduler_config

    config = {**read_scheduler_config(folder / "scheduler_config.json"),
              **ddim_overrides(folder)}
    if config.get("thresholding", False):
        raise DataError(folder, "dynamic thresholding schedulers are not supported by the "
                        "SDEdit loop")
    clip = float(config.get("clip_sample_range", 1.0)) if config.get("clip_sample", True) else None
    final = 1.0 if config.get("set_alpha_to_one", True) else float(np.asarray(alphas_cumprod)[0])
    return {"final_alpha": final, "clip_sample": clip}
