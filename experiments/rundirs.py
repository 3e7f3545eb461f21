"""A command's ``--out`` and other path flags: every path checked before any work
(:func:`check_paths`), the folder's lock held while the command runs and what a failed run
created removed (:func:`claimed_out`), a refused write reported as bad input
(:func:`write_refused`).
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import os
import shutil
import tempfile
from pathlib import Path

from .configfiles import flag_label


#: Path flags that name outputs (everything else of type Path is an input that must exist).
OUTPUT_DIRS = ("out",)
OUTPUT_FILES = ("output",)


def _check_utf8(path: Path, name: str) -> None:
    from jaxedit import DataError

    try:
        os.fsencode(path).decode("utf-8")
    except UnicodeDecodeError:
        raise DataError(name, f"path {os.fsencode(path)!r} is not valid UTF-8; "
                        "use a UTF-8 name") from None


def check_output_path(path: Path, name: str, *, directory: bool = True) -> None:
    """Refuse, before any work, an output that cannot be created or written.

    Args:
      path: the folder (``directory``) or file to write.
      name: the flag, for the message.
    """
    from jaxedit import DataError

    _check_utf8(path, name)
    path = Path(path)
    if path.exists():
        if directory and not path.is_dir():
            raise DataError(name, f"{path} exists and is not a directory")
        if not directory and path.is_dir():
            raise DataError(name, f"{path} is a directory, expected a file name")
        if directory and (path / "config.json").is_dir():  # every run records itself there
            raise DataError(name, f"{path / 'config.json'} is a folder, where the run records "
                                  f"its settings; move it or choose another {name}")
    existing = path if directory and path.is_dir() else path.parent
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise DataError(name, f"cannot create {path}: {existing} is a file, not a directory")
    try:  # a real write: permission bits, read-only mounts and root all answer truthfully
        fd, probe = tempfile.mkstemp(prefix=".jaxedit-probe-", dir=existing)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise DataError(name, f"{path}: cannot write in {existing} ({e.strerror or e})") from None


def check_input_path(path: Path, name: str) -> None:
    from jaxedit import DataError

    _check_utf8(path, name)
    if not Path(path).exists():
        raise DataError(path, f"does not exist (given as {name})")
    if not os.access(path, os.R_OK):
        raise DataError(path, f"is not readable (given as {name})")


def check_paths(args: argparse.Namespace, arguments, *, outputs: bool = True) -> None:
    """Check every path flag among the command's parser ``arguments`` (inputs exist, outputs
    can be made) up front; ``outputs`` False: inputs only (a process that writes nothing,
    :func:`writes`)."""
    for action in arguments:
        value = getattr(args, action.dest, None)
        if action.type is not Path or value is None or action.dest == "config":
            continue
        name = flag_label(action)
        if action.dest in OUTPUT_DIRS + OUTPUT_FILES and not outputs:
            continue
        if action.dest in OUTPUT_DIRS:  # a command whose --out is a file says so (export)
            check_output_path(value, name, directory=not getattr(args._module, "OUT_IS_FILE", False))
        elif action.dest in OUTPUT_FILES:
            check_output_path(value, name, directory=False)
        else:
            check_input_path(value, name)


def _first_missing(path: Path) -> Path | None:
    """The outermost folder of ``path`` that does not exist yet (None: it all exists)."""
    path = Path(os.path.abspath(path))
    missing = None
    while not path.exists():
        missing, path = path, path.parent
    return missing


#: OSError numbers of a write the machine refused (full disk, quota, read-only, too large):
#: the environment's fault, reported as one line like bad input.
WRITE_REFUSED = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG)


def write_refused(error: OSError, out: Path | None):
    """The :class:`jaxedit.DataError` of a refused write (None for other OS errors).

    Names the file when the OS did, else the output folder ``out``.
    """
    from jaxedit import DataError

    if error.errno not in WRITE_REFUSED:
        return None
    return DataError(error.filename or out, f"cannot write ({os.strerror(error.errno)}); "
                                            f"what this command wrote there was removed")


@contextlib.contextmanager
def claimed_out(out: Path | None):
    """Hold ``out``'s lock while the command runs; on a failure remove what it created.

    A failure is a DataError or a refused write (:func:`write_refused`, raised as a
    DataError). Entries of ``out`` that existed before (a resumed run's checkpoints) are
    kept, and its ``config.json`` is put back as it was: a failed command leaves the
    record of the run alone. A DataError whose ``record`` names a file under ``out`` (the
    editor identity check's ``identity.json``) keeps that file: the record of why it stopped.
    """
    from jaxedit import DataError
    from jaxedit.io.files import LOCK_NAME, folder_lock

    if out is None:
        yield
        return
    created = _first_missing(out)
    before = None if created is not None else set(os.listdir(out))
    with folder_lock(out, flag="--out"), _record_kept(Path(out) / "config.json"):
        try:
            try:
                yield
            except OSError as e:
                refused = write_refused(e, out)
                if refused is None:
                    raise
                raise refused from None
        except DataError as e:
            remove_created(out, created, before, keep={LOCK_NAME, KEPT_RECORD},
                           record=getattr(e, "record", None))
            raise


def remove_created(out: Path, created: Path | None, before: set | None, *,
                   keep: set = frozenset(), record: Path | None = None) -> None:
    """Remove what a failed command created under ``out``: ``created`` (the outermost
    folder it made, :func:`_first_missing`), else the entries not in ``before`` (the
    listing before it ran) nor in ``keep``. ``record``, a file the failure wrote on
    purpose, stays (with the folders above it)."""
    record = None if record is None else Path(os.path.abspath(record))
    if created is not None:
        _remove_all_but(Path(os.path.abspath(created)), record)
        return
    for name in set(os.listdir(out)) - before - set(keep):
        _remove_all_but(Path(os.path.abspath(Path(out) / name)), record)


def _remove_all_but(target: Path, record: Path | None) -> None:
    """Remove ``target`` (a file or a folder) except ``record`` and the folders above it."""
    if record is not None and record == target:
        return
    if target.is_dir() and not target.is_symlink():
        if record is not None and target in record.parents:
            for entry in target.iterdir():
                _remove_all_but(entry, record)
        else:
            shutil.rmtree(target, ignore_errors=True)
    else:
        target.unlink(missing_ok=True)


KEPT_RECORD = ".config.json.kept"


@contextlib.contextmanager
def _record_kept(record: Path):
    """Put ``record`` back as it was if the block fails with a DataError.

    The old file stays hard-linked under a hidden name meanwhile (the new record is
    written beside it and renamed over it), so putting it back is a rename: it needs
    no free space, which a full disk would not give.
    """
    from jaxedit import DataError

    kept = record.with_name(KEPT_RECORD)
    had = record.is_file()
    if had:
        kept.unlink(missing_ok=True)
        os.link(record, kept)
    try:
        yield
    except DataError:
        if had:
            os.replace(kept, record)
        raise
    finally:
        kept.unlink(missing_ok=True)


def writes(args: argparse.Namespace) -> bool:
    """Whether this process writes the command's outputs (in a multi-process run only
    process 0 does; the others write nothing)."""
    return getattr(args, "_writer", True)
