"""The one exception type for bad input.

Every reader and validator in jaxedit raises :class:`DataError` with a one-line
message that names the file or field and what is wrong with it. The CLI prints
that line and exits with status 2; nothing else is caught there, so a real bug
still shows its traceback.
"""

from __future__ import annotations

import os


class DataError(ValueError):
    """Bad input: a missing/unreadable file, malformed content, or invalid values."""

    def __init__(self, where: str | os.PathLike | None, problem: str):
        self.where = None if where is None else str(where)
        self.problem = problem
        message = problem if where is None else f"{where}: {problem}"
        super().__init__(message.replace("\n", " "))


def quoted(text: str, limit: int = 80) -> str:
    """``repr(text)`` for an error line, cut to about ``limit`` characters: a message names
    what the user gave (a prompt may be pages long) without echoing all of it."""
    if len(text) <= limit:
        return repr(text)
    return f"{text[:limit]!r}... ({len(text)} characters)"
