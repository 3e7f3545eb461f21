"""``view``: an edit run's scene as Gaussian splats in the browser (viser), and its steering.

    python -m experiments view RUN_DIR [--port 8080]

Serves, on 127.0.0.1 only, the snapshots an edit run wrote (``original/scene.ply``
then ``subtasks/NN_rX.XXX/scene.ply`` in schedule order) with viser, the viewer
library nerfstudio uses. A slider picks the snapshot, i.e. the aggressivity of the
edit; the button "write selected.ply" (keep) does what ``edit --select-only --select K``
does for the node on screen. A local edit's run (``edit --local`` / ``--region`` /
``--masks``, issue 35) adds a checkbox "colour by relevance": the splats take the colour
of their lifted relevance (``local/gaussians.npz``: blue 0 .. red 1, the editable
Gaussians' set where the run kept only that; yellow: Gaussians the edit moved or created,
all from editable ones), so the frozen part of the scene shows as what stayed bit for bit.

A steered run (``tree.json``, :mod:`jaxedit.pipelines.steer_run`) adds a dropdown of its
branches: the slider runs over the chosen branch, from the original through its parent
chain's snapshots up to its start, then its own (keep writes a branch node as
``select_snapshot(RUN, "b1:2")`` does). An ``edit`` run directory (with its config.json)
gets the folder "steer": **stop** (``edit --stop``: the running edit stops after its
subtask), **refine** the node on screen, **branch** from it with the instruction and / or
seed typed above, **extend** it up to ``r_max`` -- each runs ``python -m experiments edit
--out RUN --from NODE --name bN ...`` as a subprocess, one at a time, with its last
progress line and the branch's finished subtasks in the panel (or its one-line error),
and the view moves to the new branch when its first snapshot arrives. A background
thread polls the run directory (every branch), so new branches and snapshots appear
as they are written.

``edit --view`` serves the run the same way while it is edited, each snapshot shown as
its subtask ends (there refine / branch / extend are refused while the edit holds the
run), and goes on serving, steerable, once the edit finished or stopped, until Ctrl-C.
To view a run on a remote machine, forward the port (``ssh -L``).

Needs the optional extra ``viewer`` (``pip install 'jaxedit[viewer]'``).
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

from jaxedit.errors import check_ranges, ranged

HELP = ("serve an edit run's snapshots in the browser (viser): a slider over each branch, "
        "keep, stop / refine / branch / extend")

HOST = "127.0.0.1"  # never 0.0.0.0: a run may be private; forward the port to share it
DEFAULT_PORT = 8080  # viser's; a taken port moves to the next free one
MAIN = "main"  # the run's own branch (jaxedit.edit.steer.ROOT)
DEFAULT_R_MAX = 1.25  # the extend control's initial r_max


@dataclasses.dataclass(frozen=True)
class ViewConfig:
    """Where the viewer listens, and how it runs its steering buttons.

    Attributes:
      port: port on 127.0.0.1 (taken: the next free one; 0: any free port).
      warm_worker: run the steering buttons' commands in a worker process that reads the
        run, its editor and programs as the viewer opens; off: each click starts a new
        process, and nothing is loaded before it.
    """

    port: int = ranged(DEFAULT_PORT, low=0, high=65535)
    warm_worker: bool = True

    def __post_init__(self):
        check_ranges(self)


def _config_flags():
    from experiments.flags import Flag, FlagSet

    return FlagSet(ViewConfig, (Flag("port"), Flag("warm_worker", off="--no-warm-worker"))
                   ).complete()


#: The command's flags, generated from :class:`ViewConfig`.
FLAGS = (_config_flags(),)


def add_arguments(p) -> None:
    p.add_argument("run_dir", type=Path, help="edit run directory (the --out of edit, or a demo's)")
    FLAGS[0].add_to(p)


def run_config(args) -> ViewConfig:
    """The :class:`ViewConfig` of ``args`` (range errors name the flag)."""
    return FLAGS[0].build(args)


@dataclasses.dataclass(frozen=True)
class Snapshot:
    """One scene state of a run: its label, its scene.ply, its subtask index (None: original)
    and the branch of the tree it belongs to."""

    label: str
    path: Path
    subtask: int | None
    branch: str = MAIN

    @property
    def node(self) -> int | str | None:
        """What keep selects (:func:`jaxedit.pipelines.select_snapshot`): the main branch's
        subtask index, ``"BRANCH:INDEX"``, or None for the original."""
        if self.subtask is None or self.branch == MAIN:
            return self.subtask
        return f"{self.branch}:{self.subtask}"


def node_label(branch: str, record: dict) -> str:
    """A finished subtask's label: ``subtask 2 r2 (r = 0.375)``, ``subtask b1:0 ...`` in a branch."""
    prefix = "" if branch == MAIN else f"{branch}:"
    return f"subtask {prefix}{record['index']} {record['name']} (r = {float(record['ratio']):.3f})"


