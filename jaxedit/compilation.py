"""Compiling once: JAX's persistent compilation cache, and a record of what a run compiled.

:func:`enable` switches both on (``import jaxedit`` does not); the cache lives under
``$JAXEDIT_CACHE/xla`` (or ``JAXEDIT_COMPILE_CACHE_DIR``), bounded by :func:`trim_cache`.
"""

from __future__ import annotations

import dataclasses
import os
import threading
import time
from pathlib import Path

#: Programs faster to compile than this are not cached (0: all; reads beat recompiles).
MIN_COMPILE_SECONDS = 0.0
#: The persistent cache's default bound (MiB).
DEFAULT_MAX_MB = 4096

_BACKEND_COMPILE = "/jax/core/compile/backend_compile_duration"
_TRACE = "/jax/core/compile/jaxpr_trace_duration"
_LOWER = "/jax/core/compile/jaxpr_to_mlir_module_duration"
_CACHE_HIT = "/jax/compilation_cache/cache_hits"


def persistent_cache_dir() -> Path | None:
    """The cache's default folder, or None for ``JAXEDIT_COMPILE_CACHE=0`` (off)."""
    if os.environ.get("JAXEDIT_COMPILE_CACHE", "1").strip().lower() in ("0", "false", "no", "off"):
        return None
    explicit = os.environ.get("JAXEDIT_COMPILE_CACHE_DIR")
    if explicit:
        return Path(os.path.expanduser(explicit))
    from .io.weights import cache_dir

    return cache_dir() / "xla"


def _env_number(name: str, default: float, *, zero_ok: bool, what: str) -> float:
    """Environment variable ``name``'s number (unset: ``default``), else DataError."""
    text = os.environ.get(name)
    if not text:
        return default
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (0 <= value if zero_ok else 0 < value) or value == float("inf"):
        from .errors import DataError

        raise DataError(name, f"must be {what}, got {text[:40]!r}")
    return value


def max_cache_bytes() -> int:
    """The persistent cache's bound in bytes (``JAXEDIT_COMPILE_CACHE_MB``, else
    :data:`DEFAULT_MAX_MB`); a value that is not a positive number is a DataError."""
    return int(_env_number("JAXEDIT_COMPILE_CACHE_MB", DEFAULT_MAX_MB, zero_ok=False,
                           what="a positive number of MiB") * 2 ** 20)


def min_compile_seconds() -> float:
    """The shortest compile the persistent cache keeps (``JAXEDIT_COMPILE_CACHE_MIN_S``, else
    :data:`MIN_COMPILE_SECONDS`); a value that is not a number >= 0 is a DataError."""
    return _env_number("JAXEDIT_COMPILE_CACHE_MIN_S", MIN_COMPILE_SECONDS, zero_ok=True,
                       what="a number of seconds, 0 or more")


def enable_persistent_cache(path: str | os.PathLike | None = None) -> Path | None:
    """Switch on JAX's persistent compilation cache in ``path`` (None:
    :func:`persistent_cache_dir`; one JAX already has is kept) -> its folder, or None when off.

    Raises:
      DataError: a bad ``JAXEDIT_COMPILE_CACHE_MB`` or ``_MIN_S``, before anything changes.
    """
    import jax

    configured = jax.config.jax_compilation_cache_dir
    if configured:
        return Path(configured)
    folder = Path(path) if path is not None else persistent_cache_dir()
    if folder is None:
        return None
    max_bytes, min_seconds = max_cache_bytes(), min_compile_seconds()
    trim_cache(folder, max_bytes)
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", min_seconds)
    # -1: no minimum entry size and no override of it by the file system's block size.
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    # -1: JAX keeps no bound of its own (the bound is trim_cache's, once per process).
    jax.config.update("jax_compilation_cache_max_size", -1)
    return folder


#: File name endings of JAX's cache entries and of the access times JAX writes beside them.
_ENTRY_SUFFIX, _ATIME_SUFFIX = "-cache", "-atime"


def trim_cache(folder: str | os.PathLike, max_bytes: int) -> int:
    """Remove the least recently used (accessed or modified) entries of ``folder`` until they
    take at most ``max_bytes`` -> the bytes removed (0 for a missing folder)."""
    entries, total = [], 0
    try:
        with os.scandir(folder) as listing:
            for entry in listing:
                if not entry.name.endswith(_ENTRY_SUFFIX):
                    continue
                try:
                    st = entry.stat()
                except FileNotFoundError:
                    continue
                entries.append((max(st.st_atime, st.st_mtime), entry.path, st.st_size))
                total += st.st_size
    except (FileNotFoundError, NotADirectoryError):
        return 0
    removed = 0
    for _, path, size in sorted(entries):
        if total - removed <= max_bytes:
            break
        for name in (path, path[:-len(_ENTRY_SUFFIX)] + _ATIME_SUFFIX):
            try:
                os.unlink(name)
            except FileNotFoundError:
                pass
        removed += size
    return removed


