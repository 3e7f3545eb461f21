"""Finding model weights on disk, never on the network.

Real models (InstructPix2Pix, CLIP) load from a local folder, or from a Hub id
that is already in the local Hugging Face cache. Anything else is a
:class:`DataError` naming the missing thing and how to obtain it.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from ..errors import DataError

_HUB_ID = re.compile(r"[\w.-]+/[\w.-]+")


def local_model_folder(path: str | os.PathLike, *, what: str, how_to_get: str) -> Path:
    """``path`` as a local folder: itself when it exists, else the cached snapshot of a Hub id.

    Args:
      path: a folder, or an ``owner/name`` Hub id present in the local cache.
      what: the model's name for the error message ("CLIP weights").
      how_to_get: how to obtain the weights, appended to every error.
    """
    p = Path(os.path.expanduser(str(path)))
    if p.exists():
        if not p.is_dir():
            raise DataError(p, f"is not a folder; needs {how_to_get}")
        return p
    if not _HUB_ID.fullmatch(str(path)):
        raise DataError(p, f"{what} folder not found; needs {how_to_get}")
    try:
        from huggingface_hub import snapshot_download

        return Path(snapshot_download(str(path), local_files_only=True))
    except Exception:  # noqa: BLE001 - ImportError, LocalEntryNotFoundError and friends
        raise DataError(path, f"not a folder and not in the local Hugging Face cache; "
                        f"needs {how_to_get}") from None