def edit_run_dir(run_dir: Path) -> Path:
    """``run_dir`` itself, or the edit stage of a demo run directory (``run_dir/edit``)."""
    run_dir = Path(run_dir)
    if not (run_dir / "schedule.json").exists() and (run_dir / "edit" / "schedule.json").exists():
        return run_dir / "edit"
    return run_dir


def run_snapshots(run_dir: Path) -> list[Snapshot]:
    """The snapshots written so far: ``original`` first, then finished subtasks in order.

    Both files are written atomically and a subtask enters schedule.json only after
    its scene.ply is complete, so a run that is still being edited reads consistently.
    Raises DataError when there is no snapshot at all (not an edit run, or not started).
    """
    from jaxedit import DataError

    run_dir = Path(run_dir)
    snaps = []
    if (run_dir / "original" / "scene.ply").is_file():
        snaps.append(Snapshot("original (r = 0)", run_dir / "original" / "scene.ply", None))
    path = run_dir / "schedule.json"
    try:
        subtasks = json.loads(path.read_text())["subtasks"]
        records = [s for s in subtasks if s.get("snapshot")]
        snaps += [Snapshot(node_label(MAIN, s), run_dir / s["snapshot"], int(s["index"]))
                  for s in records]
    except FileNotFoundError:
        pass
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise DataError(path, f"malformed schedule ({e})") from None
    if not snaps:
        raise DataError(run_dir, "no snapshot yet: not an edit run directory "
                                 "(no schedule.json or original/scene.ply)")
    return snaps


def branch_chains(run_dir: Path) -> dict[str, list[Snapshot]]:
    """Each branch of the run's tree (main first, then in the order they were made) with the
    snapshots its slider runs over: its parent chain's from the original up to its start,
    then its own finished subtasks. A run without tree.json: ``{"main": run_snapshots()}``.
    """
    from jaxedit import DataError
    from jaxedit.pipelines import steer_run

    run_dir = Path(run_dir)
    main = run_snapshots(run_dir)
    if not (run_dir / steer_run.TREE_NAME).is_file():
        return {MAIN: main}
    tree = steer_run.read_tree(run_dir)
    try:
        own = {row["name"]: [Snapshot(node_label(row["name"], n), Path(n["snapshot"]),
                                      int(n["index"]), row["name"])
                             for n in row["nodes"] if n["snapshot"]]
               for row in steer_run.tree_rows(run_dir) if row["name"] != MAIN}
    except (KeyError, TypeError, ValueError) as e:
        raise DataError(run_dir / steer_run.BRANCHES, f"malformed branch schedule ({e})") from None
    own[MAIN] = [s for s in main if s.subtask is not None]
    original = [s for s in main if s.subtask is None]

    def upto(ref) -> list[Snapshot]:  # from the original to node ``ref`` (None: the original)
        if ref is None:
            return list(original)
        branch = tree.get(ref.branch)
        return upto(None if branch is None else branch.start) + [
            s for s in own[ref.branch] if s.subtask <= ref.index]

    return {name: upto(None if tree.get(name) is None else tree.get(name).start) + own[name]
            for name in tree.names()}


def relevance_of_run(run_dir: Path) -> dict | None:
    """A local edit's per-Gaussian relevance (``RUN_DIR/local/gaussians.npz``,
    :func:`jaxedit.edit.local.load_gaussian_relevance`), None for a global edit's run."""
    from jaxedit.edit.local import load_gaussian_relevance
    from jaxedit.pipelines.edit_run import LOCAL_DIR

    return load_gaussian_relevance(Path(run_dir) / LOCAL_DIR)


def import_viser():
    """The viser module, or a one-line DataError naming the missing extra."""
    from jaxedit import DataError

    try:
        import viser
    except ImportError:
        raise DataError("viser", "not installed; the viewer needs the optional extra: "
                                 "pip install 'jaxedit[viewer]'") from None
    return viser


def camera_pose(centers):
    """(position, look_at) of an initial camera that frames a cloud of centres [N, 3].

    Robust to stray splats: it looks at the median and stands off by a multiple of
    the 90th-percentile radius, slightly above and to the side of +x (+z is up, and the
    built-in scenes face +x, where their cameras' azimuths start).
    """
    import numpy as np

    look_at = np.median(centers, axis=0)
    radius = float(np.quantile(np.linalg.norm(centers - look_at, axis=1), 0.9)) or 1.0
    direction = np.array([1.0, -0.35, 0.45])
    return look_at + 2.2 * radius * direction / np.linalg.norm(direction), look_at


