"""The small InstructPix2Pix shipped inside the package: where its folder is, its working
size, the instructions it was trained on."""


from __future__ import annotations

import json
from pathlib import Path

from ..errors import DataError

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
    """The resolution a diffusers folder was trained at: the bundled model's own (its VAE's
    ``sample_size``), Stable Diffusion's 512 for any other folder, whose VAE config often
    states a size it was not trained at."""
    folder = Path(folder)
    if folder.resolve() != BUNDLED.resolve():
        return DEFAULT_SIZE
    config = json.loads((folder / "vae" / "config.json").read_text())
    return int(config.get("sample_size", DEFAULT_SIZE))


def instructions(folder: str | Path | None = None) -> list[dict]:
    """The instructions a trained folder lists (``instructions.json``): prompt, kind,
    outcomes; [] for a folder without the file (InstructPix2Pix takes any text)."""
    path = Path(folder if folder is not None else BUNDLED) / "instructions.json"
    if not path.is_file():
        return []
    try:
        return list(json.loads(path.read_text())["instructions"])
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise DataError(path, f"unreadable instructions list ({e})") from None
