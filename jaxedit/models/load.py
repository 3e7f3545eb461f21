"""Reading diffusers-format weights into the equinox modules without torch; a missing,
unexpected or mis-shaped tensor is a one-line :class:`~jaxedit.errors.DataError`."""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import re
from pathlib import Path
from typing import Any, Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import DataError
from ..io.weights import load_torch_checkpoint, local_model_folder, read_safetensors
from .clip_text import CLIPTextEncoder, CLIPTokenizer
from .layers import ParamLayer

__all__ = ["IP2PModels", "DDPMSchedule", "load_ip2p", "load_module", "read_weights", "cast",
           "check_layout", "module_from_tensors", "HOW_TO_GET", "LAYOUT"]

HOW_TO_GET = ("timbrooks/instruct-pix2pix in diffusers format; download it on a machine with network "
              "with `huggingface-cli download timbrooks/instruct-pix2pix --local-dir DIR` (or "
              "`hf download`) and give that folder as the editor's weights")

#: Sub-folder -> files of which at least one must exist (diffusers' save_pretrained layout).
LAYOUT = {
    "unet": ["config.json"],
    "vae": ["config.json"],
    "text_encoder": ["config.json"],
    "tokenizer": ["vocab.json", "tokenizer.json"],
    "scheduler": ["scheduler_config.json"],
}

#: Tensors a checkpoint may hold that no module needs (buffers older libraries saved).
_IGNORED = re.compile(r"(^|\.)position_ids$")

#: The VAE attention's names before diffusers 0.14 -> today's.
_LEGACY_ATTENTION = {"query": "to_q", "key": "to_k", "value": "to_v", "proj_attn": "to_out.0"}
_LEGACY_RE = re.compile(r"^(.*attentions\.\d+)\.(query|key|value|proj_attn)\.(weight|bias)$")


def check_layout(path: str | os.PathLike) -> Path:
    """A local diffusers folder (or a Hub id in the local cache); names the sub-folders missing."""
    p = local_model_folder(path, what="InstructPix2Pix weights", how_to_get=HOW_TO_GET)
    missing = [f"{sub}/{files[0]}" for sub, files in LAYOUT.items()
               if not any((p / sub / f).is_file() for f in files)]
    if missing:
        raise DataError(p, f"incomplete diffusers folder, missing {', '.join(missing)}; "
                        f"needs {HOW_TO_GET}")
    return p


def read_config(path: Path) -> dict:
    """A JSON object from ``path`` (any config of the folder), or a DataError naming it."""
    try:
        config = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DataError(path, "missing") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:
        raise DataError(path, f"unreadable JSON ({type(e).__name__}: {str(e)[:120]})") from None
    if not isinstance(config, dict):
        raise DataError(path, "expected a JSON object")
    return config