@dataclasses.dataclass
class _Program:
    count: int = 0          # compiled by XLA in this process
    cache_hits: int = 0     # read from the persistent cache instead
    seconds: float = 0.0    # wall time of both (a hit costs the read)


class _Counters:
    """Process-wide counters fed by ``jax.monitoring`` listeners (registered once)."""

    def __init__(self):
        self.lock = threading.Lock()
        self.programs: dict[str, _Program] = {}
        self.trace_seconds = 0.0
        self.lower_seconds = 0.0
        self.in_flight: dict[int, tuple[str, float]] = {}  # thread id -> (program, start)
        self.hit_in_flight: set[int] = set()

    def on_start(self, event, value, **kwargs):
        if event == _BACKEND_COMPILE:
            with self.lock:
                self.in_flight[threading.get_ident()] = (str(kwargs.get("fun_name", "?")),
                                                         time.monotonic())

    def on_event(self, event, **kwargs):
        if event == _CACHE_HIT:
            with self.lock:
                self.hit_in_flight.add(threading.get_ident())

    def on_duration(self, event, seconds, **kwargs):
        with self.lock:
            if event == _TRACE:
                self.trace_seconds += seconds
            elif event == _LOWER:
                self.lower_seconds += seconds
            elif event == _BACKEND_COMPILE:
                me = threading.get_ident()
                self.in_flight.pop(me, None)
                program = self.programs.setdefault(_short(kwargs.get("fun_name", "?")), _Program())
                if me in self.hit_in_flight:
                    self.hit_in_flight.discard(me)
                    program.cache_hits += 1
                else:
                    program.count += 1
                program.seconds += seconds


def _short(name) -> str:
    # jit(<name>) / pjit(<name>): the function's own name is what a reader recognises.
    name = str(name)
    for prefix in ("jit(", "pjit("):
        if name.startswith(prefix) and name.endswith(")"):
            return name[len(prefix):-1]
    return name


_COUNTERS: _Counters | None = None
_COUNTERS_LOCK = threading.Lock()


def _counters() -> _Counters:
    global _COUNTERS
    with _COUNTERS_LOCK:
        if _COUNTERS is None:
            from jax import monitoring

            counters = _Counters()
            monitoring.register_scalar_listener(counters.on_start)
            monitoring.register_event_listener(counters.on_event)
            monitoring.register_event_duration_secs_listener(counters.on_duration)
            _COUNTERS = counters
        return _COUNTERS


def start_recording() -> None:
    """Register the listeners (idempotent); :func:`compile_stats` counts from then on."""
    _counters()


def enable(path: str | os.PathLike | None = None) -> Path | None:
    """Switch on the persistent cache and the compile record, early -> the cache folder or None."""
    start_recording()
    return enable_persistent_cache(path)


def compile_stats(since: dict | None = None) -> dict:
    """What this process compiled (since an earlier result ``since``) -> ``{"count" (XLA
    compiles), "seconds", "cache_hits", "trace_seconds", "lower_seconds", "programs": {name:
    {"count", "cache_hits", "seconds"}}}``."""
    c = _counters()
    with c.lock:
        programs = {name: dataclasses.asdict(p) for name, p in c.programs.items()}
        trace, lower = c.trace_seconds, c.lower_seconds
    if since is not None:
        before = since.get("programs", {})
        programs = {name: {k: v - before.get(name, {}).get(k, 0) for k, v in p.items()}
                    for name, p in programs.items()}
        programs = {n: p for n, p in programs.items() if p["count"] or p["cache_hits"]}
        trace -= since.get("trace_seconds", 0.0)
        lower -= since.get("lower_seconds", 0.0)
    programs = {n: {**p, "seconds": round(p["seconds"], 4)}
                for n, p in sorted(programs.items(), key=lambda kv: -kv[1]["seconds"])}
    return {"count": sum(p["count"] for p in programs.values()),
            "seconds": round(sum(p["seconds"] for p in programs.values()), 3),
            "cache_hits": sum(p["cache_hits"] for p in programs.values()),
            "trace_seconds": round(trace, 3), "lower_seconds": round(lower, 3),
            "programs": programs}


def compiling_now() -> tuple[str, float] | None:
    """(program name, seconds so far) of a compile running in any thread now, else None."""
    c = _counters()
    with c.lock:
        if not c.in_flight:
            return None
        name, start = min(c.in_flight.values(), key=lambda v: v[1])
    return _short(name), time.monotonic() - start
