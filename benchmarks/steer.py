"""Steering on the demo scene: the first snapshot of a refine, a branch and an extension,
against one of the run's own subtasks.

    python benchmarks/steer.py [--smoke] [--out DIR] [--work DIR]

Runs the demo (the person, reconstructed, edited by the bundled InstructPix2Pix), then from
its run directory, each as a new process the way a user starts it: ``edit --out RUN --from K
--refine`` (K: the run's hardest edit step), ``--from K --prompt P2`` (another instruction of
the bundled editor), ``--extend 1.25``, and (not in the smoke) the refine and the branch again
in a copy of the run. Each is stopped once its first snapshot is on disk. Then the viewer's
way, each in a fresh copy of the run: the viewer's warm worker started and warmed up
(:class:`experiments.view.WarmWorker`), the operation sent as its button sends it, seconds
from that click to the first snapshot (``viewer``: the median of three fresh workers).
Per command-line operation: seconds from the command's start to that snapshot, split into
stages by the command's log
lines (setup: imports, inputs, editor; start: the start scene's state and the difficulty
oracle; schedule: its edits; compile wait and checkpoint; training; snapshot), the programs it
compiled or read from the compile cache before training, its first subtask's training
seconds and its editor calls for the schedule; against the run's own subtasks (the mean
wall time between consecutive snapshots and the mean training seconds). Goals recorded: the
refined steps' difficulties against the run's threshold, the parent's files unchanged, the
same first snapshot from the same command twice (refine, branch), the extension marked
experimental. Writes ``DIR/steer.json``. ``--smoke``: the person at 32 px, 4 views, a few
steps.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable

from common import machine_info, parse_args, write_json
from experiments.cli import KEPT_RECORD
from jaxedit.io.files import LOCK_NAME

ROOT = Path(__file__).resolve().parents[1]

#: Fresh warm workers per operation the viewer's way (the median is reported).
VIEWER_TRIES = 3
#: The log lines that end each stage before training, in order (prefixes; ``{op}``: the op).
STAGES = (("setup_s", "{op} "), ("start_s", "difficulty distance:"),
          ("schedule_s", "schedule:"), ("compile_wait_s", "training starts:"))
_COMPILED = re.compile(r"training starts: (\d+) programs compiled, (\d+) read from the "
                       r"compile cache \(([\d.]+) s\)")


def extra(p):
    p.add_argument("--work", type=Path, default=None,
                   help="keep the demo and the branches here (default: a temp dir)")


def demo(out: Path, smoke: bool) -> None:
    small = ["--size", "32", "--views", "4", "--test-views", "1", "--iters", "30",
             "--max-steps", "20", "--patience", "5", "--turntable-frames", "0",
             "--ip2p-steps", "1", "--target-subtasks", "2"] if smoke else []
    subprocess.run([sys.executable, "-m", "experiments", "demo", "--out", str(out), "--quiet",
                    *small], cwd=ROOT, check=True, stdout=subprocess.DEVNULL)


def _read_lines(stream, lines: list, t0: float) -> None:
    for line in stream:
        lines.append((time.perf_counter() - t0, line.rstrip("\n")))


def stages(op: str, lines: list, first_snapshot_s: float, train_s: float) -> dict:
    """Seconds of each stage, from the arrival times of the command's log lines."""
    out, last = {}, 0.0
    for key, prefix in STAGES:
        prefix = prefix.format(op=op)
        at = next((t for t, line in lines if line.startswith(prefix)), None)
        out[key] = None if at is None else at - last
        last = last if at is None else at
    out["train_s"] = train_s
    out["snapshot_s"] = first_snapshot_s - last - train_s
    return out


def first_record(schedule: Path, argv: list[str], t0: float, failure: Callable[[], str | None],
                 timeout: float) -> dict:
    """The first finished subtask's record in a branch's ``schedule`` (schedule.json), once
    written; ``failure()`` says why the command ended without one (None while it may yet)."""
    while True:
        why = failure()
        if why is not None:
            raise RuntimeError(f"edit {' '.join(argv)} failed: {why}")
        if time.perf_counter() - t0 > timeout:
            raise RuntimeError(f"edit {' '.join(argv)}: no snapshot in {timeout:.0f} s")
        time.sleep(0.05)
        try:
            done = [r for r in json.loads(schedule.read_text())["subtasks"] if r.get("snapshot")]
        except (FileNotFoundError, ValueError):
            continue
        if done:
            return done[0]