#: Per network, its architecture's config entries: name -> (kind, least, most), kind "int",
#: "ints" (one per block), "float", "bool" or "strs"; absent entries take the default.
CONFIG_SCHEMA = {
    "unet": {"block_out_channels": ("ints", 1, 16384), "layers_per_block": ("ints", 1, 16),
             "in_channels": ("int", 1, 1024), "out_channels": ("int", 1, 1024),
             "cross_attention_dim": ("ints", 1, 16384), "attention_head_dim": ("ints", 1, 4096),
             "num_attention_heads": ("ints", 1, 4096),
             "transformer_layers_per_block": ("ints", 1, 16),
             "norm_num_groups": ("int", 1, 16384), "norm_eps": ("float", 0, 1),
             "sample_size": ("int", 1, 16384), "down_block_types": ("strs", 1, 8),
             "up_block_types": ("strs", 1, 8), "flip_sin_to_cos": ("bool", 0, 1),
             "freq_shift": ("float", -1e6, 1e6), "mid_block_scale_factor": ("float", -1e6, 1e6),
             "downsample_padding": ("int", 0, 16), "use_linear_projection": ("bool", 0, 1)},
    "vae": {"block_out_channels": ("ints", 1, 16384), "layers_per_block": ("int", 1, 16),
            "in_channels": ("int", 1, 1024), "out_channels": ("int", 1, 1024),
            "latent_channels": ("int", 1, 1024), "norm_num_groups": ("int", 1, 16384),
            "sample_size": ("int", 1, 16384), "scaling_factor": ("float", 1e-6, 1e6),
            "down_block_types": ("strs", 1, 8), "up_block_types": ("strs", 1, 8),
            "mid_block_add_attention": ("bool", 0, 1), "double_z": ("bool", 0, 1)},
    "text_encoder": {"hidden_size": ("int", 1, 16384), "num_hidden_layers": ("int", 1, 96),
                     "num_attention_heads": ("int", 1, 1024),
                     "intermediate_size": ("int", 1, 65536), "vocab_size": ("int", 1, 2_000_000),
                     "max_position_embeddings": ("int", 2, 8192),
                     "layer_norm_eps": ("float", 0, 1), "hidden_act": ("strs", 1, 1)},
}


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _entry_problem(value, kind: str, low: float, high: float) -> str | None:
    """What is wrong with one config entry (None: nothing)."""
    if kind == "bool":
        return None if isinstance(value, bool) else "must be true or false"
    if kind == "strs":
        values = [value] if isinstance(value, str) and high == 1 else value
        ok = (isinstance(values, (list, tuple)) and low <= len(values) <= high
              and all(isinstance(v, str) for v in values))
        return None if ok else (f"must be a list of {low} .. {high} names" if high > 1
                                else "must be a name")
    if kind == "float":
        ok = _number(value) and math.isfinite(value) and low <= value <= high
        return None if ok else f"must be a number in [{low:g}, {high:g}]"
    values = value if kind == "ints" and isinstance(value, (list, tuple)) else [value]
    ok = (len(values) >= 1 and len(values) <= 8 and all(
        isinstance(v, int) and not isinstance(v, bool) and low <= v <= high for v in values))
    what = "a whole number" + (" (or a list of up to 8, one per block)" if kind == "ints" else "")
    return None if ok else f"must be {what} in {low} .. {high}"


def check_network_config(kind: str, config: dict, where) -> dict:
    """A network's config.json checked against :data:`CONFIG_SCHEMA` and for consistency;
    DataError naming ``where`` and the entry."""
    for name, (entry, low, high) in CONFIG_SCHEMA[kind].items():
        if config.get(name) is None:
            continue
        problem = _entry_problem(config[name], entry, low, high)
        if problem:
            raise DataError(where, f"{name} {problem}, got {json.dumps(config[name])[:60]}")
    if kind in ("unet", "vae"):
        groups = config.get("norm_num_groups", 32)
        channels = list(config.get("block_out_channels", (320, 640, 1280, 1280)))
        for name, (entry, _, _) in CONFIG_SCHEMA[kind].items():
            value = config.get(name)
            if entry in ("ints", "strs") and isinstance(value, list) and len(value) != len(
                    channels):
                raise DataError(where, f"{name} has {len(value)} entries for "
                                       f"{len(channels)} blocks (block_out_channels)")
        if any(c % groups for c in channels):
            raise DataError(where, f"block_out_channels {channels} are not all divisible by "
                                   f"norm_num_groups {groups}")
    if kind == "text_encoder":
        width, heads = config.get("hidden_size"), config.get("num_attention_heads")
        if width is not None and heads is not None and width % heads:
            raise DataError(where, f"hidden_size {width} is not divisible by "
                                   f"num_attention_heads {heads}")
    return config


#: scheduler_config.json's entries: name -> (kind, least, most), as :data:`CONFIG_SCHEMA`.
SCHEDULER_SCHEMA = {
    "num_train_timesteps": ("int", 1, 100_000), "beta_start": ("float", 0, 1),
    "beta_end": ("float", 0, 1), "beta_schedule": ("strs", 1, 1),
    "prediction_type": ("strs", 1, 1), "clip_sample": ("bool", 0, 1),
    "clip_sample_range": ("float", 1e-6, 1e6), "set_alpha_to_one": ("bool", 0, 1),
    "thresholding": ("bool", 0, 1), "steps_offset": ("int", 0, 100_000),
    "_class_name": ("strs", 1, 1),
}


