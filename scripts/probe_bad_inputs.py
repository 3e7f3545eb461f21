"""Throw a broad set of bad inputs at every command; each must exit 2 with one line naming it.

    PYTHONPATH=$PWD JAX_PLATFORMS=cpu python scripts/probe_bad_inputs.py [--only WORD] [--list]

Builds its inputs in a temporary folder (a tiny dataset, a scene, photos, runs with
broken checkpoints, files with names that are not UTF-8), then runs every case through
:func:`experiments.cli.main` in-process with stderr captured at the descriptor level.
A case passes when the command exits 2, prints exactly one stderr line, no traceback,
and that line contains the case's needle (the flag or the path as the user gave it).
Cases are generated per class: every float flag gets inf/-inf/nan, every int flag a
word, every input path a missing and a non-UTF-8 name, and so on. Prints the failures
and the counts; a case that runs longer than ``--timeout`` seconds counts as a failure
(a bad input must be refused before the work starts).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np


PROMPT = "turn him into a bronze statue"  # one the simulated editor knows


def _inputs(root: Path) -> dict:
    """Every file the cases refer to, built once."""
    from jaxedit import camera as camlib, gaussians as G
    from jaxedit.io import save_nerfstudio, save_ply, write_image

    rng = np.random.default_rng(0)
    cams = camlib.hemisphere(4, radius=2.2, width=16, height=16, fov_deg=50.0)
    images = rng.uniform(0.2, 0.8, size=(4, 16, 16, 3)).astype(np.float32)
    pts = rng.normal(scale=0.3, size=(50, 3)).astype(np.float32)
    data = save_nerfstudio(root / "data", images, cams, test_indices=np.array([1]), points=pts,
                           point_colors=rng.uniform(size=(50, 3)).astype(np.float32)).parent
    scene = root / "scene.ply"
    save_ply(scene, G.from_points(pts, rng.uniform(size=(50, 3)), sh_degree=0))
    photos = root / "photos"
    for k in range(3):
        write_image(photos / f"p{k}.png", images[k])
    # A photo folder where one name is not UTF-8.
    badname = root / "photos_badname"
    for k in range(3):
        write_image(badname / f"p{k}.png", images[k])
    os.rename(badname / "p2.png", os.path.join(os.fsencode(badname), b"p\xff.png"))
    # A dataset whose transforms.json names a file that is not UTF-8 (JSON's \udcff escape).
    badjson = save_nerfstudio(root / "data_badname", images, cams, test_indices=np.array([1])).parent
    meta = json.loads((badjson / "transforms.json").read_text())
    first = meta["frames"][0]["file_path"]
    renamed = first.replace(".png", "\udcff.png")
    os.rename(badjson / first, os.fsencode(badjson) + b"/" + os.fsencode(renamed))
    text = json.dumps(meta).replace(json.dumps(first), json.dumps(renamed))
    (badjson / "transforms.json").write_text(text)
    # Runs whose checkpoint is empty or garbage.
    runs = {}
    for kind, content in [("empty", b""), ("garbage", b"PK\x03\x04" + bytes(range(256)) * 4),
                          ("text", b"not a checkpoint\n")]:
        run = root / f"run_{kind}"
        (run / "checkpoints").mkdir(parents=True)
        (run / "checkpoints" / "ckpt_00000020.npz").write_bytes(content)
        (run / "checkpoint.npz").write_bytes(content)
        runs[kind] = run
    edit_run = root / "edit_run"
    (edit_run / "subtasks" / "00").mkdir(parents=True)
    (edit_run / "config.json").write_text('{"command": "edit", "mine": true}\n')
    (edit_run / "subtasks" / "00" / "scene.ply").write_bytes(scene.read_bytes())
    (edit_run / "schedule.json").write_text(json.dumps({"subtasks": [
        {"index": 0, "name": "r0", "ratio": 0.5, "snapshot": "subtasks/00/scene.ply"},
        {"index": 1, "name": "r1", "ratio": 1.0, "snapshot": "subtasks/01/scene.ply"}]}))
    (root / "afile").write_text("x\n")
    (root / "emptydir").mkdir()
    return _paths(root)


def _paths(root: Path) -> dict:
    """Where :func:`_inputs` put everything."""
    return dict(data=root / "data", scene=root / "scene.ply", photos=root / "photos",
                badname=root / "photos_badname", badjson=root / "data_badname",
                runs={k: root / f"run_{k}" for k in ("empty", "garbage", "text")},
                edit_run=root / "edit_run", afile=root / "afile")


def _base(command: str, inp: dict, out: str) -> list[str]:
    """A valid command line of ``command`` writing to ``out``."""
    return {
        "make-scene": ["make-scene", "ball", "--out", out],
        "reconstruct": ["reconstruct", "--data", str(inp["data"]), "--out", out],
        "render": ["render", "--scene", str(inp["scene"]), "--out", out],
        "edit": ["edit", "--data", str(inp["data"]), "--scene", str(inp["scene"]), "--prompt",
                 PROMPT, "--out", out],
        "demo": ["demo", "--out", out],
        "ablation": ["ablation", "--out", out],
        "bench": ["bench", "--out", out],
        "report": ["report", str(inp["data"]), "--output", out + ".html"],
        "convert-lpips": ["convert-lpips", "--out", out],
        "clip-metrics": ["clip-metrics", "--run", str(inp["edit_run"]), "--caption-orig", "a",
                         "--caption-edit", "b", "--out", out],
        "view": ["view", str(inp["edit_run"])],
        "process-data": ["process-data", "--images", str(inp["photos"]), "--out", out],
    }[command]


def cases(inp: dict, root: Path) -> list[tuple[str, list[str], str, Path | None]]:
    """(name, argv, needle (or a tuple of acceptable ones), file that must stay unchanged)."""
    from experiments import cli

    out_rel = os.path.relpath(root / "o", Path.cwd())
    subs = cli.build_parser().commands
    found = []
    for command, sub in subs.items():
        base = _base(command, inp, out_rel)
        for action in sub.arguments:
            if not action.option_strings or action.dest in ("help", "out", "output"):
                continue
            flag = action.option_strings[-1]
            nargs = action.nargs if isinstance(action.nargs, int) else 1
            if action.type is float:
                for bad in ("inf", "-inf", "nan", "1e999"):
                    found.append((f"{command} {flag} {bad}", base + [flag] + [bad] * nargs, flag,
                                  None))
            elif action.type is int:
                for bad in ("x", "1.5", "1e3"):
                    found.append((f"{command} {flag} {bad}", base + [flag] + [bad] * nargs, flag,
                                  None))
            elif action.type is Path and action.dest != "config":
                given = "no/such/path"
                args = [a for a in base]
                if flag == "--video":  # instead of --images, not beside it
                    args[args.index("--images"):args.index("--images") + 2] = []
                if flag in args:  # replace the valid value
                    i = args.index(flag)
                    args[i + 1] = given
                else:
                    args += [flag, given]
                found.append((f"{command} {flag} missing", args, given, None))
                # The wrong kind of thing: a one-line text file, an empty folder.
                for kind, wrong in (("a text file", "afile"), ("an empty folder", "emptydir")):
                    bad = [wrong if a == given else a for a in args]
                    found.append((f"{command} {flag} {kind}", bad, (wrong, flag), None))
        # Positional paths (report, view): a missing one.
        if command in ("report", "view"):
            args = [a if a not in (str(inp["data"]), str(inp["edit_run"])) else "no/such/run"
                    for a in base]
            found.append((f"{command} RUN_DIR missing", args, "no/such/run", None))
        # Output locations: read-only, under a file; as given (relative).
        if "--out" in base:
            i = base.index("--out")
            for kind, where in [("read-only", "/proc/jaxedit-probe"),
                                ("under-a-file", os.path.relpath(inp["afile"] / "o"))]:
                args = base[:i + 1] + [where] + base[i + 2:]
                found.append((f"{command} --out {kind}", args, where, None))
        # Config files: missing, non-finite values.
        cfg = root / f"cfg_{command}.json"
        float_flags = [a for a in sub.arguments if a.type is float and a.nargs is None]
        if float_flags:
            cfg.write_text('{"%s": Infinity}' % float_flags[0].dest)
            found.append((f"{command} --config Infinity", base + ["--config", str(cfg)],
                          (float_flags[0].dest, float_flags[0].option_strings[-1]), None))
        found.append((f"{command} --config missing", base + ["--config", "no/cfg.json"],
                      "no/cfg.json", None))
    # Non-UTF-8 file names.
    found.append(("process-data non-UTF-8 photo name",
                  ["process-data", "--images", str(inp["badname"]), "--out", out_rel],
                  "\\xff", None))
    for command in ("reconstruct", "edit"):
        args = _base(command, inp, out_rel)
        args[args.index("--data") + 1] = str(inp["badjson"])
        found.append((f"{command} dataset naming a non-UTF-8 file", args, "\\xff", None))
    # Broken checkpoints on --resume.
    for kind, run in inp["runs"].items():
        found.append((f"reconstruct --resume {kind} checkpoint",
                      ["reconstruct", "--data", str(inp["data"]), "--out", str(run), "--resume",
                       "--quiet"], "ckpt_00000020.npz", None))
        found.append((f"edit --resume {kind} checkpoint",
                      ["edit", "--data", str(inp["data"]), "--scene", str(inp["scene"]),
                       "--prompt", PROMPT, "--out", str(run), "--resume", "--quiet"],
                      "checkpoint.npz", None))
        found.append((f"edit --resume-from {kind}",
                      ["edit", "--data", str(inp["data"]), "--scene", str(inp["scene"]),
                       "--prompt", PROMPT, "--out", out_rel, "--resume-from", str(run), "--quiet"],
                      str(run), None))
    # A failed --select must leave the run's record alone.
    for bad in ("abc", "99", "nan", "-5", "inf", "1"):  # 1: its snapshot file is missing
        found.append((f"edit --select-only --select {bad}",
                      ["edit", "--data", str(inp["data"]), "--scene", str(inp["scene"]),
                       "--prompt", PROMPT, "--out", str(inp["edit_run"]), "--select-only",
                       "--select", bad], "--select" if bad != "1" else "scene.ply",
                      inp["edit_run"] / "config.json"))
    # Ablation flag combinations.
    for flags, needle in [(["--methods", "foo"], "--methods"),
                          (["--methods", "nd_equal_steps"], "--methods"),
                          (["--methods", ""], "--methods"),
                          (["--editor-modes", "0"], "--editor-modes"),
                          (["--editor-modes", "x"], "--editor-modes"),
                          (["--scenes", "nope"], "--scenes"), (["--scenes", ""], "--scenes"),
                          (["--prompts", "zzz"], "--prompts"), (["--seeds", "0"], "--seeds")]:
        found.append((f"ablation {' '.join(flags)}",
                      ["ablation", "--out", out_rel, *flags], needle, None))
    return found


def run_case(argv: list[str], timeout: float) -> tuple[int | str, str]:
    """(exit status, "traceback" or "timeout"; stderr) of ``cli.main(argv)`` in a forked child.

    A fork starts at once (everything is imported) and can be killed when a bad input is
    not refused and the command starts its real work.
    """
    with tempfile.TemporaryFile() as err:
        pid = os.fork()
        if pid == 0:  # the child: stderr to the file, stdout to nowhere
            os.dup2(err.fileno(), 2)
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 1)
            sys.stderr = os.fdopen(2, "w", buffering=1)
            sys.stdout = os.fdopen(1, "w")
            from experiments import cli

            try:
                code = cli.main(argv)
            except SystemExit as e:
                code = e.code if isinstance(e.code, int) else 1
            except BaseException:  # noqa: BLE001 - a traceback is what we are looking for
                traceback.print_exc()
                code = 99
            sys.stderr.flush()
            os._exit(code if isinstance(code, int) else 1)
        deadline = time.monotonic() + timeout
        status = None
        while time.monotonic() < deadline:
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                break
            time.sleep(0.05)
        else:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            status = None
        err.seek(0)
        text = err.read().decode("utf-8", "replace")
    if status is None:
        return "timeout", text
    if os.WIFSIGNALED(status):
        return f"signal {os.WTERMSIG(status)}", text
    code = os.WEXITSTATUS(status)
    return ("traceback" if code == 99 else code), text


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--only", default=None, help="run only cases whose name contains this")
    p.add_argument("--list", action="store_true", help="list the cases and stop")
    p.add_argument("--timeout", type=float, default=30.0, help="seconds per case")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        os.chdir(root)  # relative paths in the cases are relative to here
        pid = os.fork()  # the inputs use JAX: build them in a child, keep this one fork-safe
        if pid == 0:
            _inputs(root)
            os._exit(0)
        assert os.waitpid(pid, 0)[1] == 0, "building the inputs failed"
        inp = _paths(root)
        todo = [c for c in cases(inp, root) if args.only is None or args.only in c[0]]
        if args.list:
            print("\n".join(name for name, *_ in todo))
            return 0
        failures = []
        for name, case_argv, needle, keep in todo:
            before = keep.read_bytes() if keep is not None else None
            code, err = run_case(case_argv, args.timeout)
            lines = err.strip().splitlines()
            problem = None
            if code != 2:
                problem = f"exit {code}"
            elif len(lines) != 1 or "Traceback" in err:
                problem = f"{len(lines)} lines"
            elif not any(n in lines[0] for n in ((needle,) if isinstance(needle, str) else needle)):
                problem = f"does not name {needle!r}"
            elif keep is not None and keep.read_bytes() != before:
                problem = f"rewrote {keep.name}"
            if keep is not None and before is not None:
                keep.write_bytes(before)
            out = root / "o"
            if out.exists():  # a case that got as far as writing: start the next one clean
                import shutil
                shutil.rmtree(out, ignore_errors=True)
            if problem:
                failures.append(name)
                print(f"FAIL {name}: {problem}: {(lines[-1] if lines else '')[:200]}")
        print(f"{len(todo) - len(failures)}/{len(todo)} cases exit 2 with one line naming the "
              f"bad input; {len(failures)} do not")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
