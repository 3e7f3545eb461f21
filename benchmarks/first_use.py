"""What a newcomer gets: the README's demo from an empty cache, then the same demo again.

    python benchmarks/first_use.py [--out DIR]              # the README's demo, cold then warm
    python benchmarks/first_use.py --smoke                  # a tiny demo, for CI
    python benchmarks/first_use.py --collect COLD WARM      # demo folders already run (GPU script)

Each pass is ``python -m experiments demo`` in a fresh process with ``JAXEDIT_CACHE`` set to
one new, empty folder: the first pass finds nothing (no compiled programs, no weights but the
bundled ones), the second finds what the first left (the persistent compilation cache). Run it
from a fresh clone with nothing installed by hand for the figure the README quotes. Writes
``first_use.json``: ``demo_cold_s`` and ``demo_warm_s`` (the demo's own total), the wall time of
each process (imports included), the stage times, the schedule (distance, ratios) and the
compiles of each run (count, seconds, persistent-cache hits, per program).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import parse_args, write_json

#: A demo of seconds for CI: the same stages and programs at the smallest sizes.
SMOKE_FLAGS = ["--size", "32", "--views", "4", "--test-views", "1", "--iters", "30",
               "--subtasks", "1", "--max-steps", "40", "--difficulty-views", "2",
               "--ip2p-steps", "2", "--turntable-frames", "0"]


def _extra(p):
    p.add_argument("--collect", nargs=2, type=Path, default=None, metavar=("COLD", "WARM"),
                   help="summarise two demo folders already run instead of running them")
    p.add_argument("--name", default="first_use", help="JSON file name (without .json)")


def summarise(run_dir: Path) -> dict:
    """The figures of one finished demo folder."""
    m = json.loads((run_dir / "metrics.json").read_text())
    schedule = json.loads((run_dir / "edit" / "schedule.json").read_text())
    return {"demo_s": m["total_s"], "stage_s": m["stage_s"], "subtask_s": m["subtask_s"],
            "distance": schedule.get("distance"),
            "ratios": [s.get("ratio") for s in schedule.get("subtasks", [])],
            "compiles": m["compiles"]}


def run_demo(out: Path, cache: Path, flags: list[str]) -> float:
    """One demo in a fresh process -> its wall time in seconds (imports included)."""
    env = {**os.environ, "JAXEDIT_CACHE": str(cache)}
    for name in ("JAXEDIT_COMPILE_CACHE", "JAXEDIT_COMPILE_CACHE_DIR", "JAX_COMPILATION_CACHE_DIR"):
        env.pop(name, None)  # the user's path: the default cache inside JAXEDIT_CACHE
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "experiments", "demo", "--out", str(out),
                           "--quiet", *flags], env=env, capture_output=True, text=True,
                          cwd=Path(__file__).resolve().parents[1])
    if done.returncode:
        sys.exit(f"demo failed:\n{done.stderr[-3000:]}")
    return round(time.perf_counter() - t0, 2)


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv, extra=_extra)
    if args.collect is not None:
        cold, warm = (summarise(d) for d in args.collect)
        process_s = {}
    else:
        flags = SMOKE_FLAGS if args.smoke else []
        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            process_s = {p: run_demo(tmp / p, tmp / "cache", flags) for p in ("cold", "warm")}
            cold, warm = summarise(tmp / "cold"), summarise(tmp / "warm")
            cache_mb = sum(f.stat().st_size for f in (tmp / "cache").rglob("*")
                           if f.is_file()) / 2 ** 20
        print(f"demo cold {cold['demo_s']:.0f} s ({process_s['cold']:.0f} s with imports), "
              f"warm {warm['demo_s']:.0f} s ({process_s['warm']:.0f} s); compiles "
              f"{cold['compiles']['count']} -> {warm['compiles']['count']}, "
              f"{warm['compiles']['cache_hits']} read back", flush=True)
    payload = {"smoke": args.smoke, "load_average_1min": os.getloadavg()[0],
               "demo_cold_s": cold["demo_s"], "demo_warm_s": warm["demo_s"],
               "process_s": process_s, "cold": cold, "warm": warm}
    if args.collect is None:
        payload["cache_mb"] = round(cache_mb, 1)
    write_json(args.out, args.name, payload)


if __name__ == "__main__":
    main()