def check_scheduler_config(config: dict, where) -> dict:
    """A scheduler config checked against :data:`SCHEDULER_SCHEMA` (beta_start <= beta_end,
    ``trained_betas`` one in (0, 1) per timestep); DataError naming ``where`` and the entry."""
    for name, (entry, low, high) in SCHEDULER_SCHEMA.items():
        if config.get(name) is None:
            continue
        problem = _entry_problem(config[name], entry, low, high)
        if problem:
            raise DataError(where, f"{name} {problem}, got {json.dumps(config[name])[:60]}")
    if config.get("beta_start", 0.0001) > config.get("beta_end", 0.02):
        raise DataError(where, f"beta_start {config.get('beta_start')} is above beta_end "
                               f"{config.get('beta_end')}")
    betas = config.get("trained_betas")
    if betas is not None:
        n = config.get("num_train_timesteps", 1000)
        if (not isinstance(betas, list) or len(betas) != n
                or not all(_number(b) and 0 < b < 1 for b in betas)):
            raise DataError(where, f"trained_betas must be {n} numbers in (0, 1) "
                                   f"(num_train_timesteps)")
    return config


def read_scheduler_config(path: Path) -> dict:
    """``scheduler_config.json``, read and checked (:func:`check_scheduler_config`)."""
    return check_scheduler_config(read_config(path), path)


def _per(value, n: int) -> list:
    return list(value) if isinstance(value, (list, tuple)) else [value] * n


def weight_bytes_at_least(kind: str, config: dict, itemsize: int) -> float:
    """A lower bound of a checked config's weight bytes, from its largest layers."""
    if kind == "text_encoder":
        d, layers = config.get("hidden_size", 768), config.get("num_hidden_layers", 12)
        inner = config.get("intermediate_size", 4 * d)
        values = layers * (4 * d * d + 2 * d * inner) + config.get("vocab_size", 49408) * d
    else:
        channels = list(config.get("block_out_channels", (320, 640, 1280, 1280)))
        layers = _per(config.get("layers_per_block", 2), len(channels))
        # Each resnet holds two 3x3 convolutions; the decoder (VAE) or up path (UNet) again.
        values = 2 * sum(n * 2 * 9 * c * c for n, c in zip(layers, channels))
    return float(values) * itemsize


def weights_file(folder: Path) -> Path:
    """A component folder's weights file: ``.safetensors``, ``.fp16`` ones, then torch ``.bin``."""
    stems = ["diffusion_pytorch_model", "model"]
    for suffix in (".safetensors", ".fp16.safetensors"):
        for stem in stems:
            if (folder / f"{stem}{suffix}").is_file():
                return folder / f"{stem}{suffix}"
    for stem in ("diffusion_pytorch_model", "pytorch_model"):  # diffusers', transformers' names
        for suffix in (".bin", ".fp16.bin"):
            if (folder / f"{stem}{suffix}").is_file():
                return folder / f"{stem}{suffix}"
    sharded = sorted(folder.glob("*.safetensors.index.json"))
    if sharded:
        raise DataError(sharded[0], "sharded weights are not supported; save the component unsharded")
    raise DataError(folder, f"no weights file ({stems[0]}.safetensors or {stems[1]}.safetensors); "
                    f"needs {HOW_TO_GET}")


def read_weights(path: Path) -> dict[str, np.ndarray]:
    """All tensors of a ``.safetensors`` file or a torch ``.bin`` (no code run), as NumPy."""
    if path.suffix == ".bin":
        return load_torch_checkpoint(path)
    return read_safetensors(path)[0]


def _path_name(path) -> str:
    parts = []
    for entry in path:
        if isinstance(entry, jax.tree_util.GetAttrKey):
            parts.append(entry.name)
        elif isinstance(entry, jax.tree_util.SequenceKey):
            parts.append(str(entry.idx))
        else:  # dict keys: none of the modules use them
            parts.append(str(getattr(entry, "key", entry)))
    return ".".join(parts)


def _named_layers(module) -> tuple[list[tuple[str, ParamLayer]], Any]:
    """(checkpoint-name prefix, layer) for every ParamLayer, and the treedef to rebuild."""
    is_layer = lambda x: isinstance(x, ParamLayer)  # noqa: E731
    leaves, treedef = jax.tree_util.tree_flatten_with_path(module, is_leaf=is_layer)
    if not all(is_layer(leaf) for _, leaf in leaves):
        raise TypeError("every array of a model must live in a ParamLayer")
    return [(_path_name(p), leaf) for p, leaf in leaves], treedef


