"""Shared helpers of the benchmarks: CLI flags, timing, machine info, JSON output.

Every benchmark is a script ``python benchmarks/NAME.py [--smoke] [--out DIR]``
that writes ``DIR/NAME.json`` (default DIR: ``benchmarks/results``, ignored by
git). ``--smoke`` runs a tiny size so CI keeps the script alive.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def parse_args(description: str, argv=None, extra=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--smoke", action="store_true", help="tiny sizes, for CI")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results")
    parser.add_argument("--repeats", type=int, default=None)
    if extra is not None:
        extra(parser)
    args = parser.parse_args(argv)
    # The benchmarks measure what the commands run with: the compile cache and its record on.
    import jaxedit

    jaxedit.enable_compilation()
    return args


def machine_info() -> dict:
    import jax

    devices = jax.devices()
    return {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "devices": [d.device_kind for d in devices],
    }


def block(x):
    import jax

    return jax.block_until_ready(x)


def time_fn(fn, *args, repeats: int = 10) -> dict:
    """Compile time (first call) and median/min of ``repeats`` later calls, in ms."""
    t0 = time.perf_counter()
    block(fn(*args))
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        block(fn(*args))
        times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    return {"first_call_ms": 1e3 * first, "compile_ms": 1e3 * max(first - med, 0.0),
            "median_ms": 1e3 * med, "min_ms": 1e3 * min(times), "repeats": repeats}


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, in MiB (Linux: ru_maxrss is KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def write_json(out_dir: Path, name: str, payload: dict) -> Path:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{name}.json"
    payload = {"benchmark": name, "machine": machine_info(), **payload}
    path.write_text(json.dumps(payload, indent=2) + "\n")
    print(f"wrote {path}")
    return path
