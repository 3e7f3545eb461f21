"""The small InstructPix2Pix shipped in the package: its folder, size, instructions, guidance."""


from __future__ import annotations

import json
from pathlib import Path

from ..errors import DataError
from .diffusion import IP2P_GUIDANCE, check_guidance

#: Where the bundled weights live inside the installed package.
BUNDLED = Path(__file__).parent / "weights" / "tiny-ip2p"

#: Working resolution of a folder that does not say it (Stable Diffusion 1.x's).
DEFAULT_SIZE = 512


def bundled_editor() -> Path:
    """The bundled diffusers folder; DataError when the package was installed without it."""
    if not (BUNDLED / "model_index.json").is_file():
        raise DataError(BUNDLED, "the bundled editor's weights are missing from this "
                                 "installation (package data of jaxedit.editors; regenerate "
                                 "them with `python -m experiments train-editor`)")
    return BUNDLED


def native_size(folder: str | Path) -> int:
    """A diffusers folder's working resolution as its pipelines default to it: the UNet's
    ``sample_size`` times the VAE factor, 512 where the configs do not say."""
    folder = Path(folder)
    try:
        unet = json.loads((folder / "unet" / "config.json").read_text())
        vae = json.loads((folder / "vae" / "config.json").read_text())
        side = unet["sample_size"]
        side = side[0] if isinstance(side, (list, tuple)) else side
        return int(side) * 2 ** (len(vae["block_out_channels"]) - 1)
    except (OSError, ValueError, KeyError, TypeError, IndexError):
        return DEFAULT_SIZE


def _listing(folder: str | Path | None) -> tuple[Path, object]:
    """(path of ``instructions.json``, its JSON or None); DataError naming an unreadable file."""
    path = Path(folder if folder is not None else BUNDLED) / "instructions.json"
    if not path.is_file():
        return path, None
    try:
        return path, json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise DataError(path, f"unreadable instructions list ({e})") from None


def instructions(folder: str | Path | None = None) -> list[dict]:
    """A folder's ``instructions.json`` entries (prompt, kind, outcomes); [] without the file."""
    path, listing = _listing(folder)
    if listing is None:
        return []
    try:
        return list(listing["instructions"])
    except (KeyError, TypeError) as e:
        raise DataError(path, f"unreadable instructions list ({e})") from None


def recommended_guidance(folder: str | Path | None = None) -> tuple[float, float]:
    """The (text, image) guidance of a folder's ``instructions.json``, else InstructPix2Pix's."""
    path, listing = _listing(folder)
    if not isinstance(listing, dict) or "guidance" not in listing:
        return IP2P_GUIDANCE
    return check_guidance(listing["guidance"], str(path))
