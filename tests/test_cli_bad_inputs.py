"""Bad input and faults through the CLI: one stderr line, exit 2, nothing left behind.

Each class of the robustness issue has a generated corpus here. Almost every bad
input fails before JAX compiles anything, so the cases call
:func:`experiments.cli.main` in-process and capture stderr at the file-descriptor
level (``capfd``: C libraries such as libpng write there, not to ``sys.stderr``).
The kill/resume and lock tests use one real subprocess each.
"""

from __future__ import annotations

import dataclasses
import json
import os
import random
import signal
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from cli_expect import fails, listing
from experiments import cli
from jaxedit.pipelines.reconstruct import capped_initial_points
from jaxedit import camera as camlib, gaussians as G
from jaxedit.io import read_image, save_nerfstudio, save_ply, write_image
from jaxedit.io.ply import load_ply

ROOT = Path(__file__).resolve().parents[1]
SIZE = 16  # every dataset of this file: 16 x 16 px, 4 views (one held out)
QUICK = settings(max_examples=25, deadline=None,
                 suppress_health_check=[HealthCheck.function_scoped_fixture])


def _dataset(folder: Path, *, size=SIZE, points=200, focal=None, shift=None) -> Path:
    """A tiny nerfstudio dataset; ``focal`` / ``shift`` make its cameras degenerate."""
    cams = camlib.hemisphere(4, radius=2.2, width=size, height=size, fov_deg=50.0)
    if focal is not None:
        cams = dataclasses.replace(cams, fx=np.full(4, focal, np.float32),
                                   fy=np.full(4, focal, np.float32))
    if shift is not None:
        w2c = np.array(cams.world_to_camera)
        w2c[:, :3, 3] += shift
        cams = dataclasses.replace(cams, world_to_camera=w2c)
    rng = np.random.default_rng(0)
    images = rng.uniform(0.2, 0.8, size=(4, size, size, 3)).astype(np.float32)
    pts = rng.normal(scale=0.3, size=(points, 3)).astype(np.float32)
    return save_nerfstudio(folder, images, cams, test_indices=np.array([1]), points=pts,
                           point_colors=rng.uniform(size=(points, 3)).astype(np.float32)).parent


@pytest.fixture(scope="module")
def corpus(tmp_path_factory) -> types.SimpleNamespace:
    """Shared inputs: a good dataset and scene, and the broken files of each class."""
    d = tmp_path_factory.mktemp("corpus")
    rng = np.random.default_rng(1)
    good = _dataset(d / "data")
    scene = d / "scene.ply"
    save_ply(scene, G.from_points(rng.normal(scale=0.3, size=(30, 3)),
                                  rng.uniform(size=(30, 3)), sh_degree=0))
    empty = d / "empty.ply"
    save_ply(empty, G.empty(0, 0))
    (d / "afile").write_text("not a folder\n")
    return types.SimpleNamespace(dir=d, data=good, scene=scene, empty=empty, afile=d / "afile")


def _fails(capfd, argv, needle: str, out: Path | None = None) -> str:
    """:func:`cli_expect.fails`, ``out`` kept by its listing (nothing created or removed)."""
    return fails(capfd, argv, needle, keep=out)


# ---------------------------------------------------------------- output locations

def _readonly_dir(tmp_path: Path) -> Path:
    if os.geteuid() == 0:  # root writes through permission bits: use a read-only mount
        return Path("/proc")
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    return ro


#: A valid command line per command; "{out}" is the output location under test.
COMMANDS = {
    "make-scene": ["make-scene", "ball", "--out", "{out}"],
    "reconstruct": ["reconstruct", "--data", "{data}", "--out", "{out}"],
    "render": ["render", "--scene", "{scene}", "--out", "{out}"],
    "edit": ["edit", "--data", "{data}", "--scene", "{scene}", "--prompt", "x", "--out", "{out}"],
    "demo": ["demo", "--out", "{out}"],
    "ablation": ["ablation", "--out", "{out}"],
    "bench": ["bench", "--out", "{out}"],
    "convert-lpips": ["convert-lpips", "--out", "{out}"],
    "report": ["report", "{data}", "--output", "{out}"],
    "train-editor": ["train-editor", "--smoke", "--out", "{out}"],
}


