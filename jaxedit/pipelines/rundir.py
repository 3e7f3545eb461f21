"""Run directories. A training run's files, as callbacks of :func:`jaxedit.train.fit`:
:class:`JsonlLog` appends each record as a JSON line, :class:`RollingCheckpoints` writes
atomic ``ckpt_<step>.npz`` files and keeps the newest few, :func:`resume` finds the newest.
An edit's: :class:`RunDir`.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import DataError
from ..io.files import atomic_path, atomic_write_text
from ..train.checkpoint import load_checkpoint, save_checkpoint
from ..train.state import TrainState

#: Checkpoints kept by :class:`RollingCheckpoints` unless told otherwise.
KEEP_CHECKPOINTS = 2


def checkpoint_name(step: int) -> str:
    """``ckpt_<step>.npz``, zero-padded so that names sort by step."""
    return f"ckpt_{int(step):08d}.npz"


def latest_checkpoint(directory: str | os.PathLike) -> Path | None:
    """The checkpoint of the highest step in ``directory`` (None if there is none)."""
    directory = Path(directory)
    if not directory.is_dir():
        return None
    found = sorted(directory.glob("ckpt_*.npz"))
    return found[-1] if found else None


def prune_checkpoints(directory: str | os.PathLike, keep: int) -> None:
    """Delete all but the newest ``keep`` checkpoints in ``directory``."""
    for old in sorted(Path(directory).glob("ckpt_*.npz"))[:-keep]:
        try:
            old.unlink()
        except FileNotFoundError:
            pass


def resume(checkpoint: str | os.PathLike) -> TrainState:
    """The state of ``checkpoint``: a file, or a directory (its newest ``ckpt_*.npz``)."""
    path = Path(checkpoint)
    if path.is_dir():
        found = latest_checkpoint(path)
        if found is None:
            raise DataError(path, "no ckpt_*.npz checkpoint in this directory")
        path = found
    elif not path.exists():
        raise DataError(path, "no such checkpoint file or directory")
    return load_checkpoint(path)


class RollingCheckpoints:
    """``fit(checkpoint=RollingCheckpoints(dir))``: ``ckpt_<step>.npz`` files, the newest ``keep`` kept."""

    def __init__(self, directory: str | os.PathLike, keep: int = KEEP_CHECKPOINTS):
        if keep < 1:
            raise DataError("keep", f"must be >= 1, got {keep}")
        self.directory, self.keep = Path(directory), int(keep)

    def __call__(self, state: TrainState) -> Path:
        path = save_checkpoint(self.directory / checkpoint_name(int(state.step)), state)
        prune_checkpoints(self.directory, self.keep)
        return path


class JsonlLog:
    """``fit(log=JsonlLog(path))``: one JSON line per record, appended and flushed.

    A context manager (the file is opened on entry and closed on exit); appending
    means a resumed run continues the log of the run it resumes.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._file = None

    def __enter__(self) -> "JsonlLog":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "a", encoding="utf-8")
        return self

    def __exit__(self, *exc) -> None:
        self._file.close()
        self._file = None

    def __call__(self, record: dict) -> None:
        if self._file is None:
            raise RuntimeError(f"{self.path}: JsonlLog used outside its `with` block")
        self._file.write(json.dumps(record) + "\n")
        self._file.flush()


# ----------------------------------------------------------------------------- an edit's


#: An edit run directory's files (:class:`RunDir`).
CHECKPOINT_NAME = "checkpoint.npz"
#: The editor identity check's record of a run it stopped.
IDENTITY_NAME = "identity.json"
#: The difficulty oracle's edits and distances, read back by the run's branches.
ORACLE_NAME = "difficulty.npz"
#: A local edit's folder: its relevance over the held-out views.
LOCAL_DIR = "local"


def read_oracle_memo(oracle, path: Path) -> bool:
    """Give ``oracle`` the edits of the memo file ``path`` if it is this oracle's
    (:meth:`jaxedit.edit.difficulty.DifficultyOracle.restore`); False when absent or not."""
    if not Path(path).is_file():
        return False
    try:
        with np.load(path, allow_pickle=False) as memo:
            return oracle.restore(memo)
    except (OSError, ValueError, KeyError) as e:
        raise DataError(path, f"unreadable difficulty memo ({e}); delete it to recompute") from None