def first_snapshot(run: Path, name: str, op: str, argv: list[str],
                   timeout: float = 3600.0) -> dict:
    """Start ``edit --out run ARGV`` and stop it once branch ``name`` has a snapshot."""
    schedule = run / "branches" / name / "schedule.json"
    load_before = os.getloadavg()[0]
    t0 = time.perf_counter()
    with tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen([sys.executable, "-m", "experiments", "edit", "--out", str(run),
                                 "--name", name, "--no-report", *argv], cwd=ROOT,
                                stdout=subprocess.PIPE, stderr=err, text=True)
        lines: list = []
        reader = threading.Thread(target=_read_lines, args=(proc.stdout, lines, t0), daemon=True)
        reader.start()

        def failure():
            if proc.poll() is None or schedule.is_file():
                return None
            err.seek(0)
            return err.read()[-2000:]

        try:
            record = first_record(schedule, argv, t0, failure, timeout)
            seconds = time.perf_counter() - t0
        finally:
            proc.kill()
            proc.wait()
        reader.join(timeout=5)
    header = json.loads(schedule.read_text())
    compiled = next((m for m in map(_COMPILED.match, (line for _, line in lines)) if m), None)
    return {"argv": argv, "first_snapshot_s": seconds, "first_subtask_train_s": record["seconds"],
            "first_ratio": record["ratio"], "steps": record["steps"],
            "editor_calls_for_schedule": header["editor_calls_for_schedule"],
            "stages": stages(op, lines, seconds, float(record["seconds"])),
            "before_training": None if compiled is None else {
                "programs_compiled": int(compiled[1]), "cache_reads": int(compiled[2]),
                "seconds": float(compiled[3])},
            "experimental": header.get("experimental", False),
            "load_average_1min": [load_before, os.getloadavg()[0]],
            "snapshot": str(schedule.parent / record["snapshot"]), "header": header}


def first_snapshot_warm(run: Path, name: str, argv: list[str], timeout: float = 3600.0) -> dict:
    """The viewer's way: start its warm worker on ``run`` (:class:`experiments.view.WarmWorker`),
    wait until it is warm, send ``edit --out run ARGV`` as a button does, and stop the branch
    (a stop request) once it has a snapshot; seconds from the click to that snapshot."""
    from experiments.view import WarmWorker
    from jaxedit import DataError
    from jaxedit.pipelines.steer_run import request_stop

    schedule = run / "branches" / name / "schedule.json"
    worker = WarmWorker(run)
    try:
        t0 = time.perf_counter()
        if not worker.wait_ready():
            raise RuntimeError(f"the warm worker ended: {worker.warm_up_messages[-5:]}")
        warm_s = time.perf_counter() - t0
        load_before = os.getloadavg()[0]
        t0 = time.perf_counter()
        command = worker([sys.executable, "-m", "experiments", "edit", "--out", str(run),
                          "--name", name, "--no-report", *argv])
        messages: list = []
        reader = threading.Thread(target=lambda: messages.extend(command.stderr), daemon=True)
        reader.start()
        record = first_record(schedule, argv, t0, lambda: None if reader.is_alive() or
                              schedule.is_file() else "".join(messages)[-2000:], timeout)
        seconds = time.perf_counter() - t0
        load_after = os.getloadavg()[0]
        try:
            request_stop(run)
        except DataError:  # it ended already (the smoke's short branches)
            pass
        reader.join(timeout)
    finally:
        worker.close()
    header = json.loads(schedule.read_text())
    return {"argv": argv, "warm_up_s": warm_s, "first_snapshot_s": seconds,
            "first_subtask_train_s": record["seconds"], "first_ratio": record["ratio"],
            "steps": record["steps"],
            "editor_calls_for_schedule": header["editor_calls_for_schedule"],
            "exit_status": command.returncode,
            "load_average_1min": [load_before, load_after]}


def run_subtasks(run: Path) -> dict:
    """The run's own subtasks: mean training seconds, mean wall seconds between snapshots."""
    records = [r for r in json.loads((run / "schedule.json").read_text())["subtasks"]
               if r.get("snapshot")]
    stamps = sorted((run / r["snapshot"]).parent.joinpath("metrics.json").stat().st_mtime
                    for r in records)
    gaps = [b - a for a, b in zip(stamps, stamps[1:])]
    return {"subtasks": len(records),
            "train_s_mean": statistics.mean(float(r["seconds"]) for r in records),
            "train_s": [float(r["seconds"]) for r in records],
            "snapshot_interval_s_mean": statistics.mean(gaps) if gaps else None,
            "snapshot_intervals_s": gaps}


#: What operations add to a run directory (the parent's own files are everything else):
#: the tree, the branches, the oracle's memo (a branch adds its edits), the stop request, the
#: report, the run's lock file (it holds the locking process's id) and the hard link to
#: config.json a command holds while it runs (left behind when the benchmark kills it).
_NOT_THE_PARENTS = ("tree.json", "branches", "difficulty.npz", "control.json", "report.html",
                    LOCK_NAME, KEPT_RECORD)


