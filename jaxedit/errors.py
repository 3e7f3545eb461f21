""":class:`DataError`, the one exception for bad input (one line naming the file or field;
the CLI exits 2), and the range checks of config fields."""

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


# A field declares its range once (``ranged(30, low=0)``); ``__post_init__`` checks it.

RANGE = "jaxedit.range"


@dataclasses.dataclass(frozen=True)
class Range:
    """``low`` <= v <= ``high`` (either may be None; ``open``: bounds excluded; None passes)."""

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
        """The error text of ``value`` (each item of a tuple), or None if it is in range."""
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
    """A dataclass field of default ``default`` whose values must lie in the :class:`Range`."""
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