def node_name(node: int | str) -> str:
    """A :attr:`Snapshot.node` as ``--from`` takes it (``main:2``, ``b1:0``)."""
    return f"{MAIN}:{node}" if isinstance(node, int) else str(node)


def operation_argv(run_dir: Path, op: str, node: int | str, name: str, *, prompt: str = "",
                   seed: int | None = None, r_max: float = DEFAULT_R_MAX,
                   threshold: float | None = None, target_subtasks: int | None = None,
                   guidance: tuple[float, float] | None = None) -> list[str]:
    """The command line of steering operation ``op`` ("refine", "branch", "extend") on
    ``node``, making branch ``name``: ``python -m experiments edit --out RUN --from NODE ...``
    (a branch command reuses the run's recorded flags). ``branch`` passes ``prompt`` when
    not blank, and ``seed``, ``threshold``, ``target_subtasks``, ``guidance`` (text, image)
    when not None."""
    argv = [sys.executable, "-m", "experiments", "edit", "--out", str(Path(run_dir).resolve()),
            "--from", node_name(node), "--name", name]
    if op == "refine":
        return argv + ["--refine"]
    if op == "extend":
        return argv + ["--extend", repr(float(r_max))]
    if op != "branch":
        raise ValueError(f"unknown operation {op!r}")
    if prompt.strip():
        argv += ["--prompt", prompt.strip()]
    if threshold is not None:
        argv += ["--threshold", repr(float(threshold))]
    if target_subtasks is not None:
        argv += ["--target-subtasks", str(int(target_subtasks))]
    if guidance is not None:
        argv += ["--guidance", *(repr(float(g)) for g in guidance)]
    return argv + ([] if seed is None else ["--seed", str(int(seed))])


def branch_labels(run_dir: Path | None, names) -> dict[str, str]:
    """The branch dropdown's entry of each branch in ``names``: its name, then where it
    grew from, e.g. ``b1 (refine of main:2)``, ``b2 (branch of b1:0: "patina")``; the main
    branch (and every branch of a run without a readable tree) is its name alone."""
    from jaxedit import DataError
    from jaxedit.pipelines import steer_run

    labels = {name: name for name in names}
    if run_dir is None or not (Path(run_dir) / steer_run.TREE_NAME).is_file():
        return labels
    try:
        tree = steer_run.read_tree(run_dir)
    except DataError:
        return labels
    for b in tree.branches:
        if b.name in labels:
            said = "" if b.prompt is None else f': "{b.prompt[:32]}"'
            labels[b.name] = f"{b.name} ({b.op} of {b.parent}{said})"
    return labels


def launch_process(argv: list[str], stdin=subprocess.DEVNULL):
    """Start ``argv`` (a steering command) with its stderr piped as text lines; this
    checkout's packages first on the path, so ``-m experiments`` is this one's."""
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = os.pathsep.join([root, *filter(None, [env.get("PYTHONPATH")])])
    return subprocess.Popen(argv, stdin=stdin, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, bufsize=1, env=env)


#: The worker's line that says it is warm (:mod:`experiments.steer_worker`).
WORKER_READY = "jaxedit-worker: ready"
#: The start of the worker's line that ends a command's messages; its exit status follows.
WORKER_EXIT = "jaxedit-worker: exit "


class WorkerCommand:
    """A steering command running in a :class:`WarmWorker`, as :class:`Operation` reads a
    process: ``stderr`` yields its messages until the worker says it ended, ``wait()`` gives
    its exit status, ``terminate()`` ends the worker with it."""

    def __init__(self, worker: subprocess.Popen):
        self._worker, self.returncode = worker, None
        self.stderr = self._messages()

    def _messages(self):
        for line in self._worker.stderr:
            if line.startswith(WORKER_EXIT):
                self.returncode = int(line[len(WORKER_EXIT):])
                return
            if line.rstrip("\n") != WORKER_READY:
                yield line
        self.returncode = self._worker.wait()  # the worker ended (terminated, crashed)

    def wait(self, timeout: float | None = None) -> int | None:
        return self.returncode

    def terminate(self) -> None:
        self._worker.terminate()


