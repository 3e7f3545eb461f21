"""``bench``: run every benchmark script and summarise their JSON in markdown.

    python -m experiments bench --out DIR [--smoke] [--only raster,train_step] [--timeout S]

Each ``benchmarks/NAME.py`` (all but ``common.py``) runs in its own process
(``python benchmarks/NAME.py [--smoke] --out DIR/json``), so one crashing or
leaking benchmark cannot take the others down and peak-memory figures are per
benchmark. ``DIR/summary.md`` holds the machine, each benchmark's status and
wall time, and its scalar results; ``DIR/bench.json`` the same as JSON; each
script's output is kept in ``DIR/logs/NAME.log``. A benchmark that fails makes
the command exit with status 1 after the summary is written.
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

from jaxedit.errors import check_ranges, ranged

HELP = "run the benchmarks in benchmarks/ (each --smoke-able) and write DIR/summary.md"

BENCH_DIR = Path(__file__).resolve().parents[1] / "benchmarks"
SKIP = {"__init__", "common"}


@dataclasses.dataclass(frozen=True)
class BenchConfig:
    """What ``bench`` runs and how much of it the summary shows.

    Attributes:
      smoke: tiny sizes (seconds per benchmark).
      only: comma-separated benchmark names to run (None: all).
      timeout: seconds allowed per benchmark before it is stopped.
      max_rows: at most this many result rows per benchmark in the summary.
    """

    smoke: bool = False
    only: str | None = None
    timeout: float = ranged(1800.0, low=0, open=True)
    max_rows: int = ranged(24, low=1)

    def __post_init__(self):
        check_ranges(self)


def _config_flags():
    from experiments.flags import Flag, FlagSet

    return FlagSet(BenchConfig, (Flag("smoke"), Flag("only"), Flag("timeout"),
                                 Flag("max_rows"))).complete()


#: The command's flags, generated from :class:`BenchConfig`.
FLAGS = (_config_flags(),)


def add_arguments(p) -> None:
    FLAGS[0].add_to(p)


def run_config(args) -> BenchConfig:
    """The :class:`BenchConfig` of ``args`` (range errors name the flag)."""
    return FLAGS[0].build(args)


def discover(bench_dir: Path = BENCH_DIR) -> list[str]:
    """Names of the benchmark scripts, sorted."""
    return sorted(p.stem for p in bench_dir.glob("*.py") if p.stem not in SKIP)


def flatten(value, prefix: str = "") -> list[tuple[str, object]]:
    """Scalar leaves of nested JSON as (dotted.path, value); lists by index."""
    if isinstance(value, dict):
        items = []
        for k, v in value.items():
            items += flatten(v, f"{prefix}.{k}" if prefix else str(k))
        return items
    if isinstance(value, list):
        if all(not isinstance(v, (dict, list)) for v in value) and len(value) <= 8:
            return [(prefix, value)]
        items = []
        for i, v in enumerate(value):
            items += flatten(v, f"{prefix}[{i}]")
        return items
    return [(prefix, value)]


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return str(v).replace("|", "\\|").replace("\n", " ")


def machine() -> dict:
    """Machine info without importing jax into this process's hot path."""
    info = {"platform": platform.platform(), "python": platform.python_version(),
            "cpu_count": os.cpu_count(), "processor": platform.processor() or platform.machine()}
    try:
        with open("/proc/meminfo") as f:
            kib = int(next(line for line in f if line.startswith("MemTotal")).split()[1])
        info["memory_gib"] = round(kib / 2**20, 1)
    except (OSError, StopIteration, ValueError):
        pass
    try:
        import jax

        info.update(jax=jax.__version__, backend=jax.default_backend(),
                    devices=[d.device_kind for d in jax.devices()])
    except Exception as e:  # noqa: BLE001 - a summary without jax info is still useful
        info["jax"] = f"unavailable ({e})"
    return info


