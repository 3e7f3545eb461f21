"""Reading diffusers-format weights straight into the equinox modules, without torch.

A diffusers pipeline folder (what ``huggingface-cli download timbrooks/instruct-pix2pix``
writes) holds ``model_index.json`` and one sub-folder per component; each network's
``config.json`` says its architecture and its weights file holds tensors named by the torch
module path. The modules here use the same attribute names, so a layer's pytree path is its
tensors' name (:mod:`jaxedit.models.layers`); loading builds the module's skeleton from the
config (shapes only, no random init), then fills every layer from the tensor of its name,
converting torch's layout. A missing, unexpected or mis-shaped tensor is a one-line
:class:`~jaxedit.errors.DataError` naming the file and the tensor(s).

Weights files, per sub-folder, in order of preference: ``model.safetensors`` /
``diffusion_pytorch_model.safetensors``, then their ``.fp16.safetensors`` variants
(converted to the requested dtype), read by :func:`jaxedit.io.weights.read_safetensors`;
then legacy torch ``.bin`` checkpoints (``diffusion_pytorch_model.bin``,
``pytorch_model.bin``), read by a restricted unpickler that rebuilds tensors as NumPy
arrays and refuses anything else (a pickle can run code).
"""

from __future__ import annotations

import dataclasses
import json
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


# ----------------------------------------------------------------------------- the folder

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
    try:
        config = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DataError(path, "missing") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DataError(path, f"unreadable JSON ({e})") from None
    if not isinstance(config, dict):
        raise DataError(path, "expected a JSON object")
    return config


def weights_file(folder: Path) -> Path:
    """The weights file of one component folder (see the module docstring for the order)."""
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
    """All tensors of a ``.safetensors`` file, or of a torch ``.bin`` state_dict (read without
    torch and without running code, :func:`jaxedit.io.weights.load_torch_checkpoint`), as
    NumPy arrays."""
    if path.suffix == ".bin":
        return load_torch_checkpoint(path)
    return read_safetensors(path)[0]


# ----------------------------------------------------------------------------- name mapping

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
    """``skeleton`` (a module, or its ``eqx.filter_eval_shape``) with every array from ``tensors``.

    ``tensors``: checkpoint name -> array in torch layout; names start with ``prefix``.
    Raises DataError(where, ...) naming missing, unexpected or mis-shaped tensors.
    """
    # transformers >= 5 saves CLIPTextModel without its "text_model." prefix: accept both, and
    # name tensors in errors as this file does.
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
            values[field] = jnp.asarray(convert(np.asarray(array)), dtype=dtype)
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
                dtype=jnp.float32):
    """A module from one component folder: ``build(config, key=..., dtype=...)`` gives its
    architecture (only its shapes are evaluated), the weights file fills it."""
    folder = Path(folder)
    config = read_config(folder / "config.json")
    path = weights_file(folder)
    skeleton = eqx.filter_eval_shape(build, config, key=jax.random.key(0), dtype=dtype)
    return module_from_tensors(skeleton, read_weights(path), path, prefix=prefix, dtype=dtype)


# ----------------------------------------------------------------------------- the pipeline

@dataclasses.dataclass(frozen=True, eq=False)
class DDPMSchedule:
    """The training noise schedule from ``scheduler/scheduler_config.json``.

    Hashable (by value) so it can be a static field of a jitted module."""

    num_train_timesteps: int
    beta_start: float
    beta_end: float
    beta_schedule: str
    alphas_cumprod: np.ndarray  # float32 [num_train_timesteps]
    prediction_type: str

    @staticmethod
    def from_config(config: dict, where: str | os.PathLike = "scheduler_config.json") -> "DDPMSchedule":
        """Betas as diffusers' schedulers make them: "linear", "scaled_linear" (linear in
        sqrt(beta)) or "squaredcos_cap_v2"; alphas_cumprod = prod(1 - beta)."""
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
    """An InstructPix2Pix (or any SD 1.x) diffusers folder -> :class:`IP2PModels` in ``dtype``.

    Each tensor is converted to ``dtype`` as it is read (as :func:`cast` would), so a bf16
    load never holds the float32 networks."""
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
            read_config(root / "scheduler" / "scheduler_config.json"),
            root / "scheduler" / "scheduler_config.json"))
    return models


def cast(models, dtype):
    """Every floating array of ``models`` (any pytree) cast to ``dtype`` (e.g. jnp.bfloat16).

    The layers compute in their weights' dtype; normalisation statistics and the attention
    softmax stay in float32 whatever it is (see :mod:`jaxedit.models.layers`)."""
    def convert(x):
        if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.floating):
            return x.astype(dtype)
        return x
    return jax.tree_util.tree_map(convert, models)