@pytest.mark.parametrize("kind", ["existing-file", "under-a-file", "read-only", "not-utf8"])
@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_unusable_output_location(corpus, tmp_path, capfd, command, kind):
    if kind == "existing-file":
        out, needle = corpus.afile, "not a directory"
    elif kind == "under-a-file":
        out, needle = corpus.afile / "run", "is a file"
    elif kind == "read-only":
        out, needle = _readonly_dir(tmp_path) / "run", "cannot write in"
    else:
        out, needle = tmp_path / os.fsdecode(b"run-\xff\xfe"), "not valid UTF-8"
    if command == "report":  # its output is a file: an existing folder is the bad case there
        out, needle = (tmp_path, "is a directory") if kind == "existing-file" else (out, needle)
    argv = [a.format(out=out, data=corpus.data, scene=corpus.scene) for a in COMMANDS[command]]
    flag = "--output" if command == "report" else "--out"
    line = _fails(capfd, argv, needle)
    assert line.startswith(f"error: {flag}"), line
    assert corpus.afile.read_text() == "not a folder\n"
    assert not (tmp_path / os.fsdecode(b"run-\xff\xfe")).exists()


def test_missing_inputs_are_named_before_any_work(corpus, tmp_path, capfd):
    for argv, needle in [
        (["reconstruct", "--data", tmp_path / "nope", "--out", tmp_path / "o"], "nope"),
        (["edit", "--data", corpus.data, "--scene", tmp_path / "gone.ply", "--out",
          tmp_path / "o"], "gone.ply"),
        (["render", "--scene", corpus.scene, "--camera-path", tmp_path / "p.json", "--out",
          tmp_path / "o"], "p.json"),
        (["report", tmp_path / "norun"], "norun"),
    ]:
        _fails(capfd, argv, needle)
        assert not (tmp_path / "o").exists()


# ---------------------------------------------------------------- config values

def _reconstruct_argv(corpus, out, *extra):
    return ["reconstruct", "--data", corpus.data, "--out", out, *extra]


def _parse(argv):
    """(args, None) or (None, the one error line) of parsing ``argv`` alone."""
    from jaxedit import DataError

    try:
        return cli.parse([str(a) for a in argv]), None
    except SystemExit:
        return None, "argparse"
    except DataError as e:
        return None, str(e)


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-10**6, 10**6) | st.floats(allow_nan=False)
    | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=3), inner,
                                                                max_size=2),
    max_leaves=5)


@QUICK
@given(key=st.sampled_from(["iters", "cull_alpha", "background", "resume", "densify_until",
                            "downscale"]),
       value=JSON_VALUES)
def test_config_values_get_the_flags_validation(corpus, tmp_path, capfd, key, value):
    """A config value is accepted iff its command-line spelling is, and to the same value."""
    config = tmp_path / "c.json"
    config.write_text(json.dumps({key: value}))
    out = tmp_path / "o"
    from_file, error = _parse(_reconstruct_argv(corpus, out, "--config", config))
    flag = "--" + key.replace("_", "-")
    if isinstance(value, bool) and key == "resume":
        typed = [flag] if value else []
    elif value is None or isinstance(value, (bool, list, dict)):
        typed = None  # no command-line spelling: the file must be refused
    else:
        # "--flag=value": argparse reads a separate "-1e+16" as an unknown option, not a value.
        typed = [f"{flag}={value}"]
    if value is None and key in ("densify_until", "downscale"):
        typed = []  # null where the flag's default is unset means "not given"
    from_flags, _ = (None, "unspellable") if typed is None else _parse(
        _reconstruct_argv(corpus, out, *typed))
    if from_flags is None:
        assert from_file is None, (value, vars(from_file))
        assert error.startswith(str(config)) and key in error, error
        _fails(capfd, _reconstruct_argv(corpus, out, "--config", config), str(config), out)
    else:
        assert error is None, error
        assert getattr(from_file, key) == getattr(from_flags, key)


@pytest.mark.parametrize("name, content, needle", [
    ("latin1.json", b'{"iters": "\xff"}', "not UTF-8"),
    ("deep.json", b"[" * 100_000 + b"]" * 100_000, "nested too deeply"),
    ("deep.toml", b"x = " + b"[" * 100_000 + b"]" * 100_000, "malformed config"),
    ("list.json", b"[1, 2]", "must be a table/object"),
    ("unknown.json", b'{"itters": 5}', "unknown flag(s) itters"),
    ("negative.json", b'{"iters": -3}', "--iters"),
    ("switch.json", b'{"resume": "yes"}', "switch"),
    ("triple.json", b'{"background": [1, 1]}', "render"),
])
def test_malformed_config_files(corpus, tmp_path, capfd, name, content, needle):
    config = tmp_path / name
    config.write_bytes(content)
    out = tmp_path / "o"
    argv = _reconstruct_argv(corpus, out, "--config", config)
    if name == "triple.json":  # render --background takes 3 numbers
        argv, needle = ["render", "--scene", corpus.scene, "--out", out, "--config", config], "3 values"
    _fails(capfd, argv, needle)
    assert not out.exists()


