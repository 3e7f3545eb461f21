"""What a persistent-cache write costs as the cache folder fills, bounded by JAX or by jaxedit.

    python benchmarks/compile_cache.py [--smoke] [--out DIR]

JAX bounds its compilation cache (``jax_compilation_cache_max_size``) inside every write: under
a file lock that every process sharing the folder takes for reads too, it lists the folder and
reads each entry's access-time file. jaxedit leaves JAX unbounded and bounds the folder once per
process instead (:func:`jaxedit.compilation.trim_cache`). For folders of N entries (20 KB each,
the size of a small CPU program), this times one write through JAX's cache object both ways
and one ``trim_cache`` pass, the median of ``--repeats`` each.

The folders are filled by writing the entry files directly, in the layout JAX's cache uses
(``KEY-cache`` and, for the bounded folder, ``KEY-atime``): filling a bounded folder through JAX
costs the sum of those writes, quadratic in N. JAX's cache class is private API
(``jax._src.lru_cache``); the benchmark pins what it measured to the JAX version in
``machine``. ``--smoke``: 100 and 200 entries.
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from pathlib import Path

from common import parse_args, write_json

ENTRY_BYTES = 20_000
BOUND = 4096 * 2 ** 20  # jaxedit's default bound


def fill(folder: Path, n: int, *, atime_files: bool) -> None:
    """``n`` entries of ENTRY_BYTES in JAX's cache layout."""
    folder.mkdir(parents=True)
    payload = os.urandom(ENTRY_BYTES)
    for i in range(n):
        (folder / f"entry{i:06d}-cache").write_bytes(payload)
        if atime_files:
            (folder / f"entry{i:06d}-atime").write_bytes(time.time_ns().to_bytes(8, "little"))


def timed_writes(cache, repeats: int) -> float:
    """Median seconds of one new entry's write through ``cache`` (a JAX LRUCache)."""
    times = []
    for r in range(repeats):
        t0 = time.perf_counter()
        cache.put(f"new{r:04d}", b"x" * ENTRY_BYTES)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def measure(n: int, root: Path, repeats: int) -> dict:
    from jax._src.lru_cache import LRUCache

    from jaxedit.compilation import trim_cache

    bounded, unbounded = root / f"bounded{n}", root / f"unbounded{n}"
    fill(bounded, n, atime_files=True)
    fill(unbounded, n, atime_files=False)
    jax_bounded = timed_writes(LRUCache(str(bounded), max_size=BOUND), repeats)
    jax_unbounded = timed_writes(LRUCache(str(unbounded), max_size=-1), repeats)
    trims = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        trim_cache(unbounded, BOUND)
        trims.append(time.perf_counter() - t0)
    return {"entries": n, "write_ms_bounded_by_jax": round(1e3 * jax_bounded, 3),
            "write_ms_unbounded": round(1e3 * jax_unbounded, 3),
            "trim_cache_ms": round(1e3 * statistics.median(trims), 3)}


def main(argv=None) -> None:
    args = parse_args(__doc__.splitlines()[0], argv)
    sizes = (100, 200) if args.smoke else (500, 1000, 2000, 4000)
    repeats = args.repeats or 5
    with tempfile.TemporaryDirectory(prefix="jaxedit-cache-bench-") as tmp:
        rows = [measure(n, Path(tmp), repeats) for n in sizes]
    for r in rows:
        print(f"{r['entries']:5d} entries: a write {r['write_ms_bounded_by_jax']:8.2f} ms "
              f"bounded by JAX, {r['write_ms_unbounded']:6.2f} ms unbounded; "
              f"trim_cache {r['trim_cache_ms']:6.2f} ms (once per process)")
    write_json(args.out, "compile_cache", {
        "smoke": args.smoke, "entry_bytes": ENTRY_BYTES, "bound_bytes": BOUND,
        "repeats": repeats, "sizes": rows})


if __name__ == "__main__":
    main()