def parent_digest(run: Path) -> str:
    """sha256 over the main branch's files (paths and bytes), without what branches add."""
    h = hashlib.sha256()
    for path in sorted(p for p in run.rglob("*") if p.is_file()):
        rel = path.relative_to(run)
        if rel.parts[0] in _NOT_THE_PARENTS:
            continue
        h.update(str(rel).encode() + b"\0" + path.read_bytes())
    return h.hexdigest()


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv, extra)
    from jaxedit.compilation import persistent_cache_dir
    from jaxedit.editors import instructions

    cache = persistent_cache_dir()
    cache_entries = (sum(1 for p in cache.glob("*-cache")) if cache is not None
                     and cache.is_dir() else 0)
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        t0, demo_load = time.perf_counter(), [os.getloadavg()[0]]
        if not (work / "demo" / "edit" / "metrics.json").exists():
            demo(work / "demo", args.smoke)
        demo_s = time.perf_counter() - t0
        demo_load.append(os.getloadavg()[0])
        run = work / "demo" / "edit"
        main_schedule = json.loads((run / "schedule.json").read_text())
        edits = [r for r in main_schedule["subtasks"] if r["kind"] == "edit"]
        hardest = max(edits, key=lambda r: r["difficulty"] or 0.0)["index"]
        other = next(i["prompt"] for i in instructions() if i["prompt"] != main_schedule["prompt"])
        copy, pristine = work / "copy", work / "pristine"
        if not (work / "operations.json").is_file():
            for folder in (copy, pristine):
                shutil.rmtree(folder, ignore_errors=True)
                shutil.copytree(run, folder)
        own = run_subtasks(run)
        demo_compiles = json.loads((run / "metrics.json").read_text()).get("compiles")
        before = parent_digest(run)
        argvs = {"refine": ["--from", str(hardest), "--refine"],
                 "branch": ["--from", str(hardest), "--prompt", other],
                 "extend": ["--extend", "1.25"]}
        measured = work / "operations.json"  # kept: the figures survive a later failure
        if measured.is_file():
            ops, parent_unchanged, same = json.loads(measured.read_text())
        else:
            ops = {name: first_snapshot(run, name, name, argvs[name]) for name in argvs}
            parent_unchanged = parent_digest(run) == before
            same = {}  # the smoke keeps CI short: no second run
            if not args.smoke:
                for name in ("refine", "branch"):
                    again = first_snapshot(copy, name, name, argvs[name])
                    same[name] = (Path(again["snapshot"]).read_bytes()
                                  == Path(ops[name]["snapshot"]).read_bytes())
                    ops[name]["again_first_snapshot_s"] = again["first_snapshot_s"]
            for name in argvs:  # the viewer's way: each the first click on a warm worker
                tries = []
                for _ in range(1 if args.smoke else VIEWER_TRIES):
                    shutil.rmtree(work / "viewer", ignore_errors=True)
                    shutil.copytree(pristine, work / "viewer")
                    tries.append(first_snapshot_warm(work / "viewer", name, argvs[name]))
                median = sorted(tries, key=lambda t: t["first_snapshot_s"])[len(tries) // 2]
                ops[name]["viewer"] = dict(median, tries_first_snapshot_s=[
                    t["first_snapshot_s"] for t in tries])
            measured.write_text(json.dumps([ops, parent_unchanged, same]))
        refine_header = ops["refine"]["header"]
        halves = [r["difficulty"] for r in refine_header["subtasks"]
                  if r["kind"] == "edit"][:2]
        for name, op in ops.items():
            for way in (op, op["viewer"]):
                way["vs_run_subtask"] = (way["first_snapshot_s"] / own["snapshot_interval_s_mean"]
                                         if own["snapshot_interval_s_mean"] else None)
            print(f"{name}: first snapshot in {op['first_snapshot_s']:.1f} s from the command "
                  f"line ({op['vs_run_subtask']:.2f}x the run's {own['snapshot_interval_s_mean']:.1f} s "
                  f"a subtask), {op['viewer']['first_snapshot_s']:.1f} s from the viewer "
                  f"({op['viewer']['vs_run_subtask']:.2f}x; its worker warmed up in "
                  f"{op['viewer']['warm_up_s']:.1f} s), {op['editor_calls_for_schedule']} editor "
                  f"calls for its schedule; command line stages "
                  f"{', '.join(f'{k} {v:.1f}' for k, v in op['stages'].items() if v is not None)}",
                  flush=True)
            op.pop("snapshot")
            op.pop("header")
    threshold = main_schedule["threshold"]
    write_json(args.out, "steer", {
        "smoke": args.smoke, "scene": "person (the demo)", "demo_s": demo_s,
        "demo_load_average_1min": demo_load,
        "compile_cache": {"entries_before_the_demo": cache_entries,
                          "note": "the demo and the operations share one persistent cache"},
        "demo_compiles": demo_compiles,
        "prompt": main_schedule["prompt"], "branch_prompt": other, "refined_node": hardest,
        "threshold": threshold, "run": own, "operations": ops,
        "goals": {
            "vs_run_subtask_at_most": 1.5,
            "vs_run_subtask_met": {
                way: all(o["vs_run_subtask"] is not None and o["vs_run_subtask"] <= 1.5
                         for o in (ops.values() if way == "command_line" else
                                   (op["viewer"] for op in ops.values())))
                for way in ("viewer", "command_line")},
            "refined_steps_difficulty": halves,
            "refined_steps_at_most_threshold": all(d is not None and d <= threshold + 1e-12
                                                   for d in halves),
            "parent_files_unchanged": parent_unchanged,
            "same_command_twice_same_first_snapshot": same or None,
            "extend_marked_experimental": bool(ops["extend"]["experimental"])},
        "machine": machine_info()})


if __name__ == "__main__":
    main()
