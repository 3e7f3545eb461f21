"""The test suite's own cost: the README's test command, timed, with its compile share.

    python benchmarks/test_suite.py [--out DIR]       # the README's command (the default tier)
    python benchmarks/test_suite.py --tier slow       # the tests marked slow alone
    python benchmarks/test_suite.py --tier all        # both tiers, as CI runs them
    python benchmarks/test_suite.py --smoke           # one small file, for CI

Runs the README's ``python -m pytest tests -n auto`` (``--smoke``: ``tests/test_compilation.py``;
``--tier slow``: ``-m slow`` added, ``--tier all``: ``--slow``, see ``tests/conftest.py``)
in a fresh process with ``JAXEDIT_TEST_PROFILE`` set, so that ``tests/conftest.py`` records each
test's wall time and the XLA compiles it caused in the test process (the CLI tests'
subprocesses compile on their own; their time is in the test's wall time, not in its compile
seconds). With several workers the tests' times add up to more than the wall time. Writes
``test_suite.json`` (``test_suite_slow.json``, ``test_suite_all.json``): the total wall time,
the outcome counts, the compile share, the 20 slowest tests, the programs the suite spends
most compiling, and each file's time against its budget
(:data:`FILE_BUDGET_S`; files over it are listed, not failed: speed is checked here, never by
timed assertions in tests).
"""

from __future__ import annotations

import collections
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import parse_args, write_json

ROOT = Path(__file__).resolve().parents[1]
#: Seconds a test file may take on the 2-core CPU before this benchmark lists it (the
#: suite's goal is 10 minutes for about fifty files).
FILE_BUDGET_S = 60.0
#: Programs listed by their compile seconds summed over the suite (``top_programs``).
TOP_PROGRAMS = 25


#: pytest's arguments for each tier, after ``tests -n auto``.
TIERS = {"default": [], "slow": ["-m", "slow"], "all": ["--slow"]}


def _extra(p):
    p.add_argument("--tier", choices=sorted(TIERS), default="default",
                   help="default: the README's command; slow: the tests marked slow; all: both")
    p.add_argument("--pytest-args", nargs="*", default=None,
                   help="what to run instead of the README's `tests` (e.g. a file)")


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv, extra=_extra)
    targets = args.pytest_args or ["tests/test_compilation.py" if args.smoke else "tests",
                                   "-n", "auto", *TIERS[args.tier]]
    with tempfile.TemporaryDirectory() as tmp:
        profile = Path(tmp) / "profile.jsonl"
        env = {**os.environ, "JAXEDIT_TEST_PROFILE": str(profile), "JAX_PLATFORMS": "cpu"}
        t0 = time.perf_counter()
        done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                               *targets], cwd=ROOT, env=env, capture_output=True, text=True)
        total = time.perf_counter() - t0
        records = [json.loads(line) for line in profile.read_text().splitlines()] \
            if profile.exists() else []
    summary = done.stdout.strip().splitlines()[-1] if done.stdout.strip() else ""
    counts = {k: int(v) for v, k in re.findall(r"(\d+) (passed|failed|skipped|errors?)", summary)}
    failed = [line.split(" ")[1] for line in done.stdout.splitlines()
              if line.startswith(("FAILED ", "ERROR "))]
    if done.returncode not in (0, 1) or not records:
        sys.exit(f"pytest did not run the tests (exit {done.returncode}):\n"
                 f"{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
    per_file = collections.defaultdict(float)
    for r in records:
        per_file[r["test"].split("::")[0]] += r["seconds"]
    compile_s = sum(r["compile_seconds"] for r in records)
    tests_s = sum(r["seconds"] for r in records)
    slowest = [{k: v for k, v in r.items() if k != "programs"}
               for r in sorted(records, key=lambda r: -r["seconds"])[:20]]
    # Which programs the suite compiles most: where sharing one program pays most.
    programs = collections.defaultdict(lambda: [0, 0.0])
    for r in records:
        for name, (count, seconds) in r.get("programs", {}).items():
            programs[name][0] += count
            programs[name][1] += seconds
    top_programs = [{"program": name, "compiles": c, "seconds": round(s, 1)} for name, (c, s)
                    in sorted(programs.items(), key=lambda kv: -kv[1][1])[:TOP_PROGRAMS]]
    payload = {
        "smoke": args.smoke, "tier": args.tier, "command": "python -m pytest " + " ".join(targets),
        "cpu_count": os.cpu_count(),
        "load_average_1min": os.getloadavg()[0], "total_s": round(total, 1),
        "tests_s": round(tests_s, 1), "outcomes": counts, "failed": failed,
        "exit_status": done.returncode,
        "compile_s": round(compile_s, 1),
        "compile_share": round(compile_s / tests_s, 3) if tests_s else None,
        "compiles": sum(r["compiles"] for r in records),
        "cache_hits": sum(r["cache_hits"] for r in records),
        "slowest": slowest,
        "top_programs": top_programs,
        "file_budget_s": FILE_BUDGET_S,
        "files_s": dict(sorted(((f, round(s, 1)) for f, s in per_file.items()),
                               key=lambda kv: -kv[1])),
        "files_over_budget": [f for f, s in per_file.items() if s > FILE_BUDGET_S],
    }
    print(f"{summary}; {total:.0f} s, compiling {compile_s:.0f} s of {tests_s:.0f} s in tests",
          flush=True)
    write_json(args.out, "test_suite" if args.tier == "default" else f"test_suite_{args.tier}",
               payload)


if __name__ == "__main__":
    main()
