"""Several processes on JAX's distributed runtime: joining it, splitting edits over the
processes, and supervising workers (the runtime ``abort()`` s on a lost peer)."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import signal
import subprocess
import sys
import threading
from typing import Any, Sequence

import numpy as np

from ..errors import DataError, check_ranges, ranged

#: Environment variable that marks a supervised worker process (:func:`supervise`).
WORKER_ENV = "JAXEDIT_DISTRIBUTED_WORKER"

#: ``--coordinator`` value that lets JAX find the cluster itself (TPU slices, SLURM, Open MPI).
AUTO = "auto"


@dataclasses.dataclass(frozen=True)
class DistributedConfig:
    """How this process joins a multi-process run (one process: the defaults).

    Attributes:
      coordinator: HOST:PORT of process 0's coordinator; auto: detected; unset: one process.
      num_processes: processes in the run (one per host, or per GPU).
      process_id: this process's index, 0 .. num_processes - 1; process 0 writes the outputs.
      init_timeout: seconds to wait for every process to reach the coordinator.
      heartbeat_timeout: seconds without a heartbeat after which a process counts as dead.
    """

    coordinator: str | None = None
    num_processes: int = ranged(1, low=1)
    process_id: int = 0
    init_timeout: int = ranged(120, low=1)
    heartbeat_timeout: int = ranged(30, low=1)

    def __post_init__(self):
        check_ranges(self)
        if not 0 <= self.process_id < self.num_processes:
            raise DataError("process_id", f"must be in 0 .. {self.num_processes - 1} "
                                          f"(num_processes), got {self.process_id}")
        if self.coordinator is None:
            if self.num_processes > 1 or self.process_id:
                raise DataError("coordinator", "required with num_processes > 1 (HOST:PORT "
                                               "of process 0, or auto)")
        elif self.coordinator != AUTO:
            parse_address(self.coordinator)

    @property
    def active(self) -> bool:
        """Whether this process joins a distributed runtime at all."""
        return self.coordinator is not None


def parse_address(address: str) -> tuple[str, int]:
    """(host, port) of ``HOST:PORT`` (IPv6 hosts in brackets); DataError if malformed."""
    host, sep, port = str(address).rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise DataError("coordinator", f"expected HOST:PORT (port 1-65535), got {address!r}")
    return host, int(port)


def initialize(config: DistributedConfig) -> None:
    """Join the distributed runtime before anything else touches JAX (no-op for one
    process); DataError when the coordinator is unreachable."""
    if not config.active:
        return
    import jax
    from jax._src import distributed as _dist  # the client, to leave no half-joined state

    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    manual = {} if config.coordinator == AUTO else dict(
        coordinator_address=config.coordinator, num_processes=config.num_processes,
        process_id=config.process_id)
    try:
        jax.distributed.initialize(**manual, initialization_timeout=config.init_timeout,
                                   heartbeat_timeout_seconds=config.heartbeat_timeout,
                                   shutdown_timeout_seconds=config.heartbeat_timeout)
    except RuntimeError as e:  # JaxRuntimeError, and "called after the backend started"
        state = _dist.global_state
        state.client = None  # its atexit shutdown would raise again, with a traceback
        if state.service is not None:
            state.service.shutdown()
            state.service = None
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise DataError("coordinator", f"cannot join {config.coordinator} as process "
                        f"{config.process_id} of {config.num_processes} within "
                        f"{config.init_timeout} s ({first[:160]})") from None
    except ValueError as e:  # auto: no cluster environment found
        raise DataError("coordinator", str(e).splitlines()[0]) from None


AGREEMENT_KEY = "jaxedit/agreement/"
#: The settings compared first (the message names the first that differs).
AGREEMENT_FIRST = ("num_processes", "out")


def disagreement(mine: dict, theirs: dict) -> str | None:
    """The first setting on which two records {setting: JSON value} differ (None: agree)."""
    keys = [k for k in AGREEMENT_FIRST if k in mine or k in theirs]
    keys += sorted((set(mine) | set(theirs)) - set(keys))
    for key in keys:
        if mine.get(key) != theirs.get(key):
            return key
    return None


def check_agreement(record: dict, timeout: int) -> None:
    """Refuse to go on unless every process publishes the same ``record`` ({setting: JSON
    value}); a no-op for one process.

    Raises:
      DataError: naming the first flag that differs, the two values and the processes.
    """
    import jax
    from jax._src import distributed as _dist

    client = _dist.global_state.client
    if client is None or process_count() == 1:
        return
    me, count = process_index(), process_count()
    client.key_value_set(f"{AGREEMENT_KEY}{me}", json.dumps(record, sort_keys=True))
    for other in [0] + [p for p in range(1, count)]:
        if other == me:
            continue
        try:
            theirs = json.loads(client.blocking_key_value_get(f"{AGREEMENT_KEY}{other}",
                                                              timeout * 1000))
        except jax.errors.JaxRuntimeError as e:
            if "DEADLINE" in str(e).upper():  # it never came: there is no such process
                raise DataError("--num-processes", f"process {me} of {count} found no "
                                f"process {other} within {timeout} s: the processes "
                                f"disagree on their number") from None
            raise DataError(f"process {me} of {count}", f"process {other} stopped before "
                            f"every process's settings were compared") from None
        key = disagreement(record, theirs)
        if key is not None:
            flag = f"--{key.replace('_', '-')}"
            raise DataError(flag, f"the processes disagree: process {me} has "
                            f"{json.dumps(record.get(key))[:60]}, process {other} "
                            f"{json.dumps(theirs.get(key))[:60]}; every process needs the same "
                            f"{flag}")


def process_index() -> int:
    """This process's index (0 without a distributed runtime)."""
    import jax

    return jax.process_index()