def write_oracle_memo(oracle, path: Path) -> None:
    """The oracle's edits and distances, atomically, for the run's branches."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **oracle.memo())


def _write_json(path: Path, data: dict) -> None:
    atomic_write_text(path, json.dumps(data, indent=2) + "\n")


@dataclasses.dataclass(frozen=True)
class RunDir:
    """An edit's run directory, the only place an edit writes (``path`` None: an edit in
    memory, whose writes do nothing): its checkpoint, snapshots, schedule.json,
    metrics.json, the difficulty memo and the report. Locks are the commands' business."""

    path: Path | None

    @staticmethod
    def at(path: str | os.PathLike | None) -> "RunDir":
        return RunDir(None if path is None else Path(path))

    @property
    def checkpoint(self) -> Path | None:
        return None if self.path is None else self.path / CHECKPOINT_NAME

    def memo(self, start=None) -> Path | None:
        """The difficulty oracle's memo file: a branch's ``start.memo``, else the run's own."""
        if start is not None:
            return start.memo
        return None if self.path is None else self.path / ORACLE_NAME

    def resume(self, ctx, gaussians, log: Callable[[str], None]) -> tuple:
        """(state, plan, header, wall seconds so far) of the run's checkpoint, checked against
        ``ctx``'s views and the snapshots before anything is written. Raises DataError."""
        from ..edit.checkpoint import check_resume, load_checkpoint
        from ..edit.plan import SubtaskSpec

        ckpt = self.checkpoint
        if ckpt is None or not ckpt.exists():
            raise DataError(ckpt or "run_dir", "no checkpoint to resume from")
        st, meta = load_checkpoint(ckpt, ctx.trainer.init(gaussians))
        check_resume(ckpt, st, ctx.data.train_images.shape, self.path)
        log(f"resuming subtask {st.subtask} at step {st.step} from {ckpt}")
        return (st, tuple(SubtaskSpec(**p) for p in meta["plan"]), meta["header"],
                meta.get("wall_time_s", 0.0))

    def write_identity(self, error) -> None:
        """The record of a run the editor identity check (``error``) stopped."""
        if self.path is not None:
            _write_json(self.path / IDENTITY_NAME, dict(error.figures, stopped=str(error)))
            error.record = self.path / IDENTITY_NAME  # kept by the command's cleanup

    def write_memo(self, oracle, restored: bool, start=None) -> bool:
        """The oracle's edits, for the run's branches: the path's owner (re)writes its memo;
        a branch adds to it, never over another's. Whether it wrote."""
        memo = self.memo(start)
        if oracle is not None and memo is not None and (
                restored or start is None or not memo.exists()):
            write_oracle_memo(oracle, memo)
            return True
        return False

    def write_original(self, ctx, gaussians, local_plan=None) -> None:
        """The input scene's snapshot and a local edit's region at the held-out views."""
        from ..edit import local as local_lib
        from .snapshots import write_scene_snapshot

        if self.path is None:
            return
        write_scene_snapshot(ctx, self.path / "original", gaussians, ratio=0.0)
        if local_plan is not None:
            data = ctx.data
            local_lib.write_overlays(self.path / LOCAL_DIR, gaussians, data.test_cameras,
                                     data.test_images, local_plan.editable,
                                     relevance=local_plan.relevance)

    def save(self, st, plan, header: dict, wall_time_s: float) -> None:
        """The checkpoint of ``st`` with the run's plan and header."""
        from ..edit.checkpoint import save_checkpoint

        if self.path is not None:
            save_checkpoint(self.checkpoint, st, {"plan": [dataclasses.asdict(p) for p in plan],
                                                  "header": header, "wall_time_s": wall_time_s})

    def write_schedule(self, schedule: dict) -> None:
        if self.path is not None:
            _write_json(self.path / "schedule.json", schedule)

    def write_snapshot(self, ctx, spec, gaussians, record: dict, reference,
                       shapes: dict) -> dict:
        """``record`` with the finished subtask's snapshot (``subtasks/NN_rX.XXX``), its
        metrics, fingerprint and the state's ``shapes`` (capacity, tile buffer: a branch
        from it starts on them, so the programs compiled for this run fit)."""
        from ..edit.checkpoint import snapshot_fingerprint
        from .snapshots import write_scene_snapshot

        rel = Path("subtasks") / spec.dirname
        metrics = write_scene_snapshot(ctx, self.path / rel, gaussians, ratio=spec.ratio,
                                       reference=reference)
        return dict(record, metrics=metrics, snapshot=str(rel / "scene.ply"),
                    **snapshot_fingerprint(self.path / rel / "scene.ply"), shapes=shapes)

    def finish(self, metrics: dict, select=None, report: bool = True) -> None:
        """metrics.json, ``selected.ply`` (``select``) and report.html."""
        from .report import write_report
        from .snapshots import select_snapshot

        if self.path is None:
            return
        _write_json(self.path / "metrics.json", metrics)
        if select is not None:
            select_snapshot(self.path, select)
        if report:
            write_report(self.path)
