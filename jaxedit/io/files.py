"""Atomic file writes (a crash never leaves a half-written file), folder locks, npz reads."""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path next to ``path`` (same suffix); rename it onto ``path`` on success."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    # mkstemp creates owner-only files; outputs are ordinary files, readable as the umask allows.
    os.chmod(tmp, 0o666 & ~current_umask())
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


#: The lock file a running command keeps in its output folder.
LOCK_NAME = ".jaxedit.lock"


@contextlib.contextmanager
def folder_lock(folder: str | os.PathLike, *, flag: str = "folder"):
    """Create ``folder`` and hold an exclusive ``flock`` on it, or raise a :class:`DataError`
    naming the holder's pid; the kernel releases it if the holder dies."""
    import fcntl

    from ..errors import DataError

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / LOCK_NAME
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 32).decode("ascii", "replace").strip() or "?"
            os.close(fd)
            raise DataError(flag, f"{folder} is in use by another jaxedit process (pid {holder}); "
                            "wait for it to finish or choose another folder") from None
        # the previous holder may have removed the file between our open and flock
        try:
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        yield path
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)
        os.close(fd)


def read_npz(path) -> dict:
    """Every array of an ``.npz`` file, or a DataError naming it (empty, truncated, not a zip)."""
    import zipfile
    import zlib

    import numpy as np

    from ..errors import DataError

    path = Path(path)
    try:
        if path.stat().st_size == 0:
            raise DataError(path, "cannot read checkpoint (empty file); delete it to start over")
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error) as e:
        if isinstance(e, DataError):
            raise
        raise DataError(path, f"cannot read checkpoint ({type(e).__name__}: {e}); it may be "
                              f"truncated or not a checkpoint") from None