class WarmWorker:
    """``launch(argv)`` for a viewer of one edit run: its steering commands run one at a
    time in a worker process (:mod:`experiments.steer_worker`) that read the run and
    prepared a refine before the first one arrives, and stays warm for the next. A worker
    that ended (terminated with its command, crashed) is started anew by the next command.

    ``start()`` starts it (the viewer does when it opens the run, ``edit --view`` once the
    edit is over); ``close()`` ends it.
    """

    def __init__(self, run_dir: Path):
        self.run_dir = Path(run_dir).resolve()
        self._proc: subprocess.Popen | None = None
        self.warm_up_messages: list[str] = []

    def start(self) -> subprocess.Popen:
        if self._proc is None or self._proc.poll() is not None:
            self._proc = launch_process([sys.executable, "-m", "experiments.steer_worker",
                                         str(self.run_dir)], stdin=subprocess.PIPE)
        return self._proc

    def wait_ready(self) -> bool:
        """Block until the worker is warm (its warm-up messages in ``warm_up_messages``);
        False when it ended first. Not while a command runs (both read its stderr)."""
        for line in self.start().stderr:
            if line.rstrip("\n") == WORKER_READY:
                return True
            self.warm_up_messages.append(line.rstrip("\n"))
        return False

    def __call__(self, argv: list[str]) -> WorkerCommand:
        prefix = [sys.executable, "-m", "experiments"]
        if argv[:3] != prefix:
            raise ValueError(f"not a command of python -m experiments: {argv[:3]}")
        proc = self.start()
        proc.stdin.write(json.dumps({"argv": argv[3:]}) + "\n")
        proc.stdin.flush()
        return WorkerCommand(proc)

    def close(self) -> None:
        """End the worker (the viewer ends a running command first)."""
        proc, self._proc = self._proc, None
        if proc is not None and proc.poll() is None:
            proc.terminate()
            proc.wait(30)


def branch_progress(run_dir: Path, name: str) -> tuple[int, int] | None:
    """(finished, planned) subtasks of branch ``name`` (None: no schedule.json yet)."""
    from jaxedit.pipelines.snapshots import branch_folder

    try:
        subtasks = json.loads((branch_folder(run_dir, name) / "schedule.json").read_text())["subtasks"]
        return sum(1 for r in subtasks if r.get("snapshot")), len(subtasks)
    except (OSError, ValueError, KeyError, TypeError):
        return None