def process_count() -> int:
    """Processes in the run (1 without a distributed runtime)."""
    import jax

    return jax.process_count()


def is_writer() -> bool:
    """Whether this process writes the outputs: process 0, the only one."""
    return process_index() == 0


def process_slice(count: int, process: int, processes: int) -> slice:
    """The contiguous slice of ``count`` views that ``process`` edits (the last may be empty)."""
    per = -(-count // processes)
    lo = min(process * per, count)
    return slice(lo, min(lo + per, count))


def gather_views(local, count: int) -> np.ndarray:
    """float32 [count, H, W, 3]: every process's ``local`` [b, H, W, 3] in order (a collective)."""
    from jax.experimental import multihost_utils

    processes = process_count()
    per = -(-count // processes)
    local = np.asarray(local, np.float32)
    padded = np.zeros((per,) + local.shape[1:], np.float32)
    padded[:len(local)] = local
    stacked = multihost_utils.process_allgather(padded)  # [processes, per, H, W, 3]
    return np.asarray(stacked).reshape((processes * per,) + local.shape[1:])[:count]


def barrier(name: str) -> None:
    """Wait until every process reaches ``name`` (a no-op for one process)."""
    if process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)


class SplitEditor:
    """An editor whose ``edit_many`` edits this process's :func:`process_slice` and returns
    all B views gathered, float32 [B, H, W, 3]."""

    def __init__(self, editor):
        self.inner = editor
        self.batch = max(int(getattr(editor, "batch", 1)), 1) * process_count()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def edit(self, image, original, embedding, key, **kwargs):
        return self.inner.edit(image, original, embedding, key, **kwargs)

    def edit_many(self, images, originals, embeddings, keys, **kwargs) -> np.ndarray:
        from ..editors.base import edit_views

        count = len(images)
        part = process_slice(count, process_index(), process_count())
        mine = edit_views(self.inner, images[part], originals[part], embeddings,
                          keys[part], **kwargs) if part.stop > part.start else []
        shape = tuple(np.shape(images[0]))
        local = np.stack([np.asarray(v, np.float32) for v in mine]) if mine else np.zeros(
            (0,) + shape, np.float32)
        return gather_views(local, count)

    def relevance(self, *args, **kwargs):
        from ..editors.base import relevance

        return relevance(self.inner, *args, **kwargs)


def split_edits(editor):
    """``editor`` as a :class:`SplitEditor` when there are several processes, else itself."""
    return SplitEditor(editor) if process_count() > 1 else editor


#: A glog / absl line: severity, date, time, thread, file:line].
_LOG_LINE = re.compile(r"[IWEF]\d{4} \d\d:\d\d:\d\d\.\d+\s+\d+ [^\]]+\] ")
_FATAL = re.compile(r"F\d{4} \d\d:\d\d:\d\d\.\d+\s+\d+ [^\]]+\] ")
#: gloo's connection notice, also where a line begins inside an interleaved one.
_GLOO_NOTICE = re.compile(r"is connected to \d+ peer ranks|Expected number of connected peer")


def is_runtime_noise(line: str) -> bool:
    """Whether a worker's stderr line is the runtime's logging (glog, gloo, a fatal trace)."""
    return bool(_LOG_LINE.search(line) or line.startswith(("[Gloo] ", "*** Check failure"))
                or _GLOO_NOTICE.search(line) or re.match(r"\s+@\s+0x", line))


def fatal_reason(message: str, returncode: int, config: DistributedConfig) -> str:
    """The one-line reason a worker ended abnormally, from the runtime's fatal ``message``
    (may be empty) and its ``returncode`` (negative: the signal)."""
    text = " ".join(message.split())
    if "stopped sending heartbeats" in text or "heartbeat" in text.lower():
        tasks = re.search(r"heartbeats\):\s*([\d ,]+)", text)
        who = f"process {tasks.group(1).strip()}" if tasks else "another process"
        return (f"{who} stopped answering for {config.heartbeat_timeout} s "
                "(it died or its host is unreachable)")
    if "RegisterTask" in text or ("DEADLINE_EXCEEDED" in text and "Connect" in text):
        return (f"cannot reach the coordinator {config.coordinator} within "
                f"{config.init_timeout} s")
    if text:
        status = text.split("absl::Status: ", 1)[-1]
        if "UNAVAILABLE" in status or "coordination" in text.lower():
            return f"lost the distributed runtime ({status[:200]})"
        return status[:240]
    if returncode < 0:
        try:
            name = signal.Signals(-returncode).name
        except ValueError:
            name = f"signal {-returncode}"
        return f"killed by {name}"
    return f"exited with status {returncode}"


# Seconds to wait for a finished worker's output to be passed on.
PUMP_DRAIN_S = 60


def supervise(command: Sequence[str], config: DistributedConfig, *, cleanup=None,
              stderr=None) -> int:
    """Run ``command`` as a worker, minus the runtime's log noise; an abnormal end prints
    ``error: process I of N stopped: REASON`` and returns 2, after ``cleanup()``."""
    stderr = stderr or sys.stderr
    env = {**os.environ, WORKER_ENV: "1"}
    env.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")  # the runtime's info/warning lines
    child = subprocess.Popen(list(command), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             env=env)
    fatal: list[str] = []
    said: list[str] = []  # the worker's own error lines, passed on
    pumps = [threading.Thread(target=_pump, args=(child.stdout, sys.stdout, None), daemon=True),
             threading.Thread(target=_pump, args=(child.stderr, stderr, fatal, said),
                              daemon=True)]
    for pump in pumps:
        pump.start()
    code = _wait(child)  # the worker gets Ctrl-C's SIGINT too and ends itself
    for pump in pumps:  # its last lines (its one-line error) may still be in the pipes
        pump.join(timeout=PUMP_DRAIN_S)
    if code in (0, 130) or (code == 2 and said):
        return code
    if cleanup is not None:
        cleanup()
    who = f"process {config.process_id} of {config.num_processes}"
    stderr.write(f"error: {who} stopped: {fatal_reason(''.join(fatal), code, config)}\n")
    stderr.flush()
    return 2


def _wait(child: subprocess.Popen) -> int:
    while True:
        try:
            return child.wait()
        except KeyboardInterrupt:
            continue


def _pump(source, sink, fatal: list[str] | None, said: list[str] | None = None) -> None:
    """Copy a worker's stream to ``sink`` line by line (``\r`` ends a line) via :func:`_route`."""
    pending = b""
    while True:
        chunk = os.read(source.fileno(), 65536)
        if not chunk:
            break
        pending += chunk
        *lines, pending = re.split(rb"(?<=[\n\r])", pending)
        for raw in lines:
            _route(raw.decode("utf-8", "replace"), fatal, sink, said)
    if pending:
        _route(pending.decode("utf-8", "replace"), fatal, sink, said)


def _route(line: str, fatal: list[str] | None, stderr, said: list[str] | None = None) -> None:
    """Pass a worker's stderr ``line`` on, keep it as the fatal message, or drop it."""
    if said is not None and line.startswith("error: "):
        said.append(line)
        stderr.write(line)
        stderr.flush()
        return
    match = _FATAL.search(line) if fatal is not None else None
    if match or fatal:  # everything from a fatal log on is the dying runtime's
        if not is_runtime_noise(line) or match:
            fatal.append(line[match.end():] if match else line)
        if match and line[:match.start()].strip():
            stderr.write(line[:match.start()] + "\n")
        return
    if not is_runtime_noise(line):
        stderr.write(line)
        stderr.flush()


__all__ = ["AUTO", "DistributedConfig", "SplitEditor", "WORKER_ENV", "barrier", "check_agreement",
           "disagreement", "fatal_reason",
           "gather_views", "initialize", "is_runtime_noise", "is_writer", "parse_address",
           "process_count", "process_index", "process_slice", "split_edits", "supervise"]
