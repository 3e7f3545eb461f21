"""The one exception type for bad input, and the range checks of config fields.

Readers and validators raise :class:`DataError` with a one-line message naming the file
or field; the CLI prints it and exits 2 (a real bug still shows its traceback).
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any


class DataError(ValueError):
    """Bad input: a missing/unreadable file, malformed content, or invalid values."""

    def __init__(self, where: str | os.PathLike | None, problem: str):
        self.where = None if where is None else str(where)
        self.problem = problem
        message = problem if where is None else f"{where}: {problem}"
        super().__init__(message.replace("\n", " "))


def quoted(text: str, limit: int = 80) -> str:
    """``repr(text)`` for an error line, cut to about ``limit`` characters."""
    if len(text) <= limit:
        return repr(text)
    return f"{text[:limit]!r}... ({len(text)} characters)"


# --- range checks of config fields -----------------------------------------------------
# A field declares its range once in its metadata (``ranged(30, low=0)``); ``__post_init__``
# calls :func:`check_ranges` and the generated flags show it in their help.

RANGE = "jaxedit.range"


@dataclasses.dataclass(frozen=True)
class Range:
    """The values a number field accepts: ``low`` <= v <= ``high`` (either may be None);
    ``open``: the bounds themselves excluded. None (an unset optional field) always passes."""

    low: float | None = None
    high: float | None = None
    open: bool = False

    def describe(self) -> str:
        low, high = self.low, self.high
        if low is not None and high is not None:
            return f"in ({low:g}, {high:g})" if self.open else f"in [{low:g}, {high:g}]"
        if self.open:
            return f"> {low:g}" if low is not None else f"< {high:g}"
        return f">= {low:g}" if low is not None else f"<= {high:g}"

    def problem(self, value) -> str | None:
        """The error text of ``value`` ("must be >= 1, got 0"), or None if it is in range; a
        tuple (a colour, a point) is in range when each of its items is."""
        if value is None:
            return None
        if isinstance(value, tuple):
            bad = [v for v in value if self.problem(v)]
            return f"must be {self.describe()} each, got {value}" if bad else None
        if self.open:
            bad = ((self.low is not None and not value > self.low)
                   or (self.high is not None and not value < self.high))
        else:
            bad = ((self.low is not None and not value >= self.low)
                   or (self.high is not None and not value <= self.high))
        return f"must be {self.describe()}, got {value}" if bad else None


def ranged(default, *, low: float | None = None, high: float | None = None,
           open: bool = False) -> Any:
    """A dataclass field of default ``default`` whose values must lie in the :class:`Range`
    (checked by :func:`check_ranges`)."""
    return dataclasses.field(default=default,
                             metadata={RANGE: Range(low=low, high=high, open=open)})


def field_range(field: dataclasses.Field) -> Range | None:
    """The :class:`Range` a field was declared with (:func:`ranged`), or None."""
    return field.metadata.get(RANGE)


def check_ranges(config) -> None:
    """DataError naming the first field of dataclass instance ``config`` outside its range."""
    for field in dataclasses.fields(config):
        bounds = field_range(field)
        problem = bounds and bounds.problem(getattr(config, field.name))
        if problem:
            raise DataError(field.name, problem)