def run_one(name: str, out: Path, *, smoke: bool, timeout: float,
            bench_dir: Path = BENCH_DIR) -> dict:
    """Run one benchmark script; its status, wall time and parsed JSON result."""
    json_dir = out / "json"
    cmd = [sys.executable, str(bench_dir / f"{name}.py"), "--out", str(json_dir)]
    if smoke:
        cmd.append("--smoke")
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(bench_dir.parent), env.get("PYTHONPATH")]))
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env,
                              cwd=bench_dir.parent)
        rc, log = proc.returncode, proc.stdout + proc.stderr
    except subprocess.TimeoutExpired as e:
        rc = None
        log = ((e.stdout or b"").decode(errors="replace") if isinstance(e.stdout, bytes)
               else (e.stdout or "")) + f"\n[stopped after {timeout:g} s]\n"
    seconds = time.perf_counter() - t0
    (out / "logs").mkdir(parents=True, exist_ok=True)
    (out / "logs" / f"{name}.log").write_text(log)
    record = {"name": name, "command": " ".join(cmd), "seconds": round(seconds, 2),
              "returncode": rc, "status": "ok" if rc == 0 else ("timeout" if rc is None else "failed")}
    result_path = json_dir / f"{name}.json"
    if rc == 0:
        try:
            record["result"] = json.loads(result_path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            record["status"] = "failed"
            record["error"] = f"no readable {result_path.name} ({e})"
    else:
        tail = [line for line in log.strip().splitlines() if line.strip()][-1:]
        record["error"] = tail[0][:300] if tail else "no output"
    return record


def summary_markdown(records: list[dict], info: dict, *, smoke: bool, max_rows: int = 24) -> str:
    lines = ["# jaxedit benchmarks" + (" (smoke sizes)" if smoke else ""), "",
             f"Run {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}.", "", "## Machine", ""]
    lines += [f"- {k}: {_fmt(v)}" for k, v in info.items()]
    lines += ["", "Timings on a shared machine are noisy; compare runs on the same machine only.",
              "", "## Overview", "", "| benchmark | status | wall s | note |", "|---|---|---:|---|"]
    for r in records:
        lines.append(f"| {r['name']} | {r['status']} | {r['seconds']:.1f} | "
                     f"{_fmt(r.get('error', ''))} |")
    for r in records:
        if "result" not in r:
            continue
        leaves = [(k, v) for k, v in flatten(r["result"])
                  if not k.startswith(("machine", "benchmark")) and v is not None]
        lines += ["", f"## {r['name']}", "", "| result | value |", "|---|---:|"]
        lines += [f"| {_fmt(k)} | {_fmt(v)} |" for k, v in leaves[:max_rows]]
        if len(leaves) > max_rows:
            lines.append(f"| ... {len(leaves) - max_rows} more in json/{r['name']}.json | |")
    return "\n".join(lines) + "\n"


def run(args) -> dict:
    from experiments.progress import Progress, configure
    from jaxedit import DataError
    from jaxedit.io.files import atomic_write_text

    if args.out is None:
        raise DataError("--out", "an output directory is required")
    config = run_config(args)
    available = discover()
    names = available
    if config.only:
        names = [n.strip() for n in config.only.split(",") if n.strip()]
        unknown = sorted(set(names) - set(available))
        if unknown:
            raise DataError("--only", f"unknown benchmark(s) {', '.join(unknown)}; "
                                      f"available: {', '.join(available) or 'none'}")
    if not names:
        raise DataError(BENCH_DIR, "no benchmark scripts found")
    configure(quiet=args.quiet)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    records = []
    with Progress(len(names), "bench") as bar:
        for name in names:
            bar.set_postfix(running=name)
            records.append(run_one(name, out, smoke=config.smoke, timeout=config.timeout))
            bar.update(1, last=f"{name}:{records[-1]['status']}")
        bar.postfix.pop("running", None)
    info = machine()
    atomic_write_text(out / "summary.md",
                      summary_markdown(records, info, smoke=config.smoke,
                                       max_rows=config.max_rows))
    atomic_write_text(out / "bench.json", json.dumps(
        {"machine": info, "smoke": config.smoke, "benchmarks": records}, indent=2, default=str) + "\n")
    failed = [r["name"] for r in records if r["status"] != "ok"]
    result = {"summary": str(out / "summary.md"),
              "benchmarks": {r["name"]: {"status": r["status"], "seconds": r["seconds"]}
                             for r in records}}
    atomic_write_text(out / "metrics.json", json.dumps(
        {"failed": failed, "wall_time_s": round(sum(r["seconds"] for r in records), 2),
         **result}, indent=2) + "\n")
    if failed:
        print(json.dumps(result, indent=2))
        print(f"error: benchmark(s) failed: {', '.join(failed)} (see {out / 'logs'})", file=sys.stderr)
        raise SystemExit(1)
    return result