def _modernise(tensors: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Rename legacy attention tensors (VAE ``query``/``proj_attn`` ...) to today's names."""
    out = {}
    for name, value in tensors.items():
        m = _LEGACY_RE.match(name)
        out[f"{m[1]}.{_LEGACY_ATTENTION[m[2]]}.{m[3]}" if m else name] = value
    return out


def _listing(names: list[str], limit: int = 3) -> str:
    shown = ", ".join(repr(n) for n in names[:limit])
    return shown + (f" and {len(names) - limit} more" if len(names) > limit else "")


def module_from_tensors(skeleton, tensors: dict[str, np.ndarray], where: str | os.PathLike, *,
                        prefix: str = "", dtype=jnp.float32):
    """``skeleton`` (a module, or shapes only) filled from ``tensors``, checkpoint name (under
    ``prefix``) -> torch-layout array; DataError(where, ...) naming bad tensors."""
    # transformers >= 5 saves CLIPTextModel without "text_model.": accept both.
    prefix = prefix if any(k.startswith(prefix) for k in tensors) else ""
    tensors = _modernise({k[len(prefix):] if k.startswith(prefix) else k: v
                          for k, v in tensors.items()})
    layers, treedef = _named_layers(skeleton)
    filled, used, missing, wrong = [], set(), [], []
    for name, layer in layers:
        values = {}
        for field, (shape, convert) in layer.torch_layout().items():
            key = f"{name}.{field}"
            if key not in tensors:
                missing.append(prefix + key)
                continue
            used.add(key)
            array = tensors[key]
            squeezable = len(shape) == 2 and array.shape == tuple(shape) + (1, 1)
            if array.shape != tuple(shape) and not squeezable:
                wrong.append(f"{prefix + key!r} has shape {list(array.shape)}, expected {list(shape)}")
                continue
            # converted on the host: on the device each shape would compile its own conversion
            values[field] = jax.device_put(np.asarray(convert(np.asarray(array)), dtype=dtype))
        filled.append(dataclasses.replace(layer, **values) if values else layer)
    unexpected = sorted(prefix + k for k in tensors if k not in used and not _IGNORED.search(k))
    problems = []
    if missing:
        problems.append(f"missing tensor{'s' * (len(missing) > 1)} {_listing(missing)}")
    if unexpected:
        problems.append(f"unexpected tensor{'s' * (len(unexpected) > 1)} {_listing(unexpected)}")
    if wrong:
        problems.append(wrong[0] + (f" (and {len(wrong) - 1} more mis-shaped)" if len(wrong) > 1 else ""))
    if problems:
        raise DataError(where, "; ".join(problems) + " (does config.json match the weights?)")
    return jax.tree_util.tree_unflatten(treedef, filled)


def load_module(folder: str | os.PathLike, build: Callable[..., Any], *, prefix: str = "",
                dtype=jnp.float32, kind: str | None = None):
    """A module from one component folder, shaped by ``build(config, key=..., dtype=...)``;
    the config (``kind``: default the folder's name) and free memory are checked first."""
    from ..memory import require_memory

    folder = Path(folder)
    kind = kind or folder.name
    where = folder / "config.json"
    config = check_network_config(kind, read_config(where), where)
    path = weights_file(folder)
    require_memory(where, weight_bytes_at_least(kind, config, jnp.dtype(dtype).itemsize),
                   f"the {kind} this config describes")
    skeleton = eqx.filter_eval_shape(build, config, key=jax.random.key(0), dtype=dtype)
    return module_from_tensors(skeleton, read_weights(path), path, prefix=prefix, dtype=dtype)


@dataclasses.dataclass(frozen=True, eq=False)
class DDPMSchedule:
    """The training noise schedule of ``scheduler_config.json``, hashable by value."""

    num_train_timesteps: int
    beta_start: float
    beta_end: float
    beta_schedule: str
    alphas_cumprod: np.ndarray  # float32 [num_train_timesteps]
    prediction_type: str

    @staticmethod
    def from_config(config: dict, where: str | os.PathLike = "scheduler_config.json") -> "DDPMSchedule":
        """Betas as diffusers makes them ("linear", "scaled_linear", "squaredcos_cap_v2")."""
        check_scheduler_config(config, where)
        n = int(config.get("num_train_timesteps", 1000))
        b0, b1 = float(config.get("beta_start", 0.0001)), float(config.get("beta_end", 0.02))
        kind = config.get("beta_schedule", "linear")
        if config.get("trained_betas") is not None:
            betas = np.asarray(config["trained_betas"], np.float64)
        elif kind == "linear":
            betas = np.linspace(b0, b1, n, dtype=np.float64)
        elif kind == "scaled_linear":
            betas = np.linspace(b0 ** 0.5, b1 ** 0.5, n, dtype=np.float64) ** 2
        elif kind == "squaredcos_cap_v2":
            f = lambda t: np.cos((t + 0.008) / 1.008 * np.pi / 2) ** 2  # noqa: E731
            t = np.arange(n, dtype=np.float64)
            betas = np.minimum(1 - f((t + 1) / n) / f(t / n), 0.999)
        else:
            raise DataError(where, f"unsupported beta_schedule {kind!r}")
        # diffusers holds the betas and their running product in float32: keep its rounding.
        alphas_cumprod = np.cumprod(1.0 - betas.astype(np.float32), dtype=np.float32)
        prediction = config.get("prediction_type", "epsilon")
        if prediction not in ("epsilon", "v_prediction", "sample"):
            raise DataError(where, f"unsupported prediction_type {prediction!r}")
        return DDPMSchedule(n, b0, b1, kind, alphas_cumprod, prediction)

    def _key(self):
        return (self.num_train_timesteps, self.beta_start, self.beta_end, self.beta_schedule,
                self.prediction_type, np.asarray(self.alphas_cumprod, np.float32).tobytes())

    def __eq__(self, other):
        return isinstance(other, DDPMSchedule) and self._key() == other._key()

    def __hash__(self):
        return hash(self._key())


class IP2PModels(eqx.Module):
    """The networks and the fixed pieces of an InstructPix2Pix pipeline."""

    unet: Any  # UNet2DCondition
    vae: Any  # AutoencoderKL
    text_encoder: CLIPTextEncoder
    tokenizer: CLIPTokenizer = eqx.field(static=True)
    scheduler: DDPMSchedule = eqx.field(static=True)


def load_ip2p(folder: str | os.PathLike, *, dtype=jnp.float32) -> IP2PModels:
    """An InstructPix2Pix (or SD 1.x) diffusers folder -> :class:`IP2PModels`, cast as read."""
    from .unet import UNet2DCondition
    from .vae import AutoencoderKL

    root = check_layout(folder)
    models = IP2PModels(
        unet=load_module(root / "unet", UNet2DCondition.from_config, dtype=dtype),
        vae=load_module(root / "vae", AutoencoderKL.from_config, dtype=dtype),
        text_encoder=load_module(root / "text_encoder", CLIPTextEncoder.from_config,
                                 prefix=CLIPTextEncoder.CHECKPOINT_PREFIX, dtype=dtype),
        tokenizer=CLIPTokenizer.from_folder(root / "tokenizer"),
        scheduler=DDPMSchedule.from_config(
            read_scheduler_config(root / "scheduler" / "scheduler_config.json"),
            root / "scheduler" / "scheduler_config.json"))
    check_tokenizer_fits(models.tokenizer, models.text_encoder, root / "tokenizer")
    return models


def check_tokenizer_fits(tokenizer: CLIPTokenizer, text_encoder, where) -> None:
    """Refuse a tokenizer whose ids or length the text encoder has no rows for
    (JAX would clamp the lookups silently)."""
    rows = text_encoder.embeddings.token_embedding.weight.shape[0]
    positions = text_encoder.embeddings.position_embedding.weight.shape[0]
    vocab = tokenizer._tokenizer.get_vocab_size()
    if vocab > rows:
        raise DataError(where, f"has {vocab} tokens, the text encoder's vocab_size is {rows}")
    if tokenizer.max_length > positions:
        raise DataError(where, f"model_max_length {tokenizer.max_length} is above the text "
                               f"encoder's max_position_embeddings {positions}")


def cast(models, dtype):
    """Every floating array of ``models`` (any pytree) cast to ``dtype`` in one program."""
    arrays, rest = eqx.partition(models, eqx.is_array)
    return eqx.combine(_cast_floating(arrays, jnp.dtype(dtype)), rest)


@functools.partial(jax.jit, static_argnums=1)
def _cast_floating(arrays, dtype):
    return jax.tree_util.tree_map(
        lambda x: x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x, arrays)
