"""The free-memory check every size from a flag, config or file header passes before allocation."""

from __future__ import annotations

import os
from pathlib import Path

from .errors import DataError

#: Bytes a Gaussian costs in training at degree-3 SH: 59 float32 parameters, each with a
#: gradient and two Adam moments, and the densification statistics (about 1 KiB).
GAUSSIAN_BYTES = 1024


def working_set(num_views: int, height: int, width: int, channel_bytes: int,
                max_gaussians: int) -> float:
    """Estimated bytes of fitting Gaussians to views (reconstruct, edit): the views on the
    host and on a device (``channel_bytes`` 1 for uint8), one float32 copy of them (the
    training images of an edit; the random start and the evaluation of a reconstruction)
    and ``max_gaussians`` Gaussians (:data:`GAUSSIAN_BYTES` each)."""
    views = num_views * height * width * 3
    return views * (2 * channel_bytes + 4) + max_gaussians * GAUSSIAN_BYTES


#: Suffixes of network weight files.
WEIGHT_SUFFIXES = (".safetensors", ".bin", ".npz", ".msgpack")


def weight_file_bytes(folder) -> int:
    """Bytes of the weight files under ``folder`` (as stored: a lower bound of the weights
    in memory)."""
    return sum(f.stat().st_size for f in Path(folder).rglob("*")
               if f.suffix in WEIGHT_SUFFIXES and f.is_file())


def available_memory() -> int:
    """Bytes of memory a new allocation can get now (MemAvailable; else physical memory)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def require_memory(where, needed: float, what: str) -> None:
    """Raise a DataError naming ``where`` (the flag or file that set the size) when
    ``needed`` estimated bytes for ``what`` exceed the free memory."""
    free = available_memory()
    if needed > free:
        raise DataError(where, f"{what} would need about {gib(needed)} of memory, "
                        f"this machine has {gib(free)} free")


def gib(nbytes: float) -> str:
    """``nbytes`` in GiB, three significant digits."""
    return f"{nbytes / 2**30:.3g} GiB"