def test_config_may_set_a_required_flag(corpus, tmp_path):
    config = tmp_path / "c.toml"
    config.write_text(f'data = "{corpus.data}"\niters = 7\n')
    args = cli.parse(["reconstruct", "--out", str(tmp_path / "o"), "--config", str(config),
                      "--iters", "9"])
    assert args.data == corpus.data and args.iters == 9  # the command line wins


# ---------------------------------------------------------------- degenerate data

@pytest.fixture(scope="module")
def degenerate(corpus) -> dict:
    d = corpus.dir
    return {"tiny": _dataset(d / "tiny", size=1, points=10),
            "focal": _dataset(d / "focal", focal=1e29),
            "far": _dataset(d / "far", shift=1e29)}


@pytest.mark.parametrize("case, needle", [
    ("reconstruct tiny", "at least 11x11"), ("edit tiny", "at least 11x11"),
    ("reconstruct downscale", "larger than the 16x16 images"),
    ("edit downscale", "larger than the 16x16 images"),
    ("reconstruct focal", "field of view of almost zero"),
    ("render focal", "field of view of almost zero"),
    ("edit far", "too far for float32"), ("reconstruct far", "too far for float32"),
    ("edit empty", "has no Gaussians"), ("render empty", "has no Gaussians to frame"),
    ("render radius", "too far for float32"), ("render fov", "--fov"),
])
def test_degenerate_data(corpus, degenerate, tmp_path, capfd, case, needle):
    command, what = case.split()
    data = degenerate.get(what, corpus.data)
    scene = corpus.empty if what == "empty" else corpus.scene
    out = tmp_path / "o"
    extra = {"downscale": ["--downscale", "17"], "radius": ["--orbit", "2", "--radius", "1e29"],
             "empty": ["--orbit", "2"] if command == "render" else [],
             "fov": ["--orbit", "2", "--fov", "180"]}.get(what, [])
    if command == "render":
        argv = ["render", "--scene", scene, "--out", out, "--quiet"]
        argv += extra if extra else ["--data", data]
    elif command == "edit":
        argv = ["edit", "--data", data, "--scene", scene, "--prompt", "x", "--out", out, *extra]
    else:
        argv = ["reconstruct", "--data", data, "--out", out, "--quiet", *extra]
    _fails(capfd, argv, needle)
    assert not out.exists()


@pytest.mark.parametrize("path", [["--data", "{data}"],
                                  ["--orbit", "2", "--radius", "3", "--target", "0", "0", "0",
                                   "--size", str(SIZE)]])
def test_render_of_an_empty_scene_is_the_background(corpus, tmp_path, path):
    out = tmp_path / "o"
    assert cli.main(["render", "--scene", str(corpus.empty), "--out", str(out), "--background",
                     "0.2", "0.4", "0.6", "--no-depth", "--quiet",
                     *[a.format(data=corpus.data) for a in path]]) == 0
    frames = sorted((out / "frames").glob("*.png"))
    assert len(frames) == (4 if "--data" in path else 2)
    for f in frames:
        np.testing.assert_allclose(read_image(f), np.broadcast_to([0.2, 0.4, 0.6], (SIZE, SIZE, 3)),
                                   atol=1 / 255)


# ---------------------------------------------------------------- unreadable images

