"""Writing trained networks as a diffusers InstructPix2Pix folder (the inverse of
:func:`jaxedit.models.load_ip2p`).

Each layer's tensors are named by its pytree path (:mod:`jaxedit.models.layers`) and put back
in torch's layout by inverting the layer's own :meth:`~jaxedit.models.layers.ParamLayer.
torch_layout` conversion: the conversion is applied to an index array of the checkpoint's
shape, which gives the permutation it performs (a transpose, a reshape), and the trained
field is scattered back through it. So the writer cannot disagree with the reader, and
:func:`jaxedit.models.load_ip2p` of the folder gives back the same arrays, bit for bit.

The folder::

    model_index.json              StableDiffusionInstructPix2PixPipeline, no safety checker
    unet/config.json, diffusion_pytorch_model.safetensors
    vae/config.json, diffusion_pytorch_model.safetensors
    text_encoder/config.json, model.safetensors      (names prefixed "text_model.")
    tokenizer/vocab.json, merges.txt, tokenizer_config.json, special_tokens_map.json
    scheduler/scheduler_config.json
    instructions.json             prompt, kind, number of outcomes per instruction; the
                                  dataset's settings (size, cameras per scene, scenes)
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from jaxedit.io.files import atomic_write_text
from jaxedit.io.weights import write_safetensors
from jaxedit.models.load import _named_layers

MODEL_INDEX = {
    "_class_name": "StableDiffusionInstructPix2PixPipeline",
    "_diffusers_version": "0.27.0",
    "feature_extractor": [None, None],
    "image_encoder": [None, None],
    "requires_safety_checker": False,
    "safety_checker": [None, None],
    "scheduler": ["diffusers", "DDIMScheduler"],
    "text_encoder": ["transformers", "CLIPTextModel"],
    "tokenizer": ["transformers", "CLIPTokenizer"],
    "unet": ["diffusers", "UNet2DConditionModel"],
    "vae": ["diffusers", "AutoencoderKL"],
}


def _to_torch(field: np.ndarray, shape, convert) -> np.ndarray:
    """The checkpoint tensor of ``shape`` that ``convert`` turns into ``field``."""
    index = np.arange(int(np.prod(shape))).reshape(shape)
    where = np.asarray(convert(index))
    if where.shape != field.shape:
        raise ValueError(f"layout maps {tuple(shape)} to {where.shape}, field is {field.shape}")
    out = np.empty(int(np.prod(shape)), np.float32)
    out[where.reshape(-1)] = np.asarray(field, np.float32).reshape(-1)
    return out.reshape(shape)


def module_tensors(module, prefix: str = "") -> dict[str, np.ndarray]:
    """Checkpoint name -> float32 tensor in torch layout, for every array of ``module``."""
    tensors = {}
    for name, layer in _named_layers(module)[0]:
        for field, (shape, convert) in layer.torch_layout().items():
            tensors[f"{prefix}{name}.{field}"] = _to_torch(np.asarray(getattr(layer, field)),
                                                           shape, convert)
    return tensors


def _json(path: Path, obj) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2) + "\n")


def write_tokenizer(folder: Path, vocab: dict[str, int], merges: list[tuple[str, str]], *,
                    bos: str, eos: str, max_length: int) -> None:
    """A CLIPTokenizer folder (vocab.json, merges.txt, the configs)."""
    folder.mkdir(parents=True, exist_ok=True)
    _json(folder / "vocab.json", vocab)
    atomic_write_text(folder / "merges.txt",
                      "#version: 0.2\n" + "".join(f"{a} {b}\n" for a, b in merges))
    _json(folder / "special_tokens_map.json", {"bos_token": bos, "eos_token": eos,
                                               "unk_token": eos, "pad_token": eos})
    _json(folder / "tokenizer_config.json", {
        "tokenizer_class": "CLIPTokenizer", "model_max_length": max_length,
        "bos_token": bos, "eos_token": eos, "unk_token": eos, "pad_token": eos,
        "do_lower_case": True, "errors": "replace", "add_prefix_space": False,
        "clean_up_tokenization_spaces": True})


def read_tokenizer(folder: Path) -> tuple[dict[str, int], list[tuple[str, str]]]:
    """(vocab, merges) of a folder :func:`write_tokenizer` wrote (its inverse)."""
    vocab = json.loads((folder / "vocab.json").read_text())
    lines = (folder / "merges.txt").read_text().splitlines()
    merges = [tuple(line.split(" ")) for line in lines if line and not line.startswith("#")]
    return vocab, merges


def write_pipeline(out: str | os.PathLike, *, unet, unet_config: dict, vae, vae_config: dict,
                   text_encoder, text_config: dict, vocab: dict[str, int],
                   merges: list[tuple[str, str]], bos: str, eos: str, max_length: int,
                   scheduler_config: dict, instructions: list[dict],
                   dataset: dict | None = None, card: str | None = None) -> Path:
    """Write the diffusers folder ``out`` (see the module docstring); returns it."""
    from jaxedit.models import CLIPTextEncoder

    out = Path(out)
    for sub in ("unet", "vae", "text_encoder", "scheduler"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    write_safetensors(out / "unet" / "diffusion_pytorch_model.safetensors", module_tensors(unet),
                      {"format": "pt"})
    _json(out / "unet" / "config.json", unet_config)
    write_safetensors(out / "vae" / "diffusion_pytorch_model.safetensors", module_tensors(vae),
                      {"format": "pt"})
    _json(out / "vae" / "config.json", vae_config)
    write_safetensors(out / "text_encoder" / "model.safetensors",
                      module_tensors(text_encoder, CLIPTextEncoder.CHECKPOINT_PREFIX),
                      {"format": "pt"})
    _json(out / "text_encoder" / "config.json", text_config)
    write_tokenizer(out / "tokenizer", vocab, merges, bos=bos, eos=eos, max_length=max_length)
    _json(out / "scheduler" / "scheduler_config.json", scheduler_config)
    # The dataset's settings say which cameras were held out (the quality benchmark's views).
    _json(out / "instructions.json", {"instructions": instructions,
                                      **({"dataset": dataset} if dataset else {})})
    if card is not None:
        atomic_write_text(out / "README.md", card)
    _json(out / "model_index.json", MODEL_INDEX)  # last: a folder with it is complete
    return out
