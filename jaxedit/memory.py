"""The free-memory check every size read from a flag, config or file header goes
through (:func:`require_memory`) before anything is allocated.
"""

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
    """Refuse up front work whose estimated working set exceeds the free memory.

    Args:
      where: the flag(s) or file that set the size, for the message.
      needed: estimated bytes.
      what: what the bytes are for, in words.
    Raises:
      DataError: naming ``where``.
    """
    free = available_memory()
    if needed > free:
        raise DataError(where, f"{what} would need about {gib(needed)} of memory, "
                        f"this machine has {gib(free)} free")


def gib(nbytes: float) -> str:
    """``nbytes`` in GiB, three significant digits."""
    return f"{nbytes / 2**30:.3g} GiB"