class Operation:
    """One steering command run as a subprocess: its last stderr line (the progress bars'
    log lines, or the one-line error of a refused command) and its exit status.

    ``launch(argv)`` returns a process with ``stderr`` (text lines), ``wait()`` and
    ``terminate()``; ``on_change()`` is called from the reader thread on each line and at exit.
    """

    def __init__(self, op: str, name: str, argv: list[str], *, launch=launch_process,
                 on_change=lambda: None):
        self.op, self.name, self.argv = op, name, argv
        self.last, self.returncode, self._on_change = "", None, on_change
        self.proc = launch(argv)
        self._thread = threading.Thread(target=self._read, name="jaxedit-view-op", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        for line in self.proc.stderr:
            if line.strip():
                self.last = line.strip()
                self._on_change()
        self.returncode = self.proc.wait()
        self._on_change()

    @property
    def running(self) -> bool:
        return self.returncode is None

    def wait(self, timeout: float | None = None) -> int | None:
        """Wait for the command and its reader; its exit status (None: still running)."""
        self._thread.join(timeout)
        return self.returncode

    def text(self, progress: tuple[int, int] | None) -> str:
        """The panel's line: progress while it runs, then done or the command's error."""
        what = f"{self.op} {self.name}"
        if self.running:
            count = "" if progress is None else f": {progress[0]} of {progress[1]} subtasks done"
            return f"**{what}** running{count}  \n{self.last or 'starting (loading the run)'}"
        if self.returncode == 0:
            return f"{what} finished"
        return self.last if self.last.startswith("error:") else \
            f"error: {what} exited with status {self.returncode} ({self.last})"


class SnapshotViewer:
    """A viser server showing one of a growing list of scenes, picked with a slider.

    ``update(scene, label, subtask=..., branch=...)`` adds a scene (a
    :class:`jaxedit.Gaussians`) to a branch and shows it when the slider was on that
    branch's newest one (so a live view follows the edit unless the user went back). A
    run with branches (tree.json) gets a dropdown choosing the branch the slider runs
    over. With a ``run_dir``, the button "write selected.ply" (keep) writes
    ``run_dir/selected.ply`` from the node on screen through
    :func:`jaxedit.pipelines.select_snapshot`, the code path of ``edit --select-only``;
    an ``edit`` run directory (with its config.json) also gets the steering controls:
    stop, refine, branch (instruction, seed) and extend (r_max), each a subprocess
    started by ``launch(argv)`` (:func:`launch_process`), one at a time.
    """

    def __init__(self, run_dir: Path | None = None, *, port: int = DEFAULT_PORT,
                 launch=launch_process):
        viser = import_viser()
        self.run_dir = run_dir
        #: An ``edit`` run directory (its config.json: a branch reuses the recorded flags).
        self.steerable = run_dir is not None and (Path(run_dir) / "config.json").is_file()
        self.server = viser.ViserServer(host=HOST, port=port, verbose=False)
        self._lock = threading.RLock()  # GUI callbacks run on viser's threads
        # Per branch: (label, node, splat arrays); node as Snapshot.node (None: original).
        self._branches: dict[str, list[tuple[str, int | str | None, dict]]] = {MAIN: []}
        self._branch = MAIN  # the branch the slider runs over
        self._shown: int | None = None
        self._launch, self._operation, self._follow = launch, None, None
        gui = self.server.gui
        self._dropdown = gui.add_dropdown("branch", (MAIN,), initial_value=MAIN, visible=False,
                                          hint="the run's branches (refine, branch, extend)")
        self._slider = gui.add_slider("snapshot", min=0, max=0, step=1, initial_value=0,
                                      hint="subtask snapshots, least to most edited")
        self._caption = gui.add_markdown("waiting for the first snapshot")
        self._button = gui.add_button("write selected.ply", disabled=True,
                                      hint="keep: like edit --select-only --select K")
        self._status = gui.add_markdown("")
        self._edit_status = gui.add_markdown("")  # edit --view: the running subtask
        self._edit_said_at = -1.0
        self._labels: dict[str, str] = {MAIN: MAIN}  # branch -> its dropdown entry
        self._dropdown.on_update(lambda _event: self.choose(self._name_of(str(self._dropdown.value))))
        self._slider.on_update(lambda _event: self._display(int(self._slider.value)))
        self._button.on_click(self._select_clicked)
        # A local edit's per-Gaussian relevance (None: a global edit, no checkbox).
        self._relevance = relevance_of_run(run_dir) if run_dir is not None else None
        self._colour_by_relevance = None
        if self._relevance is not None:
            self._colour_by_relevance = gui.add_checkbox(
                "colour by relevance", initial_value=False,
                hint="blue: frozen (relevance 0) .. red: relevant; yellow: moved or new")
            self._colour_by_relevance.on_update(lambda _event: self._redisplay())
        if self.steerable:
            self._add_steering(gui)

    def _add_steering(self, gui) -> None:
        """The controls of :mod:`jaxedit.pipelines.steer_run` (an ``edit`` run directory only)."""
        with gui.add_folder("steer"):
            self._op_status = gui.add_markdown("")
            self._stop = gui.add_button("stop", hint="the running edit stops after its subtask")
            self._refine = gui.add_button("refine", disabled=True,
                                          hint="redo this step split in two (a new branch)")
            self._prompt = gui.add_text("instruction", "",
                                        hint="branch: a new instruction (blank: the same)")
            self._seed = gui.add_number("seed", run_seed(self.run_dir), step=1,
                                        hint="branch: the new branch's seed")
            self._threshold = gui.add_number("threshold", 0.0, min=0.0, step=0.001,
                                             hint="branch: the difficulty threshold of its "
                                                  "steps (0: the run's)")
            self._target = gui.add_number("target subtasks", 0, min=0, step=1,
                                          hint="branch: about this many subtasks (0: the run's)")
            self._guidance_text = gui.add_number("text guidance", 0.0, min=0.0, step=0.5,
                                                 hint="branch: the editor's text guidance "
                                                      "(0 and image 0: the run's)")
            self._guidance_image = gui.add_number("image guidance", 0.0, min=0.0, step=0.1,
                                                  hint="branch: the editor's image guidance")
            self._branch_button = gui.add_button("branch", disabled=True,
                                                 hint="from this node: the instruction, seed "
                                                      "and settings above")
            self._r_max = gui.add_number("r_max", DEFAULT_R_MAX, min=1.0, step=0.05,
                                         hint="extend: go past r = 1 up to this ratio")
            self._extend = gui.add_button("extend", disabled=True,
                                          hint="from this node up to r_max (experimental)")
        self._stop.on_click(self._stop_clicked)
        self._refine.on_click(lambda _event: self.start("refine"))
        self._branch_button.on_click(lambda _event: self.start("branch"))
        self._extend.on_click(lambda _event: self.start("extend"))

    @property
    def url(self) -> str:
        return f"http://{HOST}:{self.server.get_port()}/"

    @property
    def _scenes(self) -> list[tuple[str, int | str | None, dict]]:
        """The chosen branch's snapshots (label, node, splat arrays), in slider order."""
        return self._branches[self._branch]

    def __len__(self) -> int:
        with self._lock:  # not mid-update
            return len(self._scenes)

    def branches(self) -> tuple[str, ...]:
        with self._lock:
            return tuple(self._branches)

    def update(self, scene, label: str, *, subtask: int | None = None,
               branch: str = MAIN) -> None:
        """Add ``scene`` (Gaussians) as the newest snapshot of ``branch``, labelled for the user.

        ``subtask``: its subtask index in the branch (what keep writes); None for scenes
        that are no subtask's snapshot (the original).
        """
        from jaxedit.gaussians import splat_arrays

        self.add(branch, label, Snapshot(label, Path(), subtask, branch).node, splat_arrays(scene))

    def add(self, branch: str, label: str, node: int | str | None, arrays: dict) -> None:
        """Append a snapshot (its splat arrays) to ``branch``'s slider (a new branch: to
        the dropdown). The one on screen follows it when it was the branch's newest, and
        the view moves to a branch this viewer started once its own first snapshot arrives."""
        with self._lock:
            scenes = self._branches.setdefault(branch, [])
            first = not any(self._branches.values())
            follow = branch == self._branch and (self._shown is None
                                                 or self._shown == len(scenes) - 1)
            scenes.append((label, node, arrays))
            if first and len(arrays["centers"]):
                self._aim(*camera_pose(arrays["centers"]))
            if branch not in self._labels:
                self._labels = branch_labels(self.run_dir, self._branches)
            if tuple(self._dropdown.options) != self._options():
                self._dropdown.options = self._options()
                self._dropdown.visible = len(self._branches) > 1
            if branch == self._follow and isinstance(node, str):  # the branch's own node
                self._follow = None
                if branch != self._branch:
                    self._dropdown.value = self.label_of(branch)  # its callback chooses it
                    return
                follow = True
            if branch == self._branch:
                self._slider.max = len(scenes) - 1
                if follow:
                    self.show(len(scenes) - 1)

    def label_of(self, branch: str) -> str:
        """The dropdown's entry of ``branch`` (:func:`branch_labels`)."""
        with self._lock:
            return self._labels.get(branch, branch)

    def _name_of(self, label: str) -> str:
        return next((name for name, text in self._labels.items() if text == label), label)

    def _options(self) -> tuple[str, ...]:
        return tuple(self.label_of(name) for name in self._branches)

    def choose(self, branch: str) -> None:
        """Put the slider on ``branch``'s snapshots, showing its newest."""
        with self._lock:
            if branch not in self._branches or (branch == self._branch and self._shown is not None):
                return
            self._branch, self._shown = branch, None
            if str(self._dropdown.value) != self.label_of(branch):
                self._dropdown.value = self.label_of(branch)
            self._slider.max = max(len(self._scenes) - 1, 0)
            if self._scenes:
                self.show(len(self._scenes) - 1)

    def _aim(self, position, look_at) -> None:
        """Frame the first scene, also in browsers opened before it arrived (edit --view)."""
        self.server.initial_camera.look_at = look_at
        self.server.initial_camera.position = position
        for client in self.server.get_clients().values():
            client.camera.position = position  # moves look_at along: set it second
            client.camera.look_at = look_at

    def show(self, index: int) -> None:
        """Put snapshot ``index`` of the chosen branch on screen and the slider on it."""
        with self._lock:
            if int(self._slider.value) == index:
                self._display(index)
            else:
                self._slider.value = index  # its on_update callback displays it

    def _display(self, index: int) -> None:
        with self._lock:
            if index == self._shown or not 0 <= index < len(self._scenes):
                return
            label, node, arrays = self._scenes[index]
            if self._colour_by_relevance is not None and self._colour_by_relevance.value:
                from jaxedit.edit.local import relevance_colours

                arrays = dict(arrays, rgbs=relevance_colours(self._relevance, arrays["centers"]))
            # One node name: a new snapshot replaces the old one in every browser.
            self.server.scene.add_gaussian_splats("/scene", **arrays)
            self._caption.content = f"**{label}**  \n{len(arrays['centers'])} Gaussians"
            self._shown = index
            self._sync_buttons()

    def _redisplay(self) -> None:
        """Draw the snapshot on screen again (the colouring changed)."""
        with self._lock:
            index, self._shown = self._shown, None
            if index is not None:
                self._display(index)

    def node_on_screen(self) -> int | str | None:
        """The node on screen (:attr:`Snapshot.node`; None: the original or nothing)."""
        with self._lock:
            return None if self._shown is None else self._scenes[self._shown][1]

    def _sync_buttons(self) -> None:
        """Enable what applies to the node on screen and the operation running."""
        with self._lock:
            node = self.node_on_screen()
            self._button.disabled = node is None or self.run_dir is None
            if not self.steerable:
                return
            busy = self._operation is not None and self._operation.running
            for button in (self._refine, self._branch_button, self._extend):
                button.disabled = node is None or busy

    def select(self) -> Path | None:
        """Write ``selected.ply`` from the node on screen (keep, the button's action)."""
        from jaxedit.pipelines import select_snapshot

        with self._lock:
            if self._shown is None or self.run_dir is None:
                return None
            label, node, _ = self._scenes[self._shown]
            if node is None:
                return None
            path = select_snapshot(self.run_dir, node)
            self._status.content = f"wrote {path.name} from {label}"
            return path

    def _select_clicked(self, _event) -> None:
        from jaxedit import DataError

        try:
            self.select()
        except DataError as e:  # e.g. the run directory went away: say so in the panel
            self._status.content = f"error: {e}"

    # Steering (an edit run directory only)

    def start(self, op: str) -> Operation | None:
        """Start ``op`` ("refine", "branch", "extend") on the node on screen as a subprocess
        (the refine / branch / extend buttons); None, with the reason in the panel, when it
        cannot start (another operation running, no node, a branch that changes nothing)."""
        from jaxedit import DataError
        from jaxedit.pipelines.steer_run import read_tree

        with self._lock:
            node = self.node_on_screen()
            if self._operation is not None and self._operation.running:
                self._op_status.content = (f"error: {self._operation.op} "
                                           f"{self._operation.name} is still running")
                return None
            if node is None:
                self._op_status.content = f"error: {op} needs a subtask's snapshot on screen"
                return None
            seed = int(self._seed.value)
            prompt = str(self._prompt.value)
            settings = self.branch_settings()
            if (op == "branch" and not prompt.strip() and seed == run_seed(self.run_dir)
                    and not any(v is not None for v in settings.values())):
                self._op_status.content = ("error: branch: type a new instruction or change the "
                                           "seed, threshold, target subtasks or guidance")
                return None
            try:
                name = read_tree(self.run_dir).next_name()
            except DataError as e:  # a garbled tree.json
                self._op_status.content = f"error: {e}"
                return None
            argv = operation_argv(self.run_dir, op, node, name, prompt=prompt,
                                  seed=None if seed == run_seed(self.run_dir) else seed,
                                  r_max=float(self._r_max.value),
                                  **(settings if op == "branch" else {}))
            try:
                self._operation = Operation(op, name, argv, launch=self._launch,
                                            on_change=self.refresh_operation)
            except OSError as e:  # no such interpreter, too many processes, ...
                self._op_status.content = f"error: {op}: cannot start {argv[0]} ({e})"
                return None
            self._follow = name
            self.refresh_operation()
            return self._operation

    def branch_settings(self) -> dict:
        """What the branch control changes besides instruction and seed: ``threshold``,
        ``target_subtasks``, ``guidance`` (None: the run's, an input left at 0)."""
        threshold = float(self._threshold.value)
        target = int(self._target.value)
        guidance = (float(self._guidance_text.value), float(self._guidance_image.value))
        return {"threshold": threshold if threshold > 0 else None,
                "target_subtasks": target if target > 0 else None,
                "guidance": guidance if any(g > 0 for g in guidance) else None}

    def edit_progress(self, spec, step: int, loss: float, *, every: float = 1.0) -> None:
        """The running edit's subtask, step and loss in the panel (``edit --view``), at most
        once every ``every`` seconds."""
        now = time.monotonic()
        if now - self._edit_said_at < every:
            return
        self._edit_said_at = now
        self._edit_status.content = (f"editing: subtask {spec.index} {spec.name} "
                                     f"(r = {float(spec.ratio):.3f}), step {int(step)}, "
                                     f"loss {float(loss):.4f}")

    def edit_over(self, what: str) -> None:
        """The edit's outcome in the panel once it released the run (``edit --view``)."""
        self._edit_status.content = what

    def following(self, progress):
        """``progress(spec, step, loss, state)`` of an edit (its bars) that also puts the
        running subtask in the panel; its ``close`` is the bars'."""
        def both(spec, step, loss, st):
            progress(spec, step, loss, st)
            self.edit_progress(spec, step, loss)

        both.close = getattr(progress, "close", lambda: None)
        return both

    def refresh_operation(self) -> None:
        """The running operation's progress (or its outcome) into the panel."""
        with self._lock:
            op = self._operation
            if op is None or not self.steerable:
                return
            self._op_status.content = op.text(branch_progress(self.run_dir, op.name))
            if not op.running and op.returncode != 0:
                self._follow = None
            self._sync_buttons()

    def stop_edit(self) -> Path | None:
        """Ask the edit running in the run directory to stop after its current subtask
        (:func:`jaxedit.pipelines.steer_run.request_stop`); the stop button's action."""
        from jaxedit import DataError
        from jaxedit.pipelines.steer_run import request_stop

        try:
            path = request_stop(self.run_dir)
        except DataError as e:  # no edit running: say so in the panel
            self._op_status.content = f"error: {e}"
            return None
        self._op_status.content = "stop requested: the edit stops after its current subtask"
        return path

    def _stop_clicked(self, _event) -> None:
        self.stop_edit()

    def warm_up(self) -> None:
        """Start the operations' warm worker (a ``launch`` with ``start``, :class:`WarmWorker`)."""
        start = getattr(self._launch, "start", None)
        if self.steerable and start is not None:
            start()

    def serve_forever(self) -> None:
        """Block until Ctrl-C (the server runs on viser's own threads)."""
        try:
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:
            pass

    def close(self) -> None:
        """Stop the server and a running operation (``--branch NAME --resume`` goes on)."""
        op = self._operation
        if op is not None and op.running:
            op.proc.terminate()
            op.wait(30)
        getattr(self._launch, "close", lambda: None)()
        self.server.stop()


def run_seed(run_dir: Path | None) -> int:
    """The seed the run's main branch was edited with (schedule.json; 0 when unknown)."""
    try:
        return int(json.loads((Path(run_dir) / "schedule.json").read_text()).get("seed", 0))
    except (OSError, ValueError, TypeError, AttributeError):
        return 0


class RunWatcher:
    """Shows each snapshot a run directory gains in a viewer, polling from a background thread.

    The hook of ``edit --view`` and ``view``: the edit driver reports no snapshot event,
    so the watcher reads the run directory as the report does (tree.json, each branch's
    schedule.json and the snapshot files, all written atomically). Each poll also
    refreshes the progress of the viewer's running operation.
    """

    def __init__(self, run_dir: Path, viewer: SnapshotViewer, *, interval: float = 1.0):
        self.run_dir, self.viewer, self.interval = Path(run_dir), viewer, interval
        self._seen: dict[str, set[Path]] = {}  # per branch: the snapshots it shows
        self._arrays: dict[Path, dict] = {}  # a snapshot in several branches' chains: read once
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def refresh(self) -> int:
        """Add the snapshots not shown yet (every branch); returns how many were added."""
        from jaxedit import DataError
        from jaxedit.gaussians import splat_arrays
        from jaxedit.io import load_ply

        try:
            chains = branch_chains(self.run_dir)
        except DataError:
            return 0  # the run has not written its first snapshot yet (or is mid-rewrite)
        added = 0
        for branch, snaps in chains.items():
            seen = self._seen.setdefault(branch, set())
            for s in snaps:
                if s.path in seen:
                    continue
                if s.path not in self._arrays:
                    self._arrays[s.path] = splat_arrays(load_ply(s.path))
                self.viewer.add(branch, s.label, s.node, self._arrays[s.path])
                seen.add(s.path)
                added += 1
        self.viewer.refresh_operation()
        return added

    def _poll(self) -> None:
        while not self._stop.wait(self.interval):
            self.refresh()

    def start(self) -> RunWatcher:
        self._stop.clear()
        self._thread = threading.Thread(target=self._poll, name="jaxedit-view-watch", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop polling, then pick up what the run wrote last."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self.refresh()

    def serve_forever(self) -> None:
        """Poll and serve until Ctrl-C (``edit --view`` after its edit), then close the viewer."""
        if self._thread is None or not self._thread.is_alive():
            self.start()
        try:
            self.viewer.serve_forever()
        finally:
            self.stop()
            self.viewer.close()


def watch_run(run_dir: Path, *, port: int = DEFAULT_PORT,
              launch=launch_process) -> RunWatcher:
    """A watcher (not polling yet) of the edit run in ``run_dir``, its viewer serving every
    snapshot of every branch written so far."""
    run_dir = edit_run_dir(run_dir)
    branch_chains(run_dir)  # a clear error before a server starts
    viewer = SnapshotViewer(run_dir, port=port, launch=launch)
    watcher = RunWatcher(run_dir, viewer)
    try:
        watcher.refresh()
    except BaseException:
        viewer.close()
        raise
    return watcher


def open_run(run_dir: Path, *, port: int = DEFAULT_PORT,
             launch=launch_process) -> SnapshotViewer:
    """A viewer serving every snapshot of every branch of the edit run in ``run_dir``."""
    return watch_run(run_dir, port=port, launch=launch).viewer


def watch_edit(run_dir: Path, *, port: int = DEFAULT_PORT) -> RunWatcher:
    """``edit --view``: a viewer of ``run_dir`` refreshed from a background thread as subtasks
    end; its operations run in a :class:`WarmWorker` started once the edit is over."""
    viewer = SnapshotViewer(Path(run_dir), port=port, launch=WarmWorker(run_dir))
    print(f"viewer: {viewer.url} (refreshed as each subtask ends)", flush=True)
    return RunWatcher(run_dir, viewer).start()


def run(args) -> dict:
    config, run_dir = run_config(args), edit_run_dir(args.run_dir)
    watcher = watch_run(run_dir, port=config.port,
                        launch=WarmWorker(run_dir) if config.warm_worker else launch_process)
    viewer = watcher.viewer
    viewer.warm_up()
    print(f"viewer: {viewer.url} ({len(viewer)} snapshots; Ctrl-C to stop)", flush=True)
    watcher.serve_forever()  # new branches and snapshots appear as they are written
    return {"url": viewer.url, "snapshots": len(viewer)}
