"""Steering on the demo scene: the first snapshot of a refine, a branch and an extension,
against one of the run's own subtasks.

    python benchmarks/steer.py [--smoke] [--out DIR] [--work DIR]

Runs the demo (the person, reconstructed, edited by the bundled InstructPix2Pix), then from
its run directory, each as a new process the way a user starts it: ``edit --out RUN --from K
--refine`` (K: the run's hardest edit step), ``--from K --prompt P2`` (another instruction of
the bundled editor), ``--extend 1.25``, and (not in the smoke) the refine again in a copy of the run. Each is
stopped once its first snapshot is on disk. Per operation: seconds from the command's start
to that snapshot, its first subtask's training seconds, and its editor calls for the
schedule; against the run's own subtasks (the mean wall time between consecutive snapshots
and the mean training seconds). The two refines' first snapshots are compared byte for byte.
Writes ``DIR/steer.json``. ``--smoke``: the person at 32 px, 4 views, a few steps.
"""

from __future__ import annotations

import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import machine_info, parse_args, write_json

ROOT = Path(__file__).resolve().parents[1]


def extra(p):
    p.add_argument("--work", type=Path, default=None,
                   help="keep the demo and the branches here (default: a temp dir)")


def demo(out: Path, smoke: bool) -> None:
    small = ["--size", "32", "--views", "4", "--test-views", "1", "--iters", "30",
             "--max-steps", "20", "--patience", "5", "--turntable-frames", "0",
             "--ip2p-steps", "1", "--target-subtasks", "2"] if smoke else []
    subprocess.run([sys.executable, "-m", "experiments", "demo", "--out", str(out), "--quiet",
                    *small], cwd=ROOT, check=True, stdout=subprocess.DEVNULL)


def first_snapshot(run: Path, name: str, argv: list[str], timeout: float = 3600.0) -> dict:
    """Start ``edit --out run ARGV`` and stop it once branch ``name`` has a snapshot."""
    schedule = run / "branches" / name / "schedule.json"
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "experiments", "edit", "--out", str(run),
                             "--name", name, "--quiet", "--no-report", *argv], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    record = None
    while record is None:
        if proc.poll() is not None and not schedule.is_file():
            raise RuntimeError(f"edit {' '.join(argv)} failed: {proc.stderr.read()[-2000:]}")
        if time.perf_counter() - t0 > timeout:
            proc.kill()
            raise RuntimeError(f"edit {' '.join(argv)}: no snapshot in {timeout:.0f} s")
        time.sleep(0.2)
        try:
            done = [r for r in json.loads(schedule.read_text())["subtasks"] if r.get("snapshot")]
        except (FileNotFoundError, ValueError):
            continue
        record = done[0] if done else None
    seconds = time.perf_counter() - t0
    proc.kill()
    proc.wait()
    header = json.loads(schedule.read_text())
    return {"argv": argv, "first_snapshot_s": seconds, "first_subtask_train_s": record["seconds"],
            "first_ratio": record["ratio"], "steps": record["steps"],
            "editor_calls_for_schedule": header["editor_calls_for_schedule"],
            "snapshot": str(schedule.parent / record["snapshot"])}


def run_subtasks(run: Path) -> dict:
    """The run's own subtasks: mean training seconds, mean wall seconds between snapshots."""
    records = [r for r in json.loads((run / "schedule.json").read_text())["subtasks"]
               if r.get("snapshot")]
    stamps = sorted((run / r["snapshot"]).parent.joinpath("metrics.json").stat().st_mtime
                    for r in records)
    gaps = [b - a for a, b in zip(stamps, stamps[1:])]
    return {"subtasks": len(records),
            "train_s_mean": statistics.mean(float(r["seconds"]) for r in records),
            "snapshot_interval_s_mean": statistics.mean(gaps) if gaps else None,
            "snapshot_intervals_s": gaps}


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv, extra)
    from jaxedit.editors import instructions

    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        t0 = time.perf_counter()
        if not (work / "demo" / "edit" / "metrics.json").exists():
            demo(work / "demo", args.smoke)
        demo_s = time.perf_counter() - t0
        run = work / "demo" / "edit"
        main_schedule = json.loads((run / "schedule.json").read_text())
        edits = [r for r in main_schedule["subtasks"] if r["kind"] == "edit"]
        hardest = max(edits, key=lambda r: r["difficulty"] or 0.0)["index"]
        other = next(i["prompt"] for i in instructions() if i["prompt"] != main_schedule["prompt"])
        copy = work / "copy"
        shutil.rmtree(copy, ignore_errors=True)
        shutil.copytree(run, copy)
        own = run_subtasks(run)
        ops = {"refine": first_snapshot(run, "refine", ["--from", str(hardest), "--refine"]),
               "branch": first_snapshot(run, "branch", ["--from", str(hardest), "--prompt", other]),
               "extend": first_snapshot(run, "extend", ["--extend", "1.25"])}
        same = None  # the smoke keeps CI short: no second refine
        if not args.smoke:
            again = first_snapshot(copy, "refine", ["--from", str(hardest), "--refine"])
            same = (Path(again["snapshot"]).read_bytes()
                    == Path(ops["refine"]["snapshot"]).read_bytes())
        for name, op in ops.items():
            op["vs_run_subtask"] = (op["first_snapshot_s"] / own["snapshot_interval_s_mean"]
                                    if own["snapshot_interval_s_mean"] else None)
            print(f"{name}: first snapshot in {op['first_snapshot_s']:.1f} s "
                  f"({op['vs_run_subtask']:.2f}x the run's {own['snapshot_interval_s_mean']:.1f} s "
                  f"a subtask), {op['editor_calls_for_schedule']} editor calls for its schedule",
                  flush=True)
            op.pop("snapshot")
    write_json(args.out, "steer", {
        "smoke": args.smoke, "scene": "person (the demo)", "demo_s": demo_s,
        "prompt": main_schedule["prompt"], "branch_prompt": other, "refined_node": hardest,
        "threshold": main_schedule["threshold"], "run": own, "operations": ops,
        "refine_twice_same_first_snapshot": same, "goal_vs_run_subtask": 1.5,
        "machine": machine_info()})


if __name__ == "__main__":
    main()
