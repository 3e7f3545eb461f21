"""The diffusion arithmetic of the InstructPix2Pix edit, shared by both editors.

The timestep draw, the DDIM schedule (a host list, and fixed-length arrays for ``jit``),
the model size, dual guidance and the DDIM update, written with arithmetic only so they
take torch tensors and JAX arrays alike; nothing here imports torch.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import DataError
# The folder checks live with the loader.
from ..models.load import HOW_TO_GET  # noqa: F401 - re-exported
from ..models.load import check_layout as resolve_weights  # noqa: F401 - re-exported

DEFAULT_MODEL = "timbrooks/instruct-pix2pix"
#: The diffusion timesteps Stable Diffusion is trained with.
NUM_TRAIN_TIMESTEPS = 1000
#: DDIM steps per edit, both editors' default (IN2N's); commands and studies read it here.
DDIM_STEPS = 20
#: The short names both editors' ``dtype`` takes for float16, bfloat16 and float32.
DTYPE_ALIASES = {"fp16": "float16", "half": "float16", "fp32": "float32", "float": "float32",
                 "bf16": "bfloat16"}


def dtype_name(dtype) -> str:
    """An editor's ``dtype`` name with a :data:`DTYPE_ALIASES` alias spelled out
    ("fp16" -> "float16"); other names as given."""
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
    """DDIM timesteps from ``t_start`` towards 0: round(T (steps - k) / steps), k < steps,
    repeats and zeros dropped; the step after the last lands on the final alpha."""
    if steps < 1:
        raise DataError("steps", f"must be >= 1, got {steps}")
    ts = [int(round(t_start * (steps - k) / steps)) for k in range(steps)]
    return sorted({t for t in ts if t > 0}, reverse=True)


def timestep_table(t_start: jax.Array, steps: int) -> tuple[jax.Array, jax.Array, jax.Array]:
    """:func:`timestep_schedule` as fixed-length arrays, for a traced ``t_start``.

    Args:
      t_start: int [...] timesteps T.
      steps: static number of slots.
    Returns:
      (t, t_next, valid), each [..., steps]: t_k = round(T (steps - k) / steps) (half to
      even); ``valid`` drops zero and repeated slots, so the valid slots are
      ``timestep_schedule(T, steps)``; ``t_next`` the next valid timestep (0 after the last).
    """
    t_start = jnp.asarray(t_start, jnp.int32)
    # Integer arithmetic: XLA may compute a quotient as a product with 1 / steps and round
    # a half the wrong way.
    num = t_start[..., None] * (steps - jnp.arange(steps, dtype=jnp.int32))
    q, r = num // steps, num % steps
    t = q + ((2 * r > steps) | ((2 * r == steps) & (q % 2 == 1))).astype(jnp.int32)
    prev = jnp.concatenate([jnp.full(t.shape[:-1] + (1,), -1, jnp.int32), t[..., :-1]], -1)
    valid = (t > 0) & (t != prev)
    # The slots are non-increasing, so the next valid timestep is the largest smaller one.
    smaller = jnp.where(t[..., None, :] < t[..., :, None], t[..., None, :], 0)
    return t, jnp.max(smaller, axis=-1), valid


def model_size(height: int, width: int, size: int | None, factor: int = 8) -> tuple[int, int]:
    """(h, w) the networks see: longer side -> ``size`` (None: keep), multiples of ``factor``."""
    scale = 1.0 if size is None else size / max(height, width)
    return (max(factor, int(round(height * scale / factor)) * factor),
            max(factor, int(round(width * scale / factor)) * factor))


#: InstructPix2Pix's (text, image) guidance scales (Brooks et al. 2023): an editor's unless
#: its folder recommends its own (:func:`jaxedit.editors.bundled.recommended_guidance`).
IP2P_GUIDANCE = (7.5, 1.5)


def check_guidance(guidance, field: str = "guidance") -> tuple[float, float]:
    """``guidance`` as (text, image) floats, finite, text >= 0 and image > 0 (0 would drop
    the view the edit starts from); DataError naming ``field`` otherwise."""
    try:
        text, image = (float(g) for g in guidance)
    except (TypeError, ValueError):
        raise DataError(field, f"need two scales (text, image), got {guidance!r}") from None
    if not (np.isfinite(text) and np.isfinite(image) and text >= 0 and image > 0):
        raise DataError(field, f"need text >= 0 and image > 0 scales, got {guidance!r}")
    return text, image


def dual_guidance(eps, text_scale: float, image_scale: float):
    """Combine the three-branch UNet output [3B, ...] ordered (text+image, image, uncond):
    eps_u + s_t (eps_ti - eps_i) + s_i (eps_i - eps_u). Torch tensors or JAX arrays."""
    b = eps.shape[0] // 3
    eps_ti, eps_i, eps_u = eps[:b], eps[b:2 * b], eps[2 * b:]
    return eps_u + text_scale * (eps_ti - eps_i) + image_scale * (eps_i - eps_u)


def ddim_step(sample, model_output, alpha_t, alpha_prev, prediction_type: str = "epsilon",
              clip_sample: float | None = None):
    """One deterministic DDIM update (eta = 0) from cumulative alpha ``alpha_t`` to ``alpha_prev``.

    x0 = (x - sqrt(1 - a_t) eps) / sqrt(a_t), clamped to +-``clip_sample`` when given;
    x_prev = sqrt(a_prev) x0 + sqrt(1 - a_prev) eps. Torch tensors with float alphas, or
    JAX arrays with alphas broadcastable to ``sample``.
    """
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


# ----------------------------------------------------------------------------- weights folders

def ddim_overrides(folder: Path) -> dict:
    """DDIM settings for a scheduler config of another class: SD 1.x's DDIM setup
    (no x0 clipping, final alpha = alpha_0), as IN2N uses for IP2P's Euler-ancestral config.
    An explicit DDIM config is kept as is."""
    from ..models.load import read_scheduler_config

    config = read_scheduler_config(folder / "scheduler_config.json")
    if config.get("_class_name") == "DDIMScheduler":
        return {}
    return {"clip_sample": False, "set_alpha_to_one": False}


def ddim_settings(folder: Path, alphas_cumprod) -> dict:
    """The DDIM update's settings from a scheduler folder (:func:`ddim_overrides`).

    Returns {"final_alpha": float, "clip_sample": float | None}, with DDIMScheduler's
    defaults for keys an explicit DDIM config leaves out.
    """
    from ..models.load import read_scheduler_config

    config = {**read_scheduler_config(folder / "scheduler_config.json"),
              **ddim_overrides(folder)}
    if config.get("thresholding", False):
        raise DataError(folder, "dynamic thresholding schedulers are not supported by the "
                        "SDEdit loop")
    clip = float(config.get("clip_sample_range", 1.0)) if config.get("clip_sample", True) else None
    final = 1.0 if config.get("set_alpha_to_one", True) else float(np.asarray(alphas_cumprod)[0])
    return {"final_alpha": final, "clip_sample": clip}
