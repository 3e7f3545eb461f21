"""``view``: an edit run's scene as Gaussian splats in the browser (viser).

    python -m experiments view RUN_DIR [--port 8080]

Serves, on 127.0.0.1 only, the snapshots an edit run wrote (``original/scene.ply``
then ``subtasks/NN_rX.XXX/scene.ply`` in schedule order) with viser, the viewer
library nerfstudio uses. A slider picks the snapshot, i.e. the aggressivity of the
edit; the button "write selected.ply" does what ``edit --select-only --select K``
does for the subtask on screen. A local edit's run (``edit --local`` / ``--region`` /
``--masks``, issue 35) adds a checkbox "colour by relevance": the splats take the colour
of their lifted relevance (``local/gaussians.npz``: blue 0 .. red 1, the editable
Gaussians' set where the run kept only that; yellow: Gaussians the edit moved or created,
all from editable ones), so the frozen part of the scene shows as what stayed bit for bit.
``edit --view`` serves the run the same way while it is edited: a background thread
polls the run directory and shows each snapshot as its subtask ends. To view a run on a
remote machine, forward the port (``ssh -L``).

Needs the optional extra ``viewer`` (``pip install 'jaxedit[viewer]'``).
"""

from __future__ import annotations

import dataclasses
import json
import threading
import time
from pathlib import Path

from jaxedit.errors import check_ranges, ranged

HELP = "serve an edit run's snapshots in the browser (viser): a slider over subtasks, select button"

HOST = "127.0.0.1"  # never 0.0.0.0: a run may be private; forward the port to share it
DEFAULT_PORT = 8080  # viser's; a taken port moves to the next free one


@dataclasses.dataclass(frozen=True)
class ViewConfig:
    """Where the viewer listens.

    Attributes:
      port: port on 127.0.0.1 (taken: the next free one; 0: any free port).
    """

    port: int = ranged(DEFAULT_PORT, low=0, high=65535)

    def __post_init__(self):
        check_ranges(self)


def _config_flags():
    from experiments.flags import Flag, FlagSet

    return FlagSet(ViewConfig, (Flag("port"),)).complete()


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
    """One scene state of a run: its label, its scene.ply, its subtask index (None: original)."""

    label: str
    path: Path
    subtask: int | None


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
        snaps += [Snapshot(f"subtask {s['index']} {s['name']} (r = {float(s['ratio']):.3f})",
                           run_dir / s["snapshot"], int(s["index"])) for s in records]
    except FileNotFoundError:
        pass
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise DataError(path, f"malformed schedule ({e})") from None
    if not snaps:
        raise DataError(run_dir, "no snapshot yet: not an edit run directory "
                                 "(no schedule.json or original/scene.ply)")
    return snaps


def relevance_of_run(run_dir: Path) -> dict | None:
    """A local edit's per-Gaussian relevance (``RUN_DIR/local/gaussians.npz``,
    :func:`jaxedit.edit.local.load_gaussian_relevance`), None for a global edit's run."""
    from jaxedit.edit.local import load_gaussian_relevance
    from jaxedit.pipelines.edit import LOCAL_DIR

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


