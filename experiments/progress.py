"""Nested progress bars with ETA: rich's live bars on a terminal, plain lines in logs.

One :class:`Progress` per unit of long work; a child (``parent=...``) is a
stage inside its parent (a subtask inside an edit, the steps inside a subtask).
This module keeps the tree (counts, fractions, ETA, weights of unequal stages) and
leaves the drawing to ``rich.progress``. The parent's fraction includes the
running child's, so the overall ETA moves smoothly. Rates and ETAs are measured from
a bar's first advance on (its own or a child's), not from its creation: the first
unit's time (compilation, loading) and the units done before the bar opened (a
resumed run's, ``initial``) say nothing of the pace, so until a second advance, at
least :data:`MIN_SPAN` later, the ETA and rate read ``?``. How it is shown depends on
the mode:

- ``"bar"`` (default when stderr is a terminal): one live ``rich`` bar per open
  node of the tree, children indented under their parent, with percentage,
  elapsed time, ETA and the postfix fields; a finished child leaves one line
  behind ("done r0.500 400/400 in 1:23 loss=0.021").
- ``"log"`` (default otherwise, and with ``--quiet``): plain lines, the whole tree
  every ``log_interval`` seconds (10 s; 60 s when quiet) plus one line when a
  bar finishes -- readable in CI logs and ``nohup`` files::

      edit 2/5 [######------------] 41% 3:02<4:21 | r0.500 120/400 [###-----] 30% 0:25<0:58 loss=0.021

- ``"off"``: nothing (tests).

The library (``jaxedit``) never draws: it reports through plain callbacks, and the
commands turn those into these bars.

Commands call :func:`configure` once (``configure(quiet=args.quiet)``); every
bar created afterwards follows it. Updates are thread-safe (an editor thread may
report progress too). Nothing here touches the numerics: callers update bars
between jitted steps.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from typing import Callable, Iterable, TextIO

MODES = ("bar", "log", "off")
#: Seconds of work a rate must be measured over before it (and an ETA) is shown: two
#: updates close together would otherwise read as an absurd rate.
MIN_SPAN = 0.5

_settings = {"mode": None, "stream": None, "log_interval": None, "quiet": False}
# Bars that new parentless bars nest under (see :func:`nested`): lets a command that
# calls other commands (``demo``) show their bars inside its own.
_ambient: list["Progress"] = []


def configure(*, quiet: bool = False, mode: str | None = None, stream: TextIO | None = None,
              log_interval: float | None = None) -> None:
    """Set how bars created from now on are shown.

    Args:
      quiet: log lines only, and rarely (every 60 s), never a live bar.
      mode: force "bar", "log" or "off" (default: "bar" on a terminal, else "log").
      stream: where to write (default ``sys.stderr`` at the time of writing).
      log_interval: seconds between periodic log lines.
    """
    if mode is not None and mode not in MODES:
        raise ValueError(f"progress mode must be one of {MODES}, got {mode!r}")
    _settings.update(mode=mode, stream=stream, log_interval=log_interval, quiet=bool(quiet))


def format_seconds(seconds: float | None) -> str:
    """``"?"``, ``"M:SS"`` or ``"H:MM:SS"``."""
    if seconds is None or seconds != seconds or seconds == float("inf"):
        return "?"
    seconds = int(round(max(seconds, 0.0)))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


def _format_value(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


class Progress:
    """A progress bar, possibly nested under a parent.

    Args:
      total: units of work (``None``: unknown, shows a count and a rate).
      desc: short label.
      parent: the enclosing bar; the root draws the tree.
      mode, stream, log_interval: override :func:`configure`'s settings (root only).
      refresh: minimum seconds between redraws in bar mode (rich's refresh rate).
      clock: a monotonic clock (tests inject a fake one).
      weights: expected relative cost of each unit (``total`` of them), so the
        fraction and ETA of stages of unequal length are not skewed.
      initial: units already done when the bar opens (a resumed run's): counted in
        ``n``, not in the rate.

    Use as a context manager, or call :meth:`close`. ``update(n, **postfix)``
    advances and sets the key=value fields shown after the bar.
    """

    def __init__(self, total: int | None, desc: str = "", *, parent: "Progress | None" = None,
                 mode: str | None = None, stream: TextIO | None = None,
                 log_interval: float | None = None, refresh: float = 0.1,
                 clock: Callable[[], float] = time.monotonic,
                 weights: list[float] | None = None, initial: int = 0):
        if total is not None and total < 0:
            raise ValueError(f"total must be >= 0, got {total}")
        if weights is not None and (total is None or len(weights) != total
                                    or any(w < 0 for w in weights) or sum(weights) <= 0):
            raise ValueError(f"weights need one non-negative value per unit of total={total}")
        self.weights = None if weights is None else [float(w) for w in weights]
        self.total = total
        self.desc = desc
        if parent is None and _ambient and not _ambient[-1].closed:
            parent = _ambient[-1]
        self.parent = parent
        self.n = int(initial)
        self.postfix: dict = {}
        self.closed = False
        self._child: Progress | None = None
        if parent is None:
            quiet = _settings["quiet"]
            self._clock = clock
            self._lock = threading.RLock()
            self._stream = stream if stream is not None else _settings["stream"]
            self.mode = mode or _settings["mode"] or ("log" if quiet else self._auto_mode())
            if self.mode not in MODES:
                raise ValueError(f"progress mode must be one of {MODES}, got {self.mode!r}")
            default_interval = 60.0 if quiet else 10.0
            self._log_interval = (log_interval if log_interval is not None
                                  else _settings["log_interval"] or default_interval)
            self._last_log = clock()
            self._display = _RichDisplay(self._out(), refresh) if self.mode == "bar" else None
        else:
            self._clock = parent._root()._clock
            self._lock = parent._root()._lock
            self.mode = parent._root().mode
            with self._lock:
                parent._child = self
        self.start = self._clock()
        # (time, work done) at the first advance: where the measured rate starts.
        self._first: tuple[float, float] | None = None
        root = self._root()
        if root._display is not None:
            self._task = root._display.add(self)
        self._emit_event(None)
        if parent is None and self.mode != "off":
            self._compile_watch = _CompileWatch(self)

    # -- the tree ------------------------------------------------------------
    def _root(self) -> "Progress":
        node = self
        while node.parent is not None:
            node = node.parent
        return node

    def _chain(self) -> list["Progress"]:
        chain, node = [], self
        while node is not None and not node.closed:
            chain.append(node)
            node = node._child
        return chain

    def _out(self) -> TextIO:
        root = self._root()
        return root._stream if root._stream is not None else sys.stderr

    def _auto_mode(self) -> str:
        stream = self._stream if self._stream is not None else sys.stderr
        try:
            return "bar" if stream.isatty() else "log"
        except (AttributeError, ValueError):
            return "log"

    # -- numbers -------------------------------------------------------------
    @property
    def elapsed(self) -> float:
        return self._clock() - self.start

    @property
    def fraction(self) -> float | None:
        """Done fraction in [0, 1], counting the running child's share."""
        if not self.total:
            return None if self.total is None else 1.0
        child = self._child
        partial = (child.fraction or 0.0) if child is not None and not child.closed else 0.0
        if self.weights is not None:  # units of unequal expected cost
            n = min(self.n, self.total)
            done = sum(self.weights[:n]) + (self.weights[n] * partial if n < self.total else 0.0)
            return min(done / sum(self.weights), 1.0)
        return min((self.n + partial) / self.total, 1.0)

    def _done(self) -> float:
        """Work done, as the rate measures it: the fraction, or the count without a total."""
        f = self.fraction
        return float(self.n) if f is None else f

    def _measured(self) -> tuple[float, float] | None:
        """(work, seconds) since the first advance; None before a second advance at least
        :data:`MIN_SPAN` seconds after it."""
        if self._first is None:
            return None
        t0, done0 = self._first
        seconds, work = self._clock() - t0, self._done() - done0
        if seconds < MIN_SPAN or work <= 0.0:
            return None
        return work, seconds

    def rate(self) -> float | None:
        """Units per second since the first advance (fraction per second with a total);
        None until measured (:meth:`_measured`)."""
        measured = self._measured()
        return None if measured is None else measured[0] / measured[1]

    def eta(self) -> float | None:
        """Seconds left at the rate measured since the first advance; None until measured."""
        rate = self.rate()
        if rate is None or self.total is None:
            return None
        return (1.0 - self.fraction) / rate

    # -- updates -------------------------------------------------------------
    def update(self, n: int = 1, **postfix) -> None:
        """Advance by ``n`` units and set postfix fields (``loss=0.02``)."""
        with self._lock:
            self.n += n
            if postfix:
                self.postfix.update(postfix)
            if n > 0:  # this bar and its parents have advanced: their rates start here
                now, node = self._clock(), self
                while node is not None:
                    if node._first is None:
                        node._first = (now, node._done())
                    node = node.parent
        self._root()._draw()

    def set_postfix(self, **postfix) -> None:
        with self._lock:
            self.postfix.update(postfix)
        self._root()._draw()

    def child(self, total: int | None, desc: str = "") -> "Progress":
        """A bar nested under this one (same as ``Progress(total, desc, parent=self)``)."""
        return Progress(total, desc, parent=self)

    def close(self) -> None:
        with self._lock:
            if self.closed:
                return
            self.closed = True
            if self.parent is not None and self.parent._child is self:
                self.parent._child = None
        if getattr(self, "_compile_watch", None) is not None:
            self._compile_watch.stop()
        self._emit_event(self)

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close()

    def track(self, iterable: Iterable):
        """Yield from ``iterable``, advancing by one per item, then close."""
        with self:
            for item in iterable:
                yield item
                self.update(1)

    # -- drawing -------------------------------------------------------------
    def segment(self, width: int = 20) -> str:
        """This bar alone as text."""
        parts = [self.desc] if self.desc else []
        f = self.fraction
        if self.total is None:
            rate = self.rate()
            speed = ("?/s" if rate is None else f"{rate:.3g}/s" if rate >= 1.0
                     else f"{1.0 / rate:.3g}s/it")
            parts.append(f"{self.n} [{format_seconds(self.elapsed)}, {speed}]")
        else:
            filled = int(round(width * (f or 0.0)))
            bar = "#" * filled + "-" * (width - filled)
            parts.append(f"{self.n}/{self.total} [{bar}] {100 * (f or 0.0):3.0f}% "
                         f"{format_seconds(self.elapsed)}<{format_seconds(self.eta())}")
        parts += [f"{k}={_format_value(v)}" for k, v in self.postfix.items()]
        return " ".join(parts)

    def line(self) -> str:
        """The whole tree from this bar down, as one line."""
        with self._lock:
            chain = self._chain()
            width = 20 if len(chain) <= 1 else 12
            return " | ".join(node.segment(width) for node in chain)

    def _write(self, text: str) -> None:
        out = self._out()
        try:
            out.write(text)
            out.flush()
        except (OSError, ValueError):  # a closed/broken stream must not kill the work
            pass

    def _draw(self, force: bool = False) -> None:
        """Root only: update the rich bars (bar) or log periodically (log)."""
        if self.mode == "off":
            return
        with self._lock:
            if self.mode == "bar":
                for node in self._chain():
                    self._display.show(node)
                return
            now = self._clock()
            if force or now - self._last_log >= self._log_interval:
                self._last_log = now
                self._write(self.line() + "\n")

    def _emit_event(self, closed: "Progress | None") -> None:
        """Start/finish notices: a finished bar leaves one line in either mode."""
        root = self._root()
        if root.mode == "off":
            return
        with root._lock:
            if closed is None:
                if root.mode == "bar":
                    root._draw(force=True)
                    if self is root:
                        root._display.start()
                elif self is root:
                    root._write(f"start {self.desc or 'work'}"
                                + (f" ({self.total} steps)" if self.total is not None else "")
                                + "\n")
                return
            done = (f"done {closed.desc or 'work'} {closed.n}"
                    + (f"/{closed.total}" if closed.total is not None else "")
                    + f" in {format_seconds(closed.elapsed)}")
            if closed.postfix:
                done += " " + " ".join(f"{k}={_format_value(v)}" for k, v in closed.postfix.items())
            if root.mode == "bar":
                root._display.finish(closed, done)
                if closed is root:
                    root._display.stop()
                else:
                    root._draw(force=True)
            else:
                root._write(done + "\n")


class _CompileWatch:
    """While a root bar is open, says when XLA is compiling (the work stands still then, so
    the bars alone would look hung): the deepest open bar shows ``compiling=NAME 12s`` while a
    compile has run :data:`COMPILE_NOTICE` seconds or more, and log mode writes one line per
    such compile. It reads :func:`jaxedit.compilation.compiling_now` from a daemon thread."""

    #: Seconds a compile runs before it is shown (short ones would only flicker).
    COMPILE_NOTICE = 1.0
    POLL = 0.5

    def __init__(self, root: Progress):
        self.root = root
        self.done = threading.Event()
        self.logged: set[str] = set()
        self.thread = threading.Thread(target=self._run, name="compile-watch", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        from jaxedit.compilation import compiling_now

        shown = None
        while not self.done.wait(self.POLL):
            now = compiling_now()
            with self.root._lock:
                chain = self.root._chain()
                if not chain:
                    return
                node = chain[-1]
                if now is not None and now[1] >= self.COMPILE_NOTICE:
                    name, seconds = now
                    if self.root.mode == "log":
                        if name not in self.logged:  # once per program, not per poll
                            self.logged.add(name)
                            self.root._write(f"compiling {name} (XLA; the persistent cache "
                                             f"keeps it for the next run)\n")
                    else:
                        node.postfix["compiling"] = f"{name} {seconds:.0f}s"
                        shown = node
                        self.root._draw()
                elif shown is not None:
                    shown.postfix.pop("compiling", None)
                    shown = None
                    self.root._draw()

    def stop(self) -> None:
        self.done.set()


class _RichDisplay:
    """The live ``rich.progress`` display of one tree: a task per open node."""

    def __init__(self, stream: TextIO, refresh: float):
        from rich.console import Console
        from rich.progress import (BarColumn, Progress as RichProgress, TaskProgressColumn,
                                   TextColumn, TimeElapsedColumn)

        self.console = Console(file=stream, highlight=False)
        self.rich = RichProgress(
            TextColumn("{task.description}"), BarColumn(bar_width=24), TaskProgressColumn(),
            TextColumn("{task.fields[count]}"), TimeElapsedColumn(), TextColumn("<"),
            TextColumn("{task.fields[eta]}"), TextColumn("{task.fields[postfix]}"),
            console=self.console, refresh_per_second=max(1.0, 1.0 / max(refresh, 1e-3)),
            transient=False)

    @staticmethod
    def _depth(node: Progress) -> int:
        depth, parent = 0, node.parent
        while parent is not None:
            depth, parent = depth + 1, parent.parent
        return depth

    def add(self, node: Progress):
        return self.rich.add_task("  " * self._depth(node) + (node.desc or "work"),
                                  total=None if node.total is None else 1.0, count="",
                                  eta="?", postfix="")

    def show(self, node: Progress) -> None:
        """Set the node's task from the tree (its fraction counts the running child; the
        ETA is the node's own, :meth:`Progress.eta`, not rich's estimate)."""
        count = f"{node.n}" + (f"/{node.total}" if node.total is not None else "")
        postfix = " ".join(f"{k}={_format_value(v)}" for k, v in node.postfix.items())
        fraction = node.fraction
        self.rich.update(node._task, completed=fraction if fraction is not None else node.n,
                         count=count, eta=format_seconds(node.eta()), postfix=postfix)

    def finish(self, node: Progress, line: str) -> None:
        """A finished node leaves one line (above the live bars) and its bar goes."""
        self.rich.remove_task(node._task)
        self.rich.console.print(line, markup=False, highlight=False)

    def start(self) -> None:
        self.rich.start()

    def stop(self) -> None:
        self.rich.stop()


def training_bar(parent: Progress | None = None) -> Callable:
    """A ``progress`` callback for :func:`jaxedit.train.fit`: its events drive one bar.

    The bar opens on the first event (at the run's total and starting step, nested
    under ``parent`` or the ambient bar; a resumed run's steps are its ``initial``, not
    work timed) and closes when the run reaches its total.
    """
    state: dict = {}

    def on_event(event) -> None:
        bar = state.get("bar")
        if bar is None:
            bar = state["bar"] = Progress(event.total, event.desc, parent=parent,
                                          initial=event.step)
        elif event.step > bar.n:
            bar.update(event.step - bar.n, loss=event.loss, psnr=event.psnr,
                       gaussians=event.gaussians)
        if event.step >= event.total:
            bar.close()

    def close() -> None:
        if "bar" in state:
            state["bar"].close()

    on_event.close = close
    return on_event


@contextlib.contextmanager
def nested(bar: Progress):
    """Within this block, bars created without a parent become children of ``bar``."""
    _ambient.append(bar)
    try:
        yield bar
    finally:
        _ambient.remove(bar)


def track(iterable: Iterable, total: int | None = None, desc: str = "",
          parent: Progress | None = None):
    """``for x in track(items, desc="views"):`` -- a bar over an iterable."""
    if total is None and hasattr(iterable, "__len__"):
        total = len(iterable)
    return Progress(total, desc, parent=parent).track(iterable)


__all__ = ["MODES", "Progress", "configure", "format_seconds", "nested", "track", "training_bar"]