def _break_frame(data: Path, how: str) -> Path:
    frame = sorted((data / "images").glob("*.png"))[2]
    raw = frame.read_bytes()
    if how == "truncated":
        frame.write_bytes(raw[:len(raw) // 2])
    elif how == "garbage":
        frame.write_bytes(raw[:40] + b"garbage!" * 20)
    elif how == "empty":
        frame.write_bytes(b"")
    else:  # NaN pixels: an EXR frame (float) named by the json in place of the PNG
        import OpenImageIO as oiio

        pixels = np.full((SIZE, SIZE, 3), 0.5, np.float32)
        pixels[3, 4, 1] = np.nan
        exr = frame.with_suffix(".exr")
        out = oiio.ImageOutput.create(str(exr))
        out.open(str(exr), oiio.ImageSpec(SIZE, SIZE, 3, oiio.FLOAT))
        out.write_image(pixels)
        out.close()
        meta = data / "transforms.json"
        meta.write_text(meta.read_text().replace(frame.name, exr.name))
        frame = exr
    return frame


@pytest.mark.parametrize("command", ["reconstruct", "edit"])
@pytest.mark.parametrize("how, needle", [("truncated", "cannot decode"), ("garbage", "cannot open"),
                                         ("empty", "cannot open"), ("nan", "non-finite")])
def test_unreadable_image_is_one_line_naming_it(corpus, tmp_path, capfd, command, how, needle):
    data = _dataset(tmp_path / "data", points=10)
    frame = _break_frame(data, how)
    out = tmp_path / "o"
    argv = ([command, "--data", data, "--out", out, "--quiet"]
            + (["--scene", corpus.scene, "--prompt", "x"] if command == "edit" else []))
    line = _fails(capfd, argv, needle)
    assert line.startswith(f"error: {frame}:"), line  # the broken file, not another one
    assert "libpng" not in line and not out.exists()


# ---------------------------------------------------------------- absurd sizes

@pytest.mark.parametrize("argv, flag", [
    (["make-scene", "ball", "--size", "100000"], "--size/--views/--points"),
    (["make-scene", "ball", "--views", "1000000000"], "--size/--views/--points"),
    (["make-scene", "ball", "--points", "1000000000000"], "--size/--views/--points"),
    (["make-scene", "ball", "--supersample", "100000"], "--size/--views/--points"),
    (["reconstruct", "--data", "{data}", "--random-points", "1000000000000"], "--random-points"),
    (["render", "--scene", "{scene}", "--orbit", "1000000000"], "--orbit/--size"),
    (["render", "--scene", "{scene}", "--orbit", "100000000", "--size", "4096"], "--orbit/--size"),
])
def test_absurd_sizes_are_refused_with_the_memory_needed(corpus, tmp_path, capfd, argv, flag):
    out = tmp_path / "o"
    argv = [a.format(data=corpus.data, scene=corpus.scene) for a in argv] + ["--out", out]
    line = _fails(capfd, argv, "GiB of memory")
    assert line.startswith(f"error: {flag}:"), line
    assert not out.exists()


# ---------------------------------------------------------------- zero or negative counts

@pytest.mark.parametrize("argv, flag", [
    (["reconstruct", "--data", "{data}", "--iters", "0"], "--iters"),
    (["reconstruct", "--data", "{data}", "--iters", "-5"], "--iters"),
    (["reconstruct", "--data", "{data}", "--max-gaussians", "0"], "--max-gaussians"),
    (["reconstruct", "--data", "{data}", "--random-points", "-1"], "--random-points"),
    (["reconstruct", "--data", "{data}", "--downscale", "0"], "--downscale"),
    (["reconstruct", "--data", "{data}", "--log-every", "0"], "--log-every"),
    (["reconstruct", "--data", "{data}", "--camera-lr", "0"], "--camera-lr"),
    (["reconstruct", "--data", "{data}", "--camera-opt-from", "-1"], "--camera-opt-from"),
    (["edit", "--data", "{data}", "--scene", "{scene}", "--prompt", "x", "--test-views", "0"],
     "--test-views"),
    (["edit", "--data", "{data}", "--scene", "{scene}", "--prompt", "x", "--test-views", "-1"],
     "--test-views"),
    (["edit", "--data", "{data}", "--scene", "{scene}", "--prompt", "x", "--max-steps", "0"],
     "--max-steps"),
    (["edit", "--data", "{data}", "--scene", "{scene}", "--prompt", "x", "--subtasks", "0"],
     "--subtasks"),
    (["edit", "--data", "{data}", "--scene", "{scene}", "--prompt", "x", "--threshold", "-1"],
     "--threshold"),
    (["make-scene", "ball", "--views", "0"], "--views"),
    (["make-scene", "ball", "--points", "-2"], "--points"),
    (["make-scene", "ball", "--size", "0"], "--size"),
    (["render", "--scene", "{scene}", "--orbit", "-3"], "--orbit"),
    (["demo", "--iters", "0"], "--iters"),
    (["ablation", "--views", "0"], "--views"),
    (["ablation", "--recon-iters", "-1"], "--recon-iters"),
    (["bench", "--max-rows", "0"], "--max-rows"),
])
def test_zero_or_negative_counts(corpus, tmp_path, capfd, argv, flag):
    out = tmp_path / "o"
    argv = [a.format(data=corpus.data, scene=corpus.scene) for a in argv] + ["--out", out]
    line = _fails(capfd, argv, flag)
    assert line.startswith(f"error: {flag}"), line
    assert not out.exists()


def test_a_failed_run_keeps_what_was_there_before(corpus, tmp_path, capfd):
    out = tmp_path / "o"
    out.mkdir()
    (out / "notes.txt").write_text("mine\n")
    _fails(capfd, ["reconstruct", "--data", corpus.data, "--out", out, "--downscale", "99"],
           "downscale", out)
    assert (out / "notes.txt").read_text() == "mine\n"
    assert not (out / "config.json").exists()


# ---------------------------------------------------------------- the hard cap

@QUICK
# A few cloud sizes (each compiles its permutation once) around the caps and the 4-point
# threshold of the random init; any cap.
@given(n_points=st.sampled_from([0, 3, 4, 5, 40, 119, 120, 121, 300]), cap=st.integers(1, 130),
       seed=st.integers(0, 3))
def test_initial_points_never_exceed_the_cap(n_points, cap, seed):
    rng = np.random.default_rng(seed)
    cams = camlib.hemisphere(3, radius=2.0, width=8, height=8, fov_deg=50.0)
    points = rng.normal(size=(n_points, 3)).astype(np.float32) if n_points else None
    views = rng.uniform(size=(3, 8, 8, 3)).astype(np.float32)
    data = types.SimpleNamespace(points=points, cameras=cams, train=lambda: (views, cams),
                                 point_colors=None if points is None else rng.uniform(
                                     size=(n_points, 3)).astype(np.float32))
    pts, colors, source = capped_initial_points(data, 150, cap, seed)
    available = n_points if n_points >= 4 else 150  # fewer than 4 points: random init
    assert len(pts) == len(colors) == min(cap, available)
    assert source == ("dataset" if n_points >= 4 else "random")
    if source == "dataset":  # a subset of the cloud, in its order, each point once
        rows = [int(np.flatnonzero((points == p).all(1))[0]) for p in pts]
        assert rows == sorted(set(rows))
    again = capped_initial_points(data, 150, cap, seed)[0]
    np.testing.assert_array_equal(pts, again)  # the draw depends on the seed only


# ---------------------------------------------------------------- kill, resume, lock

RECON_FLAGS = ["--iters", "400", "--checkpoint-every", "20", "--max-gaussians", "40",
               "--sh-degree", "0", "--warmup", "20", "--refine-every", "20",
               "--densify-until", "200", "--reset-every", "0", "--log-every", "50", "--quiet"]


def _wait_for(path_glob, proc, timeout=240.0):
    folder, pattern = path_glob
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if folder.exists() and list(folder.glob(pattern)):
            return True
        if proc.poll() is not None:
            return False
        time.sleep(0.05)
    return False


def _start_and_kill(argv, out: Path, checkpoints: tuple, *, on_stopped=None) -> None:
    """Run the CLI in a subprocess and SIGKILL it at a random moment after its first checkpoint.

    ``on_stopped(proc)`` runs while the process is frozen (SIGSTOP) just before the kill.
    """
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    proc = subprocess.Popen([sys.executable, "-m", "experiments", *argv, "--out", str(out)],
                            cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        started = _wait_for(checkpoints, proc)
        assert started, proc.stderr.read().decode()[-2000:] if proc.poll() is not None else "slow"
        time.sleep(random.Random().uniform(0.0, 0.2))
        proc.send_signal(signal.SIGSTOP)  # frozen, it still holds the lock on --out
        assert proc.poll() is None, "the run ended before it could be killed"
        if on_stopped is not None:
            on_stopped(proc)
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == -signal.SIGKILL


@pytest.mark.slow
def test_kill_resume_and_lock_of_a_reconstruction(corpus, tmp_path, capfd):
    """SIGKILL after the first checkpoint, resume: the same scene.ply bytes as one run."""
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    base = ["reconstruct", "--data", str(corpus.data), *RECON_FLAGS]
    assert cli.main([*base, "--out", str(whole)]) == 0
    metrics = json.loads((whole / "metrics.json").read_text())
    assert metrics["num_gaussians"] <= 40 and load_ply(whole / "scene.ply").capacity <= 40

    def second_process_is_refused(proc):
        names = listing(killed)
        line = _fails(capfd, [*base, "--out", killed, "--resume"], "in use by another", killed)
        assert f"pid {proc.pid}" in line and listing(killed) == names

    _start_and_kill(base, killed, (killed / "checkpoints", "ckpt_*.npz"),
                    on_stopped=second_process_is_refused)
    assert cli.main([*base, "--out", str(killed), "--resume"]) == 0
    assert (killed / "scene.ply").read_bytes() == (whole / "scene.ply").read_bytes()


@pytest.mark.slow
def test_kill_and_resume_of_an_edit(corpus, tmp_path):
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    base = ["edit", "--data", str(corpus.data), "--scene", str(corpus.scene), "--prompt",
            "turn him into a bronze statue", "--mode", "nd", "--sync", "--max-steps", "120",
            "--test-views", "1", "--turntable-frames", "0", "--no-report", "--quiet",
            # the corpus' coarse scene is under the identity floor; what is tested is resume
            "--accept-low-identity"]
    assert cli.main([*base, "--out", str(whole)]) == 0
    _start_and_kill(base, killed, (killed, "checkpoint.npz"))
    assert cli.main([*base, "--out", str(killed), "--resume"]) == 0
    finals = sorted(whole.glob("subtasks/*/scene.ply"))
    assert finals and [p.relative_to(whole) for p in finals] == [
        p.relative_to(killed) for p in sorted(killed.glob("subtasks/*/scene.ply"))]
    assert (killed / finals[-1].relative_to(whole)).read_bytes() == finals[-1].read_bytes()


def test_folder_lock_refuses_a_second_holder_and_is_removed_after(tmp_path):
    from jaxedit import DataError
    from jaxedit.io.files import LOCK_NAME, folder_lock

    run = tmp_path / "run"
    with folder_lock(run, flag="--out"):
        assert (run / LOCK_NAME).read_text().strip() == str(os.getpid())
        with pytest.raises(DataError, match=f"--out: .* in use .*pid {os.getpid()}"):
            with folder_lock(run, flag="--out"):
                pass
    assert not (run / LOCK_NAME).exists()
    with folder_lock(run):  # free again
        pass


@pytest.mark.parametrize("change, needle", [
    (dict(fx=0.0), "must be positive"), (dict(fy=-3.0), "must be positive"),
    (dict(fx=1e12), "almost zero"), (dict(fy=1e-6), "almost 180"),
    (dict(fx=np.nan), "non-finite"), (dict(shift=1e7), "too far"), (dict(width=0), "no pixels"),
])
def test_check_cameras_explains_unusable_cameras(change, needle):
    from jaxedit import DataError

    cams = camlib.hemisphere(3, radius=2.0, width=SIZE, height=SIZE, fov_deg=50.0)
    camlib.check_cameras(cams, "rig")  # a sound rig passes
    if "shift" in change:
        w2c = np.array(cams.world_to_camera)
        w2c[1, :3, 3] += change.pop("shift")
        cams = dataclasses.replace(cams, world_to_camera=w2c)
    for k, v in change.items():
        value = v if k == "width" else np.asarray(cams.fx).copy() * 0 + v
        cams = dataclasses.replace(cams, **{k: value})
    with pytest.raises(DataError, match=f"rig: .*{needle}"):
        camlib.check_cameras(cams, "rig")


# ---------------------------------------------------------------- issue 28: one class per kind


def _float_flags() -> list[tuple[str, str, int]]:
    """(command, flag, values it takes) of every float flag of every command."""
    subs = cli.build_parser().commands
    return [(command, a.option_strings[-1], a.nargs if isinstance(a.nargs, int) else 1)
            for command, sub in subs.items() for a in sub.arguments if a.type is float]


class TestNonFiniteNumbers:
    """inf and nan are refused by every float flag (one converter for all), naming it."""

    def test_every_command_has_float_flags_here(self):
        commands = {c for c, _, _ in _float_flags()}
        assert {"render", "report", "reconstruct", "edit", "process-data", "bench"} <= commands

    @pytest.mark.parametrize("value", ["inf", "-inf", "nan", "1e999"])
    @pytest.mark.parametrize("command, flag, nargs", _float_flags())
    def test_flag(self, tmp_path, capfd, command, flag, nargs, value):
        if nargs > 1 and value.startswith("-"):
            pytest.skip("argparse reads a separate -inf as an option, not a value")
        out = tmp_path / "o"
        # "--flag=-inf": argparse reads a separate "-inf" as an option; the last of several
        # values is the bad one.
        typed = [f"{flag}={value}"] if nargs == 1 else [flag, *["1"] * (nargs - 1), value]
        line = _fails(capfd, [command, *typed, "--out", out], flag)
        assert "finite" in line and not out.exists()

    def test_config_file_value(self, corpus, tmp_path, capfd):
        config = tmp_path / "c.json"
        config.write_text('{"fps": Infinity}')  # Python's json reads it
        out = tmp_path / "o"
        line = _fails(capfd, ["render", "--scene", corpus.scene, "--out", out, "--config", config],
                      "--fps")
        assert line.startswith(f"error: {config}: fps:") and not out.exists()


@pytest.fixture(scope="module")
def badly_named(corpus) -> types.SimpleNamespace:
    """A photo folder and a dataset, each with one file whose name is not UTF-8."""
    photos = corpus.dir / "photos_badname"
    for k in range(3):
        write_image(photos / f"p{k}.png", np.full((16, 16, 3), 0.2 * k))
    os.rename(photos / "p2.png", os.fsencode(photos) + b"/p\xff.png")
    data = _dataset(corpus.dir / "data_badname", points=10)
    meta = (data / "transforms.json").read_text()
    old = "images/frame_00001.png"
    assert old in meta
    new = old.replace(".png", "\udcff.png")  # JSON's "\udcff": the stray byte 0xff of a name
    os.rename(data / old, os.fsencode(data) + b"/" + os.fsencode(new))
    (data / "transforms.json").write_text(meta.replace(old, json.dumps(new)[1:-1]))
    return types.SimpleNamespace(photos=photos, data=data)


class TestFileNamesNotUtf8:
    """Refused (the image reader takes UTF-8 names), naming the file by its bytes."""

    def test_process_data_photo(self, badly_named, tmp_path, capfd):
        pytest.importorskip("pycolmap")
        out = tmp_path / "o"
        line = _fails(capfd, ["process-data", "--images", badly_named.photos, "--out", out],
                      "not valid UTF-8")
        assert "p\\xff.png" in line and not out.exists()
        assert not [p for p in tmp_path.iterdir() if p.name.startswith(".o.")]  # no staging

    @pytest.mark.parametrize("command", ["reconstruct", "edit"])
    def test_dataset_frame(self, corpus, badly_named, tmp_path, capfd, command):
        out = tmp_path / "o"
        argv = [command, "--data", badly_named.data, "--out", out, "--quiet"]
        if command == "edit":
            argv += ["--scene", corpus.scene, "--prompt", "turn him into a bronze statue"]
        line = _fails(capfd, argv, "not valid UTF-8")
        assert "frame_00001\\xff.png" in line and not out.exists()


def _train_checkpoint(path: Path) -> Path:
    """A real reconstruct checkpoint (a fresh TrainState), written by the trainer's writer."""
    from jaxedit import train as T
    import jax

    state = T.init_state(G.empty(8, 0), T.TrainConfig(sh_degree=0), 1.0, key=jax.random.key(0))
    return T.save_checkpoint(path, state)


class TestBrokenCheckpointOnResume:
    """An empty, garbage or truncated checkpoint: one line naming it, the run left as it was."""

    @pytest.mark.parametrize("kind", ["empty", "garbage", "truncated"])
    @pytest.mark.parametrize("command", ["reconstruct", "edit"])
    def test_resume(self, corpus, tmp_path, capfd, command, kind):
        run = tmp_path / "run"
        ckpt = (run / "checkpoints" / "ckpt_00000020.npz" if command == "reconstruct"
                else run / "checkpoint.npz")
        ckpt.parent.mkdir(parents=True)
        if kind == "truncated":
            whole = _train_checkpoint(tmp_path / "whole.npz").read_bytes()
            ckpt.write_bytes(whole[:len(whole) // 2])
        else:
            ckpt.write_bytes(b"" if kind == "empty" else b"PK\x03\x04" + bytes(range(256)) * 8)
        (run / "config.json").write_text('{"the": "record"}\n')
        argv = [command, "--data", corpus.data, "--out", run, "--resume", "--quiet"]
        if command == "edit":
            argv += ["--scene", corpus.scene, "--prompt", "turn him into a bronze statue"]
        line = _fails(capfd, argv, "cannot read checkpoint", out=run)
        assert line.startswith(f"error: {ckpt}:"), line
        assert (run / "config.json").read_text() == '{"the": "record"}\n'


def _full_disk(tmp_path: Path, monkeypatch) -> Path:
    """A folder on a full disk: a 48 KiB tmpfs where we may mount one (root), else one where
    every durable write after the first (the run's config.json) fails with ENOSPC."""
    import errno
    import shutil

    mount = tmp_path / "tmpfs"
    mount.mkdir()
    if os.geteuid() == 0 and shutil.which("mount") and subprocess.run(
            ["mount", "-t", "tmpfs", "-o", "size=48k", "tmpfs", str(mount)],
            capture_output=True).returncode == 0:
        return mount
    real, calls = os.fsync, []

    def fsync(fd):
        calls.append(fd)
        if len(calls) > 1:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    return mount


class TestFullDisk:
    """A write refused mid-run: one line, exit 2, nothing of the run left (no temp files)."""

    @pytest.mark.slow  # compiles the training chunk: the first checkpoint is the failing write
    def test_reconstruct(self, corpus, tmp_path, capfd, monkeypatch):
        disk = _full_disk(tmp_path, monkeypatch)
        try:
            out = disk / "run"
            capfd.readouterr()
            code = cli.main(["reconstruct", "--data", str(corpus.data), "--out", str(out),
                             *RECON_FLAGS[:8], "--iters", "40"])
            err = capfd.readouterr().err
            lines = err.strip().splitlines()
            assert code == 2 and "Traceback" not in err, err[-2000:]
            assert lines[-1].startswith("error: ") and "No space left on device" in lines[-1]
            assert [line for line in lines if line.startswith("error")] == lines[-1:]
            assert not out.exists() and list(disk.iterdir()) == []
        finally:
            subprocess.run(["umount", str(disk)], capture_output=True)


class TestFailedCommandKeepsTheRecord:
    """A failed ``edit --select-only`` leaves config.json (and everything else) as it was."""

    @pytest.mark.parametrize("select, needle", [("abc", "--select"), ("7", "--select"),
                                                ("nan", "--select"), ("1", "is missing")])
    def test_select(self, corpus, tmp_path, capfd, select, needle):
        run = tmp_path / "run"
        (run / "subtasks" / "00").mkdir(parents=True)
        (run / "subtasks" / "00" / "scene.ply").write_bytes(corpus.scene.read_bytes())
        (run / "schedule.json").write_text(json.dumps({"subtasks": [
            {"index": 0, "name": "r0", "ratio": 0.5, "snapshot": "subtasks/00/scene.ply"},
            {"index": 1, "name": "r1", "ratio": 1.0, "snapshot": "subtasks/01/scene.ply"}]}))
        (run / "config.json").write_text('{"command": "edit", "the": "record"}\n')
        _fails(capfd, ["edit", "--data", corpus.data, "--scene", corpus.scene, "--prompt", "x",
                       "--out", run, "--select-only", "--select", select], needle, out=run)
        assert (run / "config.json").read_text() == '{"command": "edit", "the": "record"}\n'


class TestPathsAsGiven:
    """Messages about a missing input or an unwritable output name the path as typed."""

    def test_missing_data(self, tmp_path, capfd, monkeypatch):
        monkeypatch.chdir(tmp_path)
        line = _fails(capfd, ["reconstruct", "--data", "no/such/data", "--out", "o"],
                      "no/such/data")
        assert str(tmp_path) not in line and not (tmp_path / "o").exists()

    def test_read_only_out(self, corpus, tmp_path, capfd, monkeypatch):
        monkeypatch.chdir(tmp_path)
        given = os.path.relpath(_readonly_dir(tmp_path) / "run", tmp_path)
        line = _fails(capfd, ["reconstruct", "--data", corpus.data, "--out", given], given)
        assert line.startswith("error: --out:"), line


class TestAblationFlagCombinations:
    """A combination ablation cannot honour names the flag at fault."""

    @pytest.mark.parametrize("flags, flag", [
        (["--prompts", "zzz"], "--prompts"), (["--prompts", ","], "--prompts"),
        (["--methods", ","], "--methods"), (["--methods", "in2n"], "--methods"),
        (["--scenes", ","], "--scenes"), (["--variants", "1,x"], "--variants"),
        (["--smoke", "--scenes", "person"], "--scenes"), (["--smoke", "--seeds", "3"], "--seeds"),
        (["--smoke", "--prompts", "make it look like autumn"], "--prompts"),
        (["--scenes", "person", "--size", "64", "--points", "500"], "--points"),
        (["--points", "0"], "--points"),
    ])
    def test_combination(self, tmp_path, capfd, flags, flag):
        out = tmp_path / "o"
        line = _fails(capfd, ["ablation", "--out", out, *flags], flag)
        assert line.startswith(f"error: {flag}:"), line
        assert not out.exists()
