"""The free-memory check every size from a flag, config or file header passes before allocation."""

from __future__ import annotations

import os

from .errors import DataError


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
