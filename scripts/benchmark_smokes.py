"""Every benchmark's ``--smoke`` run, a few at a time, so that none of them rots (CI's last step).

    python scripts/benchmark_smokes.py [--jobs N] [--out DIR] [NAME ...]

Runs ``python benchmarks/NAME.py --smoke --out DIR`` for every benchmark script (or the NAMEs
given), ``--jobs`` processes at once (default: the machine's cores, at most 4). XLA compiles a
program on one core, so two smokes on two cores finish sooner than one after the other. They
share one persistent compilation cache (a fresh folder, unless ``JAXEDIT_COMPILE_CACHE_DIR`` is
set), so a program that one smoke compiled is read back by the next; the benchmarks that time a
cold start (``first_use``, ``real_scale``) give their runs caches of their own.

Prints a line per finished smoke with its seconds; a smoke that fails has the tail of its output
printed, and the script exits 1 once all have run. The slowest smokes start first (the order
below), so that the last one to finish is a short one.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "benchmarks"
NOT_BENCHMARKS = {"__init__.py", "common.py"}
#: Smokes measured on the 2-core CPU to take a minute or more; they start first.
SLOW_FIRST = ("first_use", "real_scale", "ablation", "budget_ablation", "editor_quality",
              "local_edit", "test_suite", "edit_pipeline", "edit_targets")


def benchmark_names() -> list[str]:
    names = sorted(p.stem for p in BENCHMARKS.glob("*.py") if p.name not in NOT_BENCHMARKS)
    return sorted(names, key=lambda n: (SLOW_FIRST.index(n) if n in SLOW_FIRST
                                        else len(SLOW_FIRST), n))


def run_smoke(name: str, out: Path, env: dict) -> tuple[str, int, float, str]:
    """(name, exit status, seconds, output) of one benchmark's smoke run."""
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, str(BENCHMARKS / f"{name}.py"), "--smoke", "--out",
                           str(out)], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, text=True)
    return name, done.returncode, time.perf_counter() - t0, done.stdout


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", help="benchmarks to run (default: all)")
    parser.add_argument("--jobs", type=int, default=min(4, os.cpu_count() or 1))
    parser.add_argument("--out", type=Path, default=None,
                        help="where the smokes write their JSON (default: a temporary folder)")
    args = parser.parse_args(argv)
    known = benchmark_names()
    unknown = [n for n in args.names if n not in known]
    if unknown:
        parser.exit(2, f"error: no benchmark named {', '.join(unknown)} in {BENCHMARKS}\n")
    if args.jobs < 1:
        parser.exit(2, f"error: --jobs: must be at least 1, got {args.jobs}\n")
    names = [n for n in known if n in args.names] if args.names else known
    with tempfile.TemporaryDirectory(prefix="jaxedit-smokes-") as tmp:
        out = args.out or Path(tmp) / "results"
        env = dict(os.environ)
        env.setdefault("JAXEDIT_COMPILE_CACHE_DIR", str(Path(tmp) / "xla"))
        t0, failed = time.perf_counter(), []
        with ThreadPoolExecutor(args.jobs) as pool:
            futures = [pool.submit(run_smoke, n, out, env) for n in names]
            for future in as_completed(futures):
                name, status, seconds, output = future.result()
                print(f"benchmark smoke {name}: {'ok' if status == 0 else f'FAILED ({status})'}"
                      f" in {seconds:.0f} s", flush=True)
                if status != 0:
                    failed.append(name)
                    print(output[-4000:], flush=True)
    print(f"{len(names) - len(failed)} of {len(names)} benchmark smokes passed in "
          f"{time.perf_counter() - t0:.0f} s with {args.jobs} at a time", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