class SnapshotViewer:
    """A viser server showing one of a growing list of scenes, picked with a slider.

    ``update(scene, label, subtask=...)`` adds a scene (a :class:`jaxedit.Gaussians`)
    and shows it when the slider was on the newest one (so a live view follows the
    edit unless the user went back). With a ``run_dir``, the button writes
    ``run_dir/selected.ply`` from the subtask on screen through
    :func:`jaxedit.pipelines.select_snapshot`, the code path of ``edit --select-only``.
    """

    def __init__(self, run_dir: Path | None = None, *, port: int = DEFAULT_PORT):
        viser = import_viser()
        self.run_dir = run_dir
        self.server = viser.ViserServer(host=HOST, port=port, verbose=False)
        self._lock = threading.RLock()  # GUI callbacks run on viser's threads
        self._scenes: list[tuple[str, int | None, dict]] = []  # (label, subtask, splat arrays)
        self._shown: int | None = None
        gui = self.server.gui
        self._slider = gui.add_slider("snapshot", min=0, max=0, step=1, initial_value=0,
                                      hint="subtask snapshots, least to most edited")
        self._caption = gui.add_markdown("waiting for the first snapshot")
        self._button = gui.add_button("write selected.ply", disabled=True,
                                      hint="like edit --select-only --select K")
        self._status = gui.add_markdown("")
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

    @property
    def url(self) -> str:
        return f"http://{HOST}:{self.server.get_port()}/"

    def __len__(self) -> int:
        with self._lock:  # not mid-update
            return len(self._scenes)

    def update(self, scene, label: str, *, subtask: int | None = None) -> None:
        """Add ``scene`` (Gaussians) as the newest snapshot, labelled for the user.

        ``subtask``: its subtask index in the run (what the select button writes);
        None for scenes that are no subtask's snapshot (the original).
        """
        from jaxedit.gaussians import splat_arrays

        arrays = splat_arrays(scene)
        with self._lock:
            follow = self._shown is None or self._shown == len(self._scenes) - 1
            self._scenes.append((label, subtask, arrays))
            if len(self._scenes) == 1 and len(arrays["centers"]):
                self._aim(*camera_pose(arrays["centers"]))
            self._slider.max = len(self._scenes) - 1
            if follow:
                self.show(len(self._scenes) - 1)

    def _aim(self, position, look_at) -> None:
        """Frame the first scene, also in browsers opened before it arrived (edit --view)."""
        self.server.initial_camera.look_at = look_at
        self.server.initial_camera.position = position
        for client in self.server.get_clients().values():
            client.camera.position = position  # moves look_at along: set it second
            client.camera.look_at = look_at

    def show(self, index: int) -> None:
        """Put snapshot ``index`` on screen and the slider on it."""
        with self._lock:
            if int(self._slider.value) == index:
                self._display(index)
            else:
                self._slider.value = index  # its on_update callback displays it

    def _display(self, index: int) -> None:
        with self._lock:
            if index == self._shown or not 0 <= index < len(self._scenes):
                return
            label, subtask, arrays = self._scenes[index]
            if self._colour_by_relevance is not None and self._colour_by_relevance.value:
                from jaxedit.edit.local import relevance_colours

                arrays = dict(arrays, rgbs=relevance_colours(self._relevance, arrays["centers"]))
            # One node name: a new snapshot replaces the old one in every browser.
            self.server.scene.add_gaussian_splats("/scene", **arrays)
            self._caption.content = f"**{label}**  \n{len(arrays['centers'])} Gaussians"
            self._button.disabled = subtask is None or self.run_dir is None
            self._shown = index

    def _redisplay(self) -> None:
        """Draw the snapshot on screen again (the colouring changed)."""
        with self._lock:
            index, self._shown = self._shown, None
            if index is not None:
                self._display(index)

    def select(self) -> Path | None:
        """Write ``selected.ply`` from the subtask on screen (the button's action)."""
        from jaxedit.pipelines import select_snapshot

        with self._lock:
            if self._shown is None or self.run_dir is None:
                return None
            label, subtask, _ = self._scenes[self._shown]
            if subtask is None:
                return None
            path = select_snapshot(self.run_dir, subtask)
            self._status.content = f"wrote {path.name} from {label}"
            return path

    def _select_clicked(self, _event) -> None:
        from jaxedit import DataError

        try:
            self.select()
        except DataError as e:  # e.g. the run directory went away: say so in the panel
            self._status.content = f"error: {e}"

    def serve_forever(self) -> None:
        """Block until Ctrl-C (the server runs on viser's own threads)."""
        try:
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:
            pass

    def close(self) -> None:
        self.server.stop()


class RunWatcher:
    """Shows each snapshot a run directory gains in a viewer, polling from a background thread.

    The hook of ``edit --view``: the edit driver reports no snapshot event, so the
    watcher reads the run directory as the report does (schedule.json and the
    snapshot files, all written atomically).
    """

    def __init__(self, run_dir: Path, viewer: SnapshotViewer, *, interval: float = 1.0):
        self.run_dir, self.viewer, self.interval = Path(run_dir), viewer, interval
        self._seen: set[Path] = set()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def refresh(self) -> int:
        """Add the snapshots not shown yet; returns how many were added."""
        from jaxedit import DataError
        from jaxedit.io import load_ply

        try:
            snaps = run_snapshots(self.run_dir)
        except DataError:
            return 0  # the run has not written its first snapshot yet
        new = [s for s in snaps if s.path not in self._seen]
        for s in new:
            self.viewer.update(load_ply(s.path), s.label, subtask=s.subtask)
            self._seen.add(s.path)
        return len(new)

    def _poll(self) -> None:
        while not self._stop.wait(self.interval):
            self.refresh()

    def start(self) -> RunWatcher:
        self._thread = threading.Thread(target=self._poll, name="jaxedit-view-watch", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop polling, then pick up what the run wrote last."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self.refresh()


def open_run(run_dir: Path, *, port: int = DEFAULT_PORT) -> SnapshotViewer:
    """A viewer serving every snapshot of the (finished) edit run in ``run_dir``."""
    run_dir = edit_run_dir(run_dir)
    run_snapshots(run_dir)  # a clear error before a server starts
    viewer = SnapshotViewer(run_dir, port=port)
    try:
        RunWatcher(run_dir, viewer).refresh()
    except BaseException:
        viewer.close()
        raise
    return viewer


def watch_edit(run_dir: Path, *, port: int = DEFAULT_PORT) -> RunWatcher:
    """``edit --view``: a viewer of ``run_dir`` refreshed from a background thread as subtasks end."""
    viewer = SnapshotViewer(Path(run_dir), port=port)
    print(f"viewer: {viewer.url} (refreshed as each subtask ends)", flush=True)
    return RunWatcher(run_dir, viewer).start()


def run(args) -> dict:
    viewer = open_run(args.run_dir, port=run_config(args).port)
    try:
        print(f"viewer: {viewer.url} ({len(viewer)} snapshots; Ctrl-C to stop)", flush=True)
        viewer.serve_forever()
    finally:
        viewer.close()
    return {"url": viewer.url, "snapshots": len(viewer)}
