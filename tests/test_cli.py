"""The runner: one-line errors with exit status 2, and the render / bench / demo commands.

A few checks run ``python -m experiments`` in a subprocess, exactly as a user
would; the others call :func:`experiments.cli.main` in-process (the same code
path, without paying Python + JAX start-up for each case).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from experiments import bench, cli, demo
from jaxedit import DataError, camera as camlib
from jaxedit.io import read_image, save_nerfstudio, save_ply

ROOT = Path(__file__).resolve().parents[1]
SIZE = 24  # one image size for every render in this file (and test_viz): one compile


def _cli(*argv, cwd=None) -> subprocess.CompletedProcess:
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    return subprocess.run([sys.executable, "-m", "experiments", *map(str, argv)], cwd=cwd or ROOT,
                          capture_output=True, text=True, timeout=120, env=env)


def _one_line_error(proc: subprocess.CompletedProcess, *needles: str) -> None:
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-800:])
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr  # no traceback, no usage dump
    assert "Traceback" not in proc.stderr
    for n in needles:
        assert n in lines[0], lines[0]


@pytest.fixture(scope="module")
def ply(tmp_path_factory) -> Path:
    from test_viz import sphere_scene  # the same shapes as test_viz: one compile

    g = sphere_scene()
    path = tmp_path_factory.mktemp("scene") / "scene.ply"
    save_ply(path, g)
    return path


def test_subprocess_errors_are_one_line_with_status_2(tmp_path, ply):
    _one_line_error(_cli("render", "--scene", tmp_path / "missing.ply", "--out", tmp_path / "o"),
                    "missing.ply", "does not exist")
    _one_line_error(_cli("render", "--scene", ply, "--out", tmp_path / "o", "--data", tmp_path,
                         "--orbit", "3"), "not allowed with")
    _one_line_error(_cli("bench", "--out", tmp_path / "b", "--only", "no_such_bench"),
                    "--only", "no_such_bench")


def test_help_lists_the_commands(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for command in ("demo", "render", "bench"):
        assert command in out


@pytest.mark.parametrize("argv, needle", [
    (["render", "--scene", "{ply}", "--out", "{out}", "--size", "2"], "--size"),
    (["render", "--scene", "{ply}", "--out", "{out}", "--split", "test"], "--split"),
    (["render", "--scene", "{ply}", "--out", "{out}", "--background", "2", "0", "0"], "--background"),
    (["render", "--scene", "{ply}", "--out", "{out}", "--radius", "-1"], "--radius"),
    (["render", "--scene", "{ply}", "--out", "{out}", "--orbit", "0"], "--orbit"),
    (["render", "--scene", "{ply}"], "--out"),
    (["render", "--scene", "{garbage}", "--out", "{out}"], "garbage.ply"),
    (["render", "--scene", "{ply}", "--out", "{out}", "--data", "{out}/nowhere"], "nowhere"),
    (["render", "--scene", "{ply}", "--out", "{out}", "--fps", "abc"], "--fps"),
    (["bench", "--out", "{out}", "--timeout", "0"], "--timeout"),
    (["bench"], "--out"),
    (["demo", "--out", "{out}", "--size", "0"], "--size"),
    (["demo", "--out", "{out}", "--mode", "fast"], "--mode"),
    (["render", "--scene", "{ply}", "--bogus-flag"], "--bogus-flag"),
    (["render", "--config", "{tmp}/bad.json", "--scene", "{ply}"], "malformed"),
    (["render", "--config", "{tmp}/unknown.json", "--scene", "{ply}"], "unknown flag(s) colour"),
    (["nonsense-command"], "nonsense-command"),
])
def test_bad_flags_and_paths_exit_2(tmp_path, ply, capsys, argv, needle):
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"not a ply at all\n")
    (tmp_path / "bad.json").write_text("{oops")
    (tmp_path / "unknown.json").write_text(json.dumps({"colour": "red"}))
    argv = [a.format(ply=ply, out=tmp_path / "out", garbage=garbage, tmp=tmp_path) for a in argv]
    with pytest.raises(SystemExit) as exc:
        raise SystemExit(cli.main(argv))
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert needle in err, err
    assert len(err.strip().splitlines()) == 1, err


def test_no_command_prints_help_and_exits_2(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main([])
    assert exc.value.code == 2 and "COMMAND" in capsys.readouterr().out


def test_render_orbit_writes_frames_depth_turntable(tmp_path, ply):
    out = tmp_path / "orbit"
    assert cli.main(["render", "--scene", str(ply), "--out", str(out), "--orbit", "3",
                     "--size", str(SIZE), "--quiet"]) == 0
    frames = sorted((out / "frames").glob("*.png"))
    assert [p.name for p in frames] == ["frame_000.png", "frame_001.png", "frame_002.png"]
    assert len(list((out / "depth").glob("*.png"))) == 3
    assert (out / "turntable.webp").is_file()
    img = read_image(frames[1])
    assert img.shape == (SIZE, SIZE, 3)
    c = SIZE // 2
    assert img[c - 2:c + 2, c - 2:c + 2].mean() < 0.9 and np.allclose(img[0, 0], 1.0, atol=0.03)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == 3 and metrics["num_gaussians"] == 48
    config = json.loads((out / "config.json").read_text())
    assert config["command"] == "render" and config["flags"]["orbit"] == 3
    # The path was saved in nerfstudio's camera-path format: following it renders the same frames.
    again = tmp_path / "again"
    assert cli.main(["render", "--scene", str(ply), "--out", str(again), "--camera-path",
                     str(out / "camera_path.json"), "--no-depth", "--quiet"]) == 0
    for name in ("frame_000.png", "frame_002.png"):
        np.testing.assert_allclose(read_image(again / "frames" / name),
                                   read_image(out / "frames" / name), atol=1.5 / 255)


def test_render_along_dataset_cameras(tmp_path, ply):
    cams = camlib.hemisphere(3, radius=2.2, width=SIZE, height=SIZE, fov_deg=50.0)
    data = save_nerfstudio(tmp_path / "data", np.ones((3, SIZE, SIZE, 3), np.float32), cams,
                           test_indices=np.array([1]))
    for photo in (tmp_path / "data" / "images").iterdir():  # cameras alone: photos unread
        photo.unlink()
    out = tmp_path / "along"
    assert cli.main(["render", "--scene", str(ply), "--out", str(out), "--data", str(data),
                     "--split", "test", "--no-depth", "--quiet"]) == 0
    assert [p.name for p in (out / "frames").iterdir()] == ["frame_000.png"]
    assert not (out / "depth").exists()
    # The frame is the test camera's view: the object in the middle.
    img = read_image(out / "frames" / "frame_000.png")
    c = SIZE // 2
    assert img[c - 2:c + 2, c - 2:c + 2].mean() < 0.9


def _script(folder: Path, name: str, body: str) -> None:
    (folder / f"{name}.py").write_text(
        "import argparse, json, pathlib, sys\n"
        "p = argparse.ArgumentParser(); p.add_argument('--smoke', action='store_true')\n"
        "p.add_argument('--out', type=pathlib.Path)\na = p.parse_args()\n" + body)


def test_bench_runs_scripts_and_summarises(tmp_path):
    scripts = tmp_path / "benchmarks"
    scripts.mkdir()
    _script(scripts, "fast", "a.out.mkdir(parents=True, exist_ok=True)\n"
            "(a.out / 'fast.json').write_text(json.dumps({'benchmark': 'fast', 'machine': {'x': 1},"
            " 'smoke': a.smoke, 'sizes': [{'n': 8, 'median_ms': 1.25}], 'peak_rss_mb': 12.5}))\n")
    _script(scripts, "broken", "sys.exit('RuntimeError: kernel exploded')\n")
    _script(scripts, "common", "raise SystemExit('common is a library, never run')\n")
    assert bench.discover(scripts) == ["broken", "fast"]
    out = tmp_path / "out"
    ok = bench.run_one("fast", out, smoke=True, timeout=60, bench_dir=scripts)
    bad = bench.run_one("broken", out, smoke=True, timeout=60, bench_dir=scripts)
    assert ok["status"] == "ok" and ok["result"]["smoke"] is True
    assert bad["status"] == "failed" and "kernel exploded" in bad["error"]
    assert "kernel exploded" in (out / "logs" / "broken.log").read_text()
    md = bench.summary_markdown([ok, bad], {"cpu_count": 2}, smoke=True)
    assert "| fast | ok |" in md and "| broken | failed |" in md
    assert "| sizes[0].median_ms | 1.25 |" in md and "| peak_rss_mb | 12.5 |" in md
    assert "machine.x" not in md and "- cpu_count: 2" in md


def test_demo_plumbing(tmp_path):
    argv = demo._stage_argv("make-scene", {"name": "face", "--out": tmp_path, "--size": 16,
                                           "--quiet": True, "--seed": None})
    assert argv == ["make-scene", "face", "--out", str(tmp_path), "--size", "16", "--quiet"]
    with pytest.raises(DataError, match="no such flag"):
        demo._stage_argv("make-scene", {"--no-such-flag": 1})
    assert demo._edit_extra(["max-steps=30", "--sync"]) == {"plan.max_steps": 30,
                                                            "plan.asynchronous": False}
    for bad in (["=3"], ["max-steps=many"], ["no-such-flag=1"], ["sync=1"], ["editor=dall-e"]):
        with pytest.raises(DataError, match="--edit-arg"):
            demo._edit_extra(bad)


def test_demo_edit_runs_the_config_tree_its_record_reproduces(tmp_path):
    """The demo's edit stage is a config tree (no argv); the command line its config.json
    records builds the same tree in the edit command."""
    from experiments import edit

    config = demo.run_config(cli.parse(["demo", "--out", str(tmp_path), "--mode", "in2n",
                                        "--patience", "7", "--edit-arg", "warmup=20",
                                        "--edit-arg", "ip2p-batch=2"]))
    assert config.edit_arg == ("warmup=20", "ip2p-batch=2")
    tree = demo.edit_config(config)
    assert (tree.plan.mode, tree.plan.patience, tree.plan.warmup) == ("in2n", 7, 20)
    assert (tree.editor.kind, tree.editor.steps, tree.editor.batch) == ("ip2p", 5, 2)
    argv = demo._edit_argv(tree, "in2n", {"--data": tmp_path, "--quiet": True})
    assert edit.run_config(cli.parse(argv)) == tree


def test_report_command_rewrites_the_page(tmp_path):
    import argparse

    from experiments import report as report_cmd
    from test_report import make_run

    run = make_run(tmp_path / "run", turntables=False)
    out = report_cmd.run(argparse.Namespace(run_dir=run, output=tmp_path / "r.html", thumb_px=64,
                                            max_views=2, max_mb=5.0))
    assert out["report"] == str(tmp_path / "r.html") and out["bytes"] > 1000
    with pytest.raises(DataError, match="--thumb-px"):
        report_cmd.run(argparse.Namespace(run_dir=run, output=None, thumb_px=1, max_views=2,
                                          max_mb=5.0))
    with pytest.raises(DataError, match="not a run directory"):
        report_cmd.run(argparse.Namespace(run_dir=tmp_path, output=None, thumb_px=64,
                                          max_views=2, max_mb=5.0))


def test_demo_stage_records_its_own_command_line(tmp_path):
    argv = ["make-scene", "ball", "--out", str(tmp_path / "data"), "--size", "16", "--views", "2",
            "--test-views", "1", "--points", "50", "--quiet"]
    demo._run_stage(argv)
    config = json.loads((tmp_path / "data" / "config.json").read_text())
    assert config["argv"] == argv and config["command"] == "make-scene"
    assert (tmp_path / "data" / "transforms.json").is_file()
    with pytest.raises(DataError, match="bad flags"):
        demo._run_stage(["make-scene", "ball", "--size", "many"])
