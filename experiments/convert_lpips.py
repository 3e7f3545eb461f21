"""convert-lpips: build jaxedit's LPIPS weights file from torchvision + lpips weights.

LPIPS needs two sets of weights, neither of which jaxedit can download:

* the ImageNet trunk: torchvision's ``vgg16-397923af.pth`` or ``alexnet-owt-7be5be79.pth``
  (a plain state_dict; torchvision itself is not needed to read it, torch is). Pass it with
  ``--trunk``; by default the torch hub cache (``$TORCH_HOME/hub/checkpoints``) is searched,
  which is where ``torchvision.models.vgg16(weights="IMAGENET1K_V1")`` leaves it.
* the linear heads, shipped inside the ``lpips`` PyPI package (``lpips/weights/v0.1/<net>.pth``),
  found without importing the package (which would import torchvision); ``--heads`` overrides.

Writes ``OUT/lpips_<net>.safetensors`` (or ``.npz`` with ``--format npz``) plus the run's
config.json, and checks that the result loads. Use the file with ``--lpips-weights FILE``.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

from jaxedit.errors import DataError

HELP = "convert torchvision trunk + lpips heads weights into jaxedit's LPIPS file"

TORCHVISION_FILES = {"vgg": "vgg16-397923af.pth", "alex": "alexnet-owt-7be5be79.pth"}


def add_arguments(p) -> None:
    p.add_argument("--net", choices=["vgg", "alex"], default="vgg", help="LPIPS trunk")
    p.add_argument("--trunk", type=Path, default=None,
                   help="torchvision state_dict .pth of the trunk (default: the torch hub cache)")
    p.add_argument("--heads", type=Path, default=None,
                   help="lpips heads .pth (default: the one shipped in the lpips package, v0.1)")
    p.add_argument("--format", choices=["safetensors", "npz"], default="safetensors")


def _torch():
    try:
        import torch
    except ImportError:
        raise DataError("torch", "reading .pth weights needs torch: pip install 'jaxedit[lpips]' "
                        "(torch==2.13.0 on CPU machines)") from None
    return torch


def default_heads(net: str) -> Path:
    spec = importlib.util.find_spec("lpips")
    if spec is None or not spec.submodule_search_locations:
        raise DataError("--heads", "the lpips package is not installed (pip install --no-deps "
                        "lpips, it ships the heads) and no --heads file was given")
    return Path(list(spec.submodule_search_locations)[0]) / "weights" / "v0.1" / f"{net}.pth"


def default_trunk(net: str) -> Path:
    home = os.environ.get("TORCH_HOME") or os.path.join(
        os.environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache")), "torch")
    return Path(home) / "hub" / "checkpoints" / TORCHVISION_FILES[net]


def _load_pth(path: Path, what: str, how: str) -> dict:
    if not path.is_file():
        raise DataError(path, f"{what} not found; {how}")
    torch = _torch()
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - torch raises many types for a bad file
        raise DataError(path, f"cannot read as a torch state_dict ({type(e).__name__})") from None
    if not isinstance(state, dict):
        raise DataError(path, "is not a state_dict (a dict of tensors)")
    return {k: v.detach().float().numpy() for k, v in state.items() if hasattr(v, "detach")}


def convert(out_file: Path, net: str = "vgg", trunk: Path | None = None,
            heads: Path | None = None) -> Path:
    """Write jaxedit's LPIPS file ``out_file`` from the two .pth files; returns its path."""
    from jaxedit.lpips import lpips_tensors, save_lpips_params

    trunk = Path(trunk) if trunk is not None else default_trunk(net)
    heads = Path(heads) if heads is not None else default_heads(net)
    trunk_state = _load_pth(
        trunk, f"torchvision {net} trunk weights",
        f"download {TORCHVISION_FILES[net]} (torchvision's ImageNet weights for "
        f"{'vgg16' if net == 'vgg' else 'alexnet'}) on a machine with network and pass "
        f"--trunk FILE")
    heads_state = _load_pth(heads, "LPIPS heads", "pip install --no-deps lpips, or pass --heads")
    tensors = lpips_tensors(trunk_state, heads_state, net, where=f"{trunk} + {heads}")
    return save_lpips_params(out_file, tensors, net, source=f"trunk={trunk.name}; heads={heads}")


def run(args):
    if args.out is None:
        raise DataError("--out", "give the folder to write lpips_<net>.<format> into")
    out_file = Path(args.out) / f"lpips_{args.net}.{args.format}"
    path = convert(out_file, args.net, args.trunk, args.heads)
    if not args.quiet:
        print(f"wrote {path}")
    return {"lpips_weights": str(path), "net": args.net}
