"""The splat viewer (experiments/view.py): snapshots, slider, select button, live refresh,
the run's tree (branch dropdown, steering buttons), browser.

Runs are written directly (three snapshot PLYs of 300 Gaussians and a schedule.json, as
the edit driver lays them out; a branch folder and tree.json for the tree) instead of
running an edit; the steering buttons' subprocess is a fake that records its command line,
except in the slow tests, which edit a tiny scene and refine it for real. The browser tests
open the viewer in headless Chromium with software WebGL and look for the splats' colours.
"""

from __future__ import annotations

import base64
import dataclasses
import json
import queue
import shutil
import subprocess
import sys
import time
import urllib.request

import jax.numpy as jnp
import numpy as np
import pytest

from experiments import view
from experiments.cli import main
from jaxedit import DataError
from jaxedit.edit.steer import Branch, NodeRef, RunTree
from jaxedit.io.files import folder_lock
from jaxedit.pipelines import select_snapshot, steer_run
from jaxedit.gaussians import covariance, from_points, grow, splat_arrays
from jaxedit.io import save_ply

# One vivid colour per snapshot, so a screenshot tells which one is on screen.
RED, GREEN, BLUE = (1.0, 0.1, 0.1), (0.1, 0.9, 0.1), (0.1, 0.2, 1.0)
YELLOW = (1.0, 0.9, 0.1)


CENTRE = np.array([4.0, -3.0, 1.0])  # off the origin, where viser's default camera looks


def blob(seed: int, rgb, n: int = 300):
    """n opaque Gaussians of one colour in a ball of radius ~0.5 around CENTRE."""
    points = CENTRE + np.random.default_rng(seed).normal(size=(n, 3)) * 0.25
    g = from_points(points, np.tile(rgb, (n, 1)), sh_degree=1, init_opacity=0.9)
    return dataclasses.replace(g, log_scales=g.log_scales - 1.0)  # a third of the spacing


def write_snapshot(run, rel: str, scene) -> str:
    save_ply(run / rel / "scene.ply", scene)
    return f"{rel}/scene.ply"


def write_schedule(run, records) -> None:
    subtasks = [{"index": i, "name": f"s{i}", "kind": "edit", "ratio": r, "snapshot": snap}
                for i, (r, snap) in enumerate(records)]
    (run / "schedule.json").write_text(json.dumps({"prompt": "test", "subtasks": subtasks}))


def make_run(run):
    """An edit run directory as the driver leaves it: original + two subtask snapshots."""
    write_snapshot(run, "original", blob(0, RED))
    snaps = [write_snapshot(run, "subtasks/00_r0.500", blob(1, GREEN)),
             write_snapshot(run, "subtasks/01_r1.000", blob(2, BLUE))]
    write_schedule(run, [(0.5, snaps[0]), (1.0, snaps[1])])
    return run


def test_splat_arrays_are_the_alive_gaussians_activated():
    g = blob(0, RED, n=5)
    quats = jnp.array([[0.9, 0.1, -0.3, 0.2]] * 5)
    g = grow(dataclasses.replace(g, log_scales=g.log_scales.at[:, 0].add(0.7), quats=quats),
             8)  # 3 dead slots
    a = splat_arrays(g)
    assert {k: v.shape for k, v in a.items()} == {
        "centers": (5, 3), "covariances": (5, 3, 3), "rgbs": (5, 3), "opacities": (5, 1)}
    assert all(v.dtype == np.float32 for v in a.values())
    np.testing.assert_allclose(a["centers"], g.means[:5])
    np.testing.assert_allclose(a["covariances"], covariance(quats, g.log_scales[:5]), rtol=1e-6)
    assert np.allclose(a["covariances"], np.swapaxes(a["covariances"], 1, 2))
    assert not np.allclose(a["covariances"][:, 0, 1], 0.0)  # rotated: not axis aligned
    np.testing.assert_allclose(a["rgbs"], np.tile(RED, (5, 1)), atol=1e-5)
    np.testing.assert_allclose(a["opacities"], 0.9, atol=1e-5)


