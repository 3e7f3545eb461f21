"""A training run's files, as callbacks of :func:`jaxedit.train.fit`: :class:`JsonlLog`
appends each record as a JSON line, :class:`RollingCheckpoints` writes atomic
``ckpt_<step>.npz`` files and keeps the newest few, :func:`resume` finds the newest.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from ..errors import DataError
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
