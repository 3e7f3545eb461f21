"""A cache of a dataset's views as loaded (downscaled, undistorted, cropped), beside it.

One ``.npy`` per view in ``<dataset>/.jaxedit_cache/``, named by a hash of the frame's
path and every setting that shapes its pixels, then of the source's size and mtime:
a changed photo or setting misses and the stale file is removed. An unwritable
dataset folder falls back to ``<jaxedit cache>/views/<hash>/``, then to no cache.
Entries are written atomically; an unreadable or mis-shaped one is rebuilt.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path

import numpy as np

from .files import atomic_path

log = logging.getLogger("jaxedit.io")

#: Bumped whenever the loader's pixels change for the same inputs.
VERSION = 1
FOLDER = ".jaxedit_cache"


def _digest(text: str, n: int) -> str:
    return hashlib.sha1(text.encode("utf-8", "surrogateescape")).hexdigest()[:n]


def _writable(folder: Path) -> bool:
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return False
    return os.access(folder, os.W_OK | os.X_OK)


def cache_folder(dataset_dir: str | os.PathLike) -> Path | None:
    """Where the views of the dataset in ``dataset_dir`` are cached: beside it when that
    folder can be written, else under jaxedit's cache folder; None (and a one-line
    warning) when neither can."""
    from .weights import cache_dir

    dataset_dir = Path(dataset_dir).resolve()
    beside = dataset_dir / FOLDER
    if _writable(beside):
        return beside
    home = cache_dir() / "views" / _digest(str(dataset_dir), 16)
    if _writable(home):
        return home
    log.warning("view cache: neither %s nor %s can be written; loading without a cache",
                beside, home)
    return None


class ViewCache:
    """The cached views of one dataset (``folder`` None: a cache that never hits)."""

    def __init__(self, folder: Path | None):
        self.folder = folder
        self.hits = 0
        self.misses = 0

    def entry(self, source: Path, name: str, settings: dict) -> Path | None:
        """The file of the view made from the file ``source`` (the frame's ``name`` in the
        dataset, which tells apart photos of one file name in different folders) with
        ``settings`` (JSON-able)."""
        if self.folder is None:
            return None
        try:
            st = source.stat()
        except OSError:
            return None
        # name: the source and settings; suffix: the source's state, so that a changed
        # photo replaces its own entry and other settings' entries stay.
        what = json.dumps({"v": VERSION, "source": name, **settings}, sort_keys=True)
        state = f"{st.st_size}:{st.st_mtime_ns}"
        return self.folder / f"{_digest(what, 20)}_{_digest(state, 12)}.npy"

    def get(self, entry: Path | None, shape: tuple, dtype) -> np.ndarray | None:
        """The cached view, or None when it is missing, unreadable or of another shape."""
        if entry is None:
            return None
        try:
            array = np.load(entry, allow_pickle=False)
        except (OSError, ValueError, EOFError):
            self.misses += 1
            return None
        if array.shape != tuple(shape) or array.dtype != np.dtype(dtype):
            self.misses += 1
            return None
        self.hits += 1
        return array

    def put(self, entry: Path | None, array: np.ndarray) -> None:
        """Store a view (atomically) and remove the stale entries of its source; a write
        that fails turns the cache off for the rest of the load, with one warning."""
        if entry is None or self.folder is None:
            return
        try:
            with atomic_path(entry) as tmp:
                np.save(tmp, np.ascontiguousarray(array), allow_pickle=False)
            prefix = entry.name.split("_")[0] + "_"
            for old in self.folder.glob(prefix + "*.npy"):
                if old != entry:
                    old.unlink(missing_ok=True)
        except OSError as e:
            log.warning("view cache: cannot write %s (%s); loading without a cache", entry,
                        e.strerror or e)
            self.folder = None