def test_run_snapshots_in_order_and_bad_run_dirs(tmp_path, capsys):
    run = make_run(tmp_path / "run")
    snaps = view.run_snapshots(run)
    assert [s.subtask for s in snaps] == [None, 0, 1]
    assert [s.path.parent.name for s in snaps] == ["original", "00_r0.500", "01_r1.000"]
    assert "r = 0.500" in snaps[1].label
    # A demo run directory is accepted through its edit stage.
    shutil.copytree(run, tmp_path / "demo" / "edit")
    assert view.edit_run_dir(tmp_path / "demo") == tmp_path / "demo" / "edit"
    with pytest.raises(DataError, match="no snapshot yet"):
        view.run_snapshots(tmp_path / "missing")
    (run / "schedule.json").write_text('{"subtasks": [{"snapshot": "x"}]}')
    with pytest.raises(DataError, match="schedule.json: malformed schedule"):
        view.run_snapshots(run)
    assert main(["view", str(tmp_path / "missing"), "--port", "0"]) == 2
    assert main(["view", str(run), "--port", "70000"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    # The CLI's shared path check refuses a missing RUN_DIR before the viewer starts.
    assert len(err) == 2 and "missing: does not exist" in err[0] and "--port" in err[1]


def test_missing_viser_is_a_one_line_error(tmp_path, monkeypatch, capsys):
    run = make_run(tmp_path / "run")
    monkeypatch.setitem(sys.modules, "viser", None)  # import viser raises ImportError
    assert main(["view", str(run)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "viser" in err and "jaxedit[viewer]" in err


@pytest.fixture
def viser_installed():
    pytest.importorskip("viser", reason="the optional extra 'viewer' is not installed")


def test_slider_and_select_button_write_what_select_only_writes(tmp_path, viser_installed):
    run = make_run(tmp_path / "run")
    viewer = view.open_run(run, port=0)
    try:
        assert len(viewer) == 3 and viewer._shown == 2  # the most edited snapshot first
        # No tree.json and no edit's config.json: as before, no dropdown, no steering.
        assert not viewer._dropdown.visible and not viewer.steerable
        assert viewer.branches() == ("main",)
        assert viewer.url.startswith("http://127.0.0.1:") and viewer.server.get_port() > 0
        viewer.show(0)
        assert viewer._button.disabled and viewer.select() is None  # the original: no subtask
        assert not (run / "selected.ply").exists()
        viewer._slider.value = 1  # what dragging the slider does
        assert viewer._shown == 1 and not viewer._button.disabled
        path = viewer.select()
        assert viewer._status.content == f"wrote selected.ply from {viewer._scenes[1][0]}"
        (run / "schedule.json").rename(run / "moved.json")
        viewer._select_clicked(None)  # a click: the error goes to the panel, not a traceback
        assert viewer._status.content.startswith("error: ") and "schedule.json" in viewer._status.content
        (run / "moved.json").rename(run / "schedule.json")
    finally:
        viewer.close()
    assert path == run / "selected.ply"
    assert path.read_bytes() == (run / "subtasks/00_r0.500/scene.ply").read_bytes()
    # The same files as `edit --select-only --select 0` on a copy of the run.
    other = shutil.copytree(run, tmp_path / "other", ignore=shutil.ignore_patterns("selected.*"))
    assert main(["edit", "--out", str(other), "--select-only", "--select", "0"]) == 0
    for name in ("selected.ply", "selected.json"):
        assert (other / name).read_bytes() == (run / name).read_bytes()
    assert select_snapshot(other, -1).read_bytes() != path.read_bytes()


def wait_for(predicate, seconds=20.0):
    deadline = time.monotonic() + seconds
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.02)


def test_watcher_shows_each_snapshot_as_the_run_writes_it(tmp_path, viser_installed):
    run = tmp_path / "run"
    run.mkdir()
    viewer = view.SnapshotViewer(run, port=0)
    watcher = view.RunWatcher(run, viewer, interval=0.02).start()
    try:
        time.sleep(0.1)
        assert len(viewer) == 0  # nothing written yet: no error, nothing shown
        write_snapshot(run, "original", blob(0, RED))
        wait_for(lambda: len(viewer) == 1)
        snap = write_snapshot(run, "subtasks/00_r1.000", blob(1, BLUE))
        time.sleep(0.1)
        assert len(viewer) == 1  # a PLY not yet in schedule.json is not a finished subtask
        write_schedule(run, [(1.0, snap)])  # the driver lists a subtask once its PLY is written
        wait_for(lambda: len(viewer) == 2)
        # Followed the edit (the slider's callback may run on viser's thread: wait for it).
        wait_for(lambda: viewer._shown == 1)
        viewer.show(0)  # the user goes back: a later snapshot must not pull the view away
        snap2 = write_snapshot(run, "subtasks/01_r1.000", blob(2, GREEN))
        write_schedule(run, [(1.0, snap), (1.0, snap2)])
    finally:
        watcher.stop()  # stopping picks up what was written last
        viewer.close()
    assert len(viewer) == 3 and viewer._shown == 0


# ---------------------------------------------------------------- the tree and steering


def add_branch(run, name, parent, start, records, rgb, seed):
    """Branch ``name`` of ``run`` as steer_run.run_branch leaves it: tree.json's entry and its
    folder with one finished subtask per (ratio) in ``records``, all of colour ``rgb``."""
    folder = run / "branches" / name
    subtasks = [{"index": i, "name": f"s{i}", "kind": "edit", "ratio": r,
                 "snapshot": write_snapshot(folder, f"subtasks/{i:02d}_r{r:.3f}",
                                            blob(seed + i, rgb))}
                for i, r in enumerate(records)]
    (folder / "schedule.json").write_text(json.dumps({"prompt": "test", "subtasks": subtasks}))
    tree = steer_run.read_tree(run).add(Branch(name, "refine", parent, start, 0.5, "main"))
    steer_run.write_tree(run, tree)


def make_steerable(run):
    """make_run's run as `edit` leaves it: its config.json makes the steering controls appear."""
    make_run(run)
    (run / "config.json").write_text(json.dumps({"command": "edit", "argv": ["edit"]}))
    return run


def test_branch_dropdown_lists_the_tree_and_the_slider_follows_the_chosen_branch(
        tmp_path, viser_installed):
    run = make_run(tmp_path / "run")
    # b1 refines main:1 from main:0; b2 branches from b1's node 0.
    add_branch(run, "b1", NodeRef("main", 1), NodeRef("main", 0), [0.75, 1.0], YELLOW, 10)
    add_branch(run, "b2", NodeRef("b1", 0), NodeRef("b1", 0), [1.0], GREEN, 20)
    chains = view.branch_chains(run)
    assert list(chains) == ["main", "b1", "b2"]
    assert [s.node for s in chains["main"]] == [None, 0, 1]
    assert [s.node for s in chains["b1"]] == [None, 0, "b1:0", "b1:1"]  # up to its start
    assert [s.node for s in chains["b2"]] == [None, 0, "b1:0", "b2:0"]
    assert "b1:1" in chains["b1"][3].label and "r = 1.000" in chains["b1"][3].label
    viewer = view.open_run(run, port=0)
    try:
        assert viewer.branches() == ("main", "b1", "b2") and viewer._dropdown.visible
        # each entry says where the branch grew from
        assert tuple(viewer._dropdown.options) == ("main", "b1 (refine of main:1)",
                                                   "b2 (refine of b1:0)")
        assert viewer._branch == "main" and len(viewer) == 3 and viewer.node_on_screen() == 1
        viewer._dropdown.value = "b1 (refine of main:1)"  # what picking it in the page does
        assert len(viewer) == 4 and int(viewer._slider.max) == 3
        assert viewer.node_on_screen() == "b1:1" and "b1:1" in viewer._caption.content
        viewer._slider.value = 2
        assert viewer.node_on_screen() == "b1:0"
        path = viewer.select()  # keep a branch node
        assert path.read_bytes() == (run / "branches/b1/subtasks/00_r0.750/scene.ply").read_bytes()
        assert json.loads((run / "selected.json").read_text())["branch"] == "b1"
        viewer._slider.value = 1  # main:0 seen in b1's chain: keep writes main's subtask 0
        assert viewer.node_on_screen() == 0
        assert viewer.select().read_bytes() == (run / "subtasks/00_r0.500/scene.ply").read_bytes()
        # A branch made later (by another process) reaches the dropdown on the next poll.
        add_branch(run, "b3", NodeRef("main", 0), NodeRef("main", 0), [0.9], BLUE, 30)
        watcher = view.RunWatcher(run, viewer)
        watcher._seen = {b: {s.path for s in c} for b, c in view.branch_chains(run).items()
                         if b != "b3"}
        assert watcher.refresh() == 3  # original, main:0, b3:0
        assert tuple(viewer._dropdown.options)[-1] == "b3 (refine of main:0)"
        assert viewer._branch == "b1" and viewer.node_on_screen() == 0  # the view stays
        viewer._dropdown.value = "main"
        assert len(viewer) == 3 and viewer.node_on_screen() == 1
    finally:
        viewer.close()
    (run / "tree.json").write_text("{}")
    with pytest.raises(DataError, match="tree.json: malformed run tree"):
        view.open_run(run, port=0)


def test_stop_writes_the_control_file_only_while_an_edit_holds_the_run(tmp_path, viser_installed):
    run = make_steerable(tmp_path / "run")
    viewer = view.open_run(run, port=0)
    try:
        assert viewer.steerable and not viewer._stop.disabled
        viewer._stop_clicked(None)  # nothing runs: refused in the panel
        assert viewer._op_status.content.startswith("error: ") and "no edit is running" in \
            viewer._op_status.content
        assert not (run / steer_run.CONTROL_NAME).exists()
        with folder_lock(run):  # an edit (another process) holds the run
            viewer._stop_clicked(None)
        assert viewer._op_status.content.startswith("stop requested")
        assert json.loads((run / steer_run.CONTROL_NAME).read_text()) == {"stop": True}
    finally:
        viewer.close()


class FakeProcess:
    """What launch_process returns, driven by the test: stderr lines, then an exit status."""

    def __init__(self, argv):
        self.argv, self._lines, self._done = argv, queue.Queue(), None

    @property
    def stderr(self):
        return iter(self._lines.get, None)

    def say(self, line):
        self._lines.put(line + "\n")

    def exit(self, status):
        self._done = status
        self._lines.put(None)

    def wait(self, timeout=None):
        return self._done

    def terminate(self):
        self.exit(-15)


def test_steering_buttons_start_the_command_and_show_its_progress(tmp_path, viser_installed):
    run = make_steerable(tmp_path / "run")
    started = []

    def launch(argv):
        started.append(FakeProcess(argv))
        return started[-1]

    viewer = view.open_run(run, port=0, launch=launch)
    cmd = [sys.executable, "-m", "experiments", "edit", "--out", str(run.resolve())]
    try:
        viewer.show(0)  # the original: nothing to refine
        assert viewer._refine.disabled and viewer.start("refine") is None and not started
        viewer.show(1)
        assert not viewer._refine.disabled
        op = viewer.start("refine")  # the refine button's action
        assert started[0].argv == cmd + ["--from", "main:0", "--name", "b1", "--refine"]
        assert viewer._refine.disabled and viewer._extend.disabled  # one operation at a time
        assert viewer.start("extend") is None and len(started) == 1
        assert "refine b1 is still running" in viewer._op_status.content
        started[0].say("start edit")
        write_snapshot(run / "branches/b1", "subtasks/00_r0.250", blob(5, GREEN))
        (run / "branches/b1/schedule.json").write_text(json.dumps({"subtasks": [
            {"index": 0, "snapshot": "subtasks/00_r0.250/scene.ply"}, {"index": 1}]}))
        started[0].say("done r0 r0.250 60 in 0:02 loss=0.0682")
        wait_for(lambda: "done r0 r0.250" in viewer._op_status.content)
        assert "running: 1 of 2 subtasks done" in viewer._op_status.content
        started[0].exit(0)
        assert op.wait(10) == 0 and viewer._op_status.content == "refine b1 finished"
        assert not viewer._refine.disabled
        # branch: a new instruction and / or another seed; neither is refused at once.
        viewer.start("branch")
        assert len(started) == 1 and "new instruction or change the seed" in \
            viewer._op_status.content
        viewer._seed.value = 7
        viewer.start("branch")
        assert started[1].argv == cmd + ["--from", "main:0", "--name", "b1", "--seed", "7"]
        started[1].exit(0)
        viewer._seed.value, viewer._prompt.value = 0, "  give him a marble texture "
        viewer._operation.wait(10)
        viewer.start("branch")
        assert started[2].argv == cmd + ["--from", "main:0", "--name", "b1",
                                         "--prompt", "give him a marble texture"]
        started[2].exit(0)
        viewer._operation.wait(10)
        # the branch's settings: left at 0 they are the run's, else given
        viewer._prompt.value, viewer._threshold.value, viewer._target.value = "", 0.01, 3
        viewer._guidance_text.value, viewer._guidance_image.value = 9.0, 1.25
        viewer.start("branch")
        assert started[3].argv == cmd + ["--from", "main:0", "--name", "b1", "--threshold",
                                         "0.01", "--target-subtasks", "3", "--guidance", "9.0",
                                         "1.25"]
        started[3].exit(0)
        viewer._operation.wait(10)
        viewer._threshold.value, viewer._target.value = 0.0, 0
        viewer._guidance_text.value, viewer._guidance_image.value = 0.0, 0.0
        started.pop()
        viewer.show(2)
        viewer._r_max.value = 1.5
        op = viewer.start("extend")
        assert started[3].argv == cmd + ["--from", "main:1", "--name", "b1", "--extend", "1.5"]
        started[3].say("error: --from: node main:1 is a consolidate subtask")
        started[3].exit(2)  # a refused command: its one line in the panel
        assert op.wait(10) == 2
        assert viewer._op_status.content == "error: --from: node main:1 is a consolidate subtask"
        assert not viewer._extend.disabled

        def broken(argv):
            raise FileNotFoundError(2, "No such file or directory")

        viewer._launch = broken  # the command cannot even start: said in the panel
        assert viewer.start("refine") is None and not viewer._refine.disabled
        assert viewer._op_status.content.startswith("error: refine: cannot start ")
    finally:
        viewer.close()


def test_edit_view_shows_the_running_subtask(tmp_path, viser_installed):
    from jaxedit.edit.plan import SubtaskSpec

    viewer = view.SnapshotViewer(make_steerable(tmp_path / "run"), port=0)
    bars = []
    try:
        progress = viewer.following(lambda *a: bars.append(a[1]))
        spec = SubtaskSpec(2, "r2", 0.625, 0.01, "edit")
        progress(spec, 40, 0.0123, None)
        assert viewer._edit_status.content == "editing: subtask 2 r2 (r = 0.625), step 40, loss 0.0123"
        progress(spec, 50, 0.02, None)  # within a second: the bars move, the panel waits
        assert bars == [40, 50] and "step 40" in viewer._edit_status.content
        viewer._edit_said_at = -1.0
        progress(spec, 60, 0.02, None)
        assert "step 60" in viewer._edit_status.content
        viewer.edit_over("edit finished")
        assert viewer._edit_status.content == "edit finished"
    finally:
        viewer.close()


# A tiny real edit (the simulated editor): 24 px views, 60 Gaussians, three subtasks.
TINY = ["--prompt", "turn him into a bronze statue", "--sync", "--max-steps", "60",
        "--warmup", "5", "--patience", "10", "--test-views", "1", "--turntable-frames", "0",
        "--accept-low-identity", "--target-subtasks", "3", "--quiet", "--no-report"]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A finished tiny edit run (copy it before steering it)."""
    from test_cli_bad_inputs import _dataset

    from jaxedit.gaussians import from_points as points

    d = tmp_path_factory.mktemp("tiny")
    rng = np.random.default_rng(1)
    _dataset(d / "data", size=24)
    save_ply(d / "scene.ply", points(rng.normal(scale=0.3, size=(60, 3)),
                                     rng.uniform(size=(60, 3)), sh_degree=0))
    assert main(["edit", "--data", str(d / "data"), "--scene", str(d / "scene.ply"),
                 "--out", str(d / "run"), *TINY]) == 0
    return d / "run"


def last_edit_step(run) -> int:
    """The main branch's last subtask of kind edit (what refine can split)."""
    return [r["index"] for r in json.loads((run / "schedule.json").read_text())["subtasks"]
            if r["kind"] == "edit"][-1]


@pytest.mark.slow
def test_refine_button_really_refines_a_tiny_run(tiny_run, tmp_path, viser_installed):
    run = shutil.copytree(tiny_run, tmp_path / "run")
    watcher = view.watch_run(run, port=0)
    viewer = watcher.viewer
    try:
        k = last_edit_step(run)
        viewer.show(k + 1)  # the original is first on the slider
        viewer._r_max.value = 1.0  # extend needs r_max > 1: the command refuses, in the panel
        op = viewer.start("extend")
        assert op.wait(120) == 2 and viewer._op_status.content.startswith("error: --extend")
        assert not (run / "branches").exists() and not (run / "tree.json").exists()
        op = viewer.start("refine")
        assert op.argv[-5:] == ["--from", f"main:{k}", "--name", "b1", "--refine"]
        assert op.wait(300) == 0, viewer._op_status.content
        watcher.refresh()
    finally:
        viewer.close()
    assert viewer._op_status.content == "refine b1 finished"
    rows = steer_run.tree_rows(run)
    assert [(r["name"], r["op"], r["parent"], r["status"]) for r in rows[1:]] == [
        ("b1", "refine", f"main:{k}", "done")]
    # The view moved to the new branch: its last node, after main's up to the refined step.
    chain = view.branch_chains(run)["b1"]
    assert viewer._branch == "b1" and viewer.node_on_screen() == chain[-1].node
    assert [s.node for s in chain[:k + 1]] == [None, *range(k)]
    assert all(isinstance(s.node, str) for s in chain[k + 1:])



def test_worker_protocol_runs_each_command_line_and_says_its_status(tmp_path, capsys):
    """experiments.steer_worker: one JSON command per line, its messages on stderr, then the
    exit line; a garbled line is refused with status 2 and the worker goes on."""
    import io

    from experiments import steer_worker

    commands = io.StringIO("not json\n" + json.dumps(
        {"argv": ["edit", "--out", str(tmp_path), "--tree", "--bogus"]}) + "\n")
    assert steer_worker.serve(tmp_path / "none", commands) == 0
    lines = capsys.readouterr().err.split("\n")
    assert lines[0].startswith("warm-up skipped: ") and "no config.json" in lines[0]
    assert lines[1] == steer_worker.READY
    assert lines[2].startswith("error: the worker's command is not JSON")
    assert lines[3] == f"{steer_worker.EXIT}2"
    assert "unrecognized arguments: --bogus" in lines[4] and lines[5] == f"{steer_worker.EXIT}2"
    assert lines[6:] == [""]


@pytest.mark.slow
def test_warm_worker_refines_as_the_command_line_does(tiny_run, tmp_path):
    """The viewer's worker runs its commands one after another in one warm process: a refused
    one says its one line, and a refine gives the bytes the command line gives."""
    run, cold = (shutil.copytree(tiny_run, tmp_path / name) for name in ("run", "cold"))
    k = last_edit_step(run)
    worker = view.WarmWorker(run)
    try:
        assert worker.wait_ready(), worker.warm_up_messages
        pid = worker._proc.pid
        refused = worker(view.operation_argv(run, "extend", k, "b1", r_max=1.0))
        assert [line for line in refused.stderr if line.startswith("error: --extend")]
        assert refused.wait() == 2 and not (run / "branches").exists()
        refine = worker(view.operation_argv(run, "refine", k, "b1"))
        said = list(refine.stderr)
        assert refine.wait() == 0, said
        assert worker._proc.pid == pid  # the same process, still warm
    finally:
        worker.close()
    assert worker._proc is None
    assert main(view.operation_argv(cold, "refine", k, "b1")[3:] + ["--quiet"]) == 0
    for folder in ("run", "cold"):
        assert steer_run.branch_status(tmp_path / folder, "b1") == "done"
    snaps = [sorted((tmp_path / f / "branches" / "b1" / "subtasks").glob("*/scene.ply"))
             for f in ("run", "cold")]
    assert len(snaps[0]) == len(snaps[1]) >= 2
    assert all(a.read_bytes() == b.read_bytes() for a, b in zip(*snaps))

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
WIDTH, HEIGHT = 1000, 700


class DevTools:
    """Headless Chromium driven over the DevTools protocol: one page, kept open.

    One browser for the whole test, so the second snapshot reaches the open page over
    viser's websocket, as in ``edit --view``, instead of by a reload.
    """

    def __init__(self, profile, url):
        from websockets.sync.client import connect

        # Software WebGL (SwiftShader through ANGLE): no GPU on CI or the developers' machines.
        self.proc = subprocess.Popen(
            [CHROMIUM, "--headless", "--no-sandbox", "--use-angle=swiftshader",
             "--enable-unsafe-swiftshader", "--no-first-run", "--disable-background-networking",
             "--disable-component-update", "--disable-sync", "--hide-scrollbars",
             "--remote-debugging-port=0", f"--user-data-dir={profile}",
             f"--window-size={WIDTH},{HEIGHT}", url],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            port_file = profile / "DevToolsActivePort"  # Chromium writes its free port here
            wait_for(lambda: port_file.is_file() and port_file.read_text().count("\n") >= 1, 60)
            port = int(port_file.read_text().split()[0])
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=30) as r:
                page = next(t for t in json.load(r) if t["type"] == "page")
            self.ws = connect(page["webSocketDebuggerUrl"], proxy=None, max_size=None)
        except BaseException:
            self.close()
            raise
        self.calls = 0

    def call(self, method, **params):
        self.calls += 1
        self.ws.send(json.dumps({"id": self.calls, "method": method, "params": params}))
        while True:  # skip the page's events until our answer
            msg = json.loads(self.ws.recv(timeout=60))
            if msg.get("id") == self.calls:
                assert "error" not in msg, msg["error"]
                return msg["result"]

    def evaluate(self, expression):
        return self.call("Runtime.evaluate", expression=expression)["result"].get("value")

    def screenshot(self, path):
        from PIL import Image

        path.write_bytes(base64.b64decode(self.call("Page.captureScreenshot")["data"]))
        return np.asarray(Image.open(path).convert("RGB"), np.int32)

    def close(self):
        if hasattr(self, "ws"):
            self.ws.close()
        self.proc.terminate()
        self.proc.wait(timeout=30)


def colour_pixels(img):
    """Pixels of each snapshot colour in the middle of the canvas (off viser's panels)."""
    h, w = img.shape[:2]
    r, g, b = np.moveaxis(img[h // 4:, w // 5:int(w * 0.64)], -1, 0)
    return {"red": int(((r - g > 80) & (r - b > 80)).sum()),
            "green": int(((g - r > 60) & (g - b > 60)).sum()),
            "blue": int(((b - r > 80) & (b - g > 60)).sum())}


def screen_until(browser, path, colour, seconds=90.0):
    """Screenshots until ``colour`` covers the canvas middle (the scene arrives over a
    websocket and software WebGL is slow on a busy machine); the pixel counts of the last."""
    deadline = time.monotonic() + seconds
    while True:
        counts = colour_pixels(browser.screenshot(path))
        if counts[colour] > 5000 or time.monotonic() > deadline:
            return counts
        time.sleep(0.5)


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not on PATH (CI installs Debian's chromium)")
def test_viewer_draws_the_splats_in_headless_chromium(tmp_path, viser_installed):
    run = make_run(tmp_path / "run")
    viewer = view.SnapshotViewer(run, port=0)
    browser = None
    try:
        # The page opens before the first snapshot, as with edit --view: the snapshots
        # and the camera framing them reach it over the websocket.
        browser = DevTools(tmp_path / "profile", viewer.url)
        if not browser.evaluate("!!document.createElement('canvas').getContext('webgl2')"):
            pytest.skip("this Chromium has no WebGL2 (no SwiftShader)")
        wait_for(lambda: len(viewer.server.get_clients()) == 1, 60)
        assert view.RunWatcher(run, viewer).refresh() == 3
        last = screen_until(browser, tmp_path / "last.png", "blue")
        viewer.show(0)  # the slider to the original: pushed to the open page
        original = screen_until(browser, tmp_path / "original.png", "red")
    finally:
        if browser is not None:
            browser.close()
        viewer.close()
    # 300 splats framed by the initial camera cover tens of thousands of pixels; the
    # other snapshots' colours are absent.
    assert last["blue"] > 5000 and last["red"] < 50 and last["green"] < 50, last
    assert original["red"] > 5000 and original["blue"] < 50 and original["green"] < 50, original


def splat_pixels(img):
    """Pixels of the canvas middle (off viser's panels and notices) that are not background."""
    h, w = img.shape[:2]
    return (np.abs(img[h // 3:, w // 5:int(w * 0.64)] - 255).max(axis=-1) > 40)


def page_text(browser):
    return browser.evaluate("document.body.innerText") or ""


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not on PATH (CI installs Debian's chromium)")
def test_refine_pressed_in_headless_chromium_renders_the_new_branch(tiny_run, tmp_path,
                                                                    viser_installed):
    run = shutil.copytree(tiny_run, tmp_path / "run")
    watcher = view.watch_run(run, port=0, launch=view.WarmWorker(run))  # as `view` does
    watcher.interval = 0.3
    viewer, browser = watcher.viewer, None
    viewer.warm_up()
    k = last_edit_step(run)
    try:
        viewer.show(k + 1)  # main:k, the last edit step, on screen
        browser = DevTools(tmp_path / "profile", viewer.url)
        if not browser.evaluate("!!document.createElement('canvas').getContext('webgl2')"):
            pytest.skip("this Chromium has no WebGL2 (no SwiftShader)")
        wait_for(lambda: f"subtask {k} " in page_text(browser), 60)
        # software WebGL draws the first frames (slowly on a busy machine)
        deadline, before = time.monotonic() + 120, None
        while before is None or splat_pixels(before).sum() <= 3000:
            assert time.monotonic() < deadline, "the page drew no splats"
            time.sleep(0.5)
            before = browser.screenshot(tmp_path / "before.png")
        watcher.start()
        # Press refine in the page: the click reaches the server over viser's websocket.
        assert browser.evaluate("""(() => { const b = [...document.querySelectorAll('button')]
            .find(b => b.innerText.trim() === 'refine'); b.click(); return !b.disabled; })()""")
        wait_for(lambda: viewer._operation is not None, 30)
        assert viewer._operation.argv[-5:] == ["--from", f"main:{k}", "--name", "b1", "--refine"]
        # The new branch's first snapshot arrives: the page's dropdown and caption move to it.
        wait_for(lambda: "subtask b1:0 " in page_text(browser)
                 or not viewer._operation.running, 400)
        assert "subtask b1:0 " in page_text(browser), viewer._op_status.content
        assert browser.evaluate("[...document.querySelectorAll('input')]"
                                ".some(i => i.type === 'text' && i.value.startsWith('b1 (refine of'))")
        shown = view.branch_chains(run)["b1"][k + 1]  # b1:0, after main's chain up to k-1
        assert shown.node == "b1:0" and viewer.node_on_screen() == "b1:0"
        deadline, after = time.monotonic() + 60, None
        while after is None or (np.abs(after - before).max(axis=-1) > 40).sum() < 500:
            assert time.monotonic() < deadline, "the page kept showing main's snapshot"
            time.sleep(0.5)
            after = browser.screenshot(tmp_path / "after.png")
    finally:
        if browser is not None:
            browser.close()
        watcher.stop()
        viewer.close()  # the refine still running is ended (--branch b1 --resume goes on)
    # Both screenshots show splats across the canvas; the new one is b1:0's.
    assert splat_pixels(before).sum() > 3000 and splat_pixels(after).sum() > 3000


@pytest.mark.slow
def test_edit_view_serves_on_steerable_once_the_edit_released_the_run(
        tiny_run, tmp_path, monkeypatch, viser_installed):
    d, seen = tiny_run.parent, {}

    def serve(viewer):  # instead of blocking until Ctrl-C: what the user would find
        seen.update(locked=steer_run._locked(out), branches=viewer.branches(), shown=len(viewer),
                    steerable=viewer.steerable)

    monkeypatch.setattr(view.SnapshotViewer, "serve_forever", serve)
    out = tmp_path / "run"
    assert main(["edit", "--data", str(d / "data"), "--scene", str(d / "scene.ply"),
                 "--out", str(out), "--view", "--view-port", "0", *TINY]) == 0
    subtasks = json.loads((out / "schedule.json").read_text())["subtasks"]
    assert seen == {"locked": False, "branches": ("main",), "shown": len(subtasks) + 1,
                    "steerable": True}
