"""One entry point for every splat file: the format from the name, and from the bytes for .ply.

=================  ==========================  ==============================================
format             file names                  module
=================  ==========================  ==============================================
``ply``            ``*.ply`` (INRIA layout)    :mod:`jaxedit.io.ply`, lossless float32
``compressed-ply`` ``*.compressed.ply``, or a  :mod:`.compressed_ply`, PlayCanvas chunks
                   ``*.ply`` with packed fields
``spz``            ``*.spz``                   :mod:`.spz`, Niantic v2-v4 (v4 written)
``sog``            ``*.sog``, ``meta.json``    :mod:`.sog`, PlayCanvas SOG v2
``splat``          ``*.splat``                 :mod:`.splat`, antimatter15, no SH
=================  ==========================  ==============================================

Reading a ``.ply`` looks at its header, so either PLY layout loads whatever the name says.
"""

from __future__ import annotations

import os
from pathlib import Path

from ...errors import DataError
from ...gaussians import Gaussians
from .. import ply
from . import compressed_ply, sog, splat, spz

FORMATS = ("ply", "compressed-ply", "spz", "sog", "splat")

#: The file name ending each format is written under (format_from_name reads it back).
SUFFIXES = {"ply": ".ply", "compressed-ply": ".compressed.ply", "spz": ".spz", "sog": ".sog",
            "splat": ".splat"}


def format_from_name(path: str | os.PathLike) -> str:
    """The format a file name asks for when writing; DataError for an unknown extension."""
    name = Path(path).name.lower()
    if name.endswith(".compressed.ply"):
        return "compressed-ply"
    for ext, fmt in ((".ply", "ply"), (".spz", "spz"), (".sog", "sog"), (".json", "sog"),
                     (".splat", "splat")):
        if name.endswith(ext):
            return fmt
    raise DataError(path, "unknown splat file extension (expected .ply, .compressed.ply, .spz, "
                          ".sog, meta.json or .splat)")


def scene_format(path: str | os.PathLike) -> str:
    """The format of an existing file: its extension, and for a .ply its header."""
    fmt = format_from_name(path)
    if fmt in ("ply", "compressed-ply"):
        try:
            with open(path, "rb") as f:
                head = f.read(1 << 16)
        except FileNotFoundError:
            raise DataError(path, "file not found") from None
        except IsADirectoryError:
            raise DataError(path, "is a directory, expected a splat file") from None
        except OSError as e:
            raise DataError(path, f"cannot read file ({e.strerror or e})") from None
        return "compressed-ply" if compressed_ply.is_compressed_ply(head) else "ply"
    return fmt


def load_scene(path: str | os.PathLike) -> Gaussians:
    """Read a splat file of any supported format into Gaussians (all slots alive).

    Raises:
      DataError: unknown extension, missing or malformed file (naming the file and the problem).
    """
    fmt = scene_format(path)
    if fmt == "ply":
        return ply.load_ply(path)
    loader = {"compressed-ply": compressed_ply.load_compressed_ply, "spz": spz.load_spz,
              "sog": sog.load_sog, "splat": splat.load_splat}[fmt]
    return loader(path)


def save_scene(path: str | os.PathLike, gaussians: Gaussians, *, format: str | None = None) -> Path:
    """Write the alive Gaussians in the format of ``path``'s name (or ``format``), atomically.

    ``format`` is one of :data:`FORMATS`; it overrides the extension (e.g. a compressed PLY
    under a plain ``.ply`` name). Returns the path written.
    """
    fmt = format_from_name(path) if format is None else format
    if fmt not in FORMATS:
        raise DataError("format", f"must be one of {', '.join(FORMATS)}, got {fmt!r}")
    saver = {"ply": ply.save_ply, "compressed-ply": compressed_ply.save_compressed_ply,
             "spz": spz.save_spz, "sog": sog.save_sog, "splat": splat.save_splat}[fmt]
    return saver(path, gaussians)
