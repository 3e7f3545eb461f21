"""Edit sources: how the 2D editor's edited views reach the 3D trainer (ProEdit 3.3)."""

from __future__ import annotations

import concurrent.futures
import dataclasses
import queue
import threading
import time
from typing import Any, Callable, Protocol

import jax
import jax.numpy as jnp
import numpy as np


@dataclasses.dataclass(frozen=True)
class EditJob:
    """One edit to perform.

    Attributes:
      view: index of the training view (position in the training set).
      iteration: edits this subtask issued before this one (seeds the editor).
      step: trainer step (within the subtask) at which the job was issued.
      timestep: fixed SDEdit timestep; None: the subtask's annealing of ``step``.
    """

    view: int
    iteration: int
    step: int
    timestep: float | None = None


@dataclasses.dataclass(frozen=True)
class EditedView:
    """An edit result: ``image`` float32 [H, W, 3] in [0, 1] (NumPy, or JAX on the
    trainer's device), ``seconds`` of editor time, ``scene_step`` the scene's trainer step."""

    job: EditJob
    image: np.ndarray | jax.Array
    seconds: float
    scene_step: int  # trainer step of the scene the editor rendered


@dataclasses.dataclass
class Utilisation:
    """Counters and wall-clock seconds of edits made/consumed and of who waited for whom."""

    edits: int = 0
    consumed: int = 0
    editor_seconds: float = 0.0
    trainer_waits: int = 0
    trainer_wait_s: float = 0.0
    editor_waits: int = 0
    editor_wait_s: float = 0.0
    polls: int = 0
    empty_polls: int = 0

    def add(self, other: "Utilisation") -> "Utilisation":
        return Utilisation(**{f.name: getattr(self, f.name) + getattr(other, f.name)
                              for f in dataclasses.fields(self)})

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


EditFn = Callable[[EditJob, Any], Any]
#: ``(jobs, scene) -> edited views``: the jobs due at one step, edited together.
EditManyFn = Callable[[list[EditJob], Any], list]


def as_view(image, device: jax.Device | None = None):
    """A finished float32 [H, W, 3] JAX array on ``device`` (None: where it is), or NumPy."""
    if isinstance(image, jax.Array):
        image = image.astype(jnp.float32)
        if device is not None:
            image = jax.device_put(image, device)
        return image.block_until_ready()  # the editor's time is the time of a finished edit
    return np.asarray(image, np.float32)


def view_order(num_views: int, key: jax.Array) -> np.ndarray:
    """int [num_views], the seeded cyclic order in which views are edited."""
    if num_views <= 0:
        raise ValueError("need at least one training view to edit")
    return np.asarray(jax.random.permutation(key, num_views))


def pick_devices() -> tuple[jax.Device, jax.Device]:
    """(trainer device, editor device), distinct when there are two local devices."""
    devices = jax.local_devices()
    return devices[0], devices[1] if len(devices) > 1 else devices[0]


def side_by_side(trainer_device: jax.Device, editor_device: jax.Device | None) -> bool:
    """Whether editor and trainer run concurrently (CPU, or two distinct devices); on one
    shared accelerator pipelining would only hold both programs' buffers at once."""
    return trainer_device.platform == "cpu" or (
        editor_device is not None and editor_device != trainer_device)


class EditSource(Protocol):
    """What a subtask's loop asks of its edits (a context manager; steps count from the
    end of warm-up).

    Attributes:
      can_wait: whether waiting brings edits (a producer thread).
      utilisation: who waited for whom (:class:`Utilisation`).
    """

    can_wait: bool
    utilisation: Utilisation

    def due(self, step: int) -> bool:
        """Whether the trainer exchanges with the editor at ``step``."""

    def next_due(self, step: int) -> int | None:
        """The first step after ``step`` with an exchange (None: none left)."""

    def exchange(self, step: int, scene) -> list[EditedView]:
        """Hand over the trainer's ``scene`` at ``step``; the edits ready for it."""

    def collect(self) -> list[EditedView]:
        """Edits begun at the last exchange and due now ([] if handed over inside it)."""

    def wait_for(self, predicate: Callable[[], bool], timeout: float | None = None,
                 on_edits: Callable[[list[EditedView]], None] | None = None) -> bool:
        """Block until ``predicate()`` holds, feeding arrivals to ``on_edits``; its value."""

    def __enter__(self): ...

    def __exit__(self, *exc): ...


class SyncEditSource:
    """Deterministic inline edits: at step ``s % every == 0``, view ``order[(s // every) % N]``.

    Args:
      edit_fn: ``(job, scene) -> image float32 [H, W, 3]``.
      order: int [N], cyclic view order (:func:`view_order`).
      every: trainer steps between edits.
      initial_sweep: step 0 edits every view once.
      trainer_device: where JAX results go (None: left where the editor made them).
      edit_many: ``(jobs, scene) -> images`` for several edits due at one step.
    """

    can_wait = False

    def __init__(self, edit_fn: EditFn, order: np.ndarray, *, every: int = 10,
                 initial_sweep: bool = False, trainer_device: jax.Device | None = None,
                 edit_many: EditManyFn | None = None):
        if every < 1:
            raise ValueError(f"every must be >= 1, got {every}")
        self.edit_fn = edit_fn
        self.edit_many = edit_many
        self.order = np.asarray(order)
        self.every = int(every)
        self.initial_sweep = initial_sweep
        self.trainer_device = trainer_device
        self.utilisation = Utilisation()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def jobs_at(self, step: int) -> list[EditJob]:
        """The edits due at ``step``; with the initial sweep, step 0 issues edits 0..N-1."""
        n = len(self.order)
        if step < 0 or step % self.every:
            return []
        k = step // self.every
        if not self.initial_sweep:
            return [EditJob(int(self.order[k % n]), k, step)]
        if k == 0:
            return [EditJob(int(v), i, 0) for i, v in enumerate(self.order)]
        i = n + k - 1
        return [EditJob(int(self.order[i % n]), i, step)]

    def due(self, step: int) -> bool:
        """Whether edits are due at ``step``."""
        return step >= 0 and step % self.every == 0

    def next_due(self, step: int) -> int | None:
        """The first step after ``step`` with edits due (None: none left)."""
        return (max(step, -1) // self.every + 1) * self.every

    def exchange(self, step: int, scene) -> list[EditedView]:
        """Perform the edits due at ``step`` on ``scene`` and return them."""
        out = self._edit(self.jobs_at(step), scene, step)
        for view in out:
            self._count(view, waited=view.seconds)
        self.utilisation.polls += 1
        self.utilisation.empty_polls += not out
        return out

    def collect(self) -> list[EditedView]:
        """[]: every edit is made inside :meth:`exchange`."""
        return []

    def _edit(self, jobs: list[EditJob], scene, step: int) -> list[EditedView]:
        """``jobs`` edited on ``scene`` (one ``edit_many`` call when given), finished."""
        together = self.edit_many is not None and len(jobs) > 1
        groups = [jobs] if together else [[job] for job in jobs]
        out = []
        for group in groups:
            t0 = time.perf_counter()
            images = (self.edit_many(group, scene) if together
                      else [self.edit_fn(group[0], scene)])
            images = [as_view(image, self.trainer_device) for image in images]
            dt = (time.perf_counter() - t0) / len(group)
            out.extend(EditedView(job, image, dt, step) for job, image in zip(group, images))
        return out

    def _count(self, view: EditedView, waited: float) -> None:
        u = self.utilisation
        u.edits += 1
        u.consumed += 1
        u.editor_seconds += view.seconds
        u.trainer_waits += waited > 0
        u.trainer_wait_s += waited

    def wait_for(self, predicate: Callable[[], bool], timeout: float | None = None,
                 on_edits: Callable[[list[EditedView]], None] | None = None) -> bool:
        """Sync edits arrive only through :meth:`exchange`; waiting cannot help."""
        return predicate()

    def close(self) -> None:
        pass


class PipelinedEditSource(SyncEditSource):
    """:class:`SyncEditSource`'s edits, made on a worker thread while the trainer trains
    to its next stop, where :meth:`collect` hands them over. Hand-over steps follow the
    rule, not timing, so runs stay bit-reproducible."""

    def __init__(self, edit_fn: EditFn, order: np.ndarray, **kwargs):
        super().__init__(edit_fn, order, **kwargs)
        self._worker = concurrent.futures.ThreadPoolExecutor(
            max_workers=1, thread_name_prefix="jaxedit-editor")
        self._pending: concurrent.futures.Future | None = None

    def exchange(self, step: int, scene) -> list[EditedView]:
        """Begin the edit due at ``step``; the initial sweep is made at once and returned."""
        if self._pending is not None:
            raise RuntimeError("collect() the edit begun at the last exchange first")
        jobs = self.jobs_at(step)
        if not jobs or (self.initial_sweep and step == 0):
            return super().exchange(step, scene)
        self.utilisation.polls += 1
        self._pending = self._worker.submit(self._edit, jobs, scene, step)
        return []

    def collect(self) -> list[EditedView]:
        """The edit begun at the last exchange, once finished; re-raises the editor's error."""
        if self._pending is None:
            return []
        pending, self._pending = self._pending, None
        t0 = time.perf_counter()
        finished = pending.done()
        out = pending.result()
        waited = 0.0 if finished else time.perf_counter() - t0
        for view in out:
            self._count(view, waited=waited)
        return out

    def close(self) -> None:
        """Wait for an edit in flight (at most one) and stop the worker."""
        self._pending = None
        self._worker.shutdown(wait=True, cancel_futures=True)


class SweepEditSource(SyncEditSource):
    """Every ``every`` steps (step 0 included), every view in ``order``."""

    def __init__(self, edit_fn: EditFn, order: np.ndarray, *, every: int,
                 trainer_device=None, edit_many: EditManyFn | None = None):
        super().__init__(edit_fn, order, every=every, initial_sweep=False,
                         trainer_device=trainer_device, edit_many=edit_many)

    def jobs_at(self, step: int) -> list[EditJob]:
        if step < 0 or step % self.every:
            return []
        n, first = len(self.order), (step // self.every) * len(self.order)
        return [EditJob(int(self.order[i % n]), i, step) for i in range(first, first + n)]


class EditorThreadError(RuntimeError):
    """The editor thread failed; the original exception is the ``__cause__``."""


class AsyncEditSource:
    """Edits made on a background thread from the newest scene (timing-dependent: not
    bit-reproducible); use as a context manager so the thread is always joined.

    Args:
      edit_fn: ``(job, scene) -> image``, given the latest published scene.
      order: int [N], cyclic view order.
      device: editor device (None: leave arrays where they are).
      trainer_device: where JAX results go (None: left on the editor's device).
      capacity: hand-over queue size; the editor waits when it is full.
      poll_interval: seconds between checks of the stop flag while waiting.
    """

    can_wait = True

    def __init__(self, edit_fn: EditFn, order: np.ndarray, *, device: jax.Device | None = None,
                 capacity: int = 4, poll_interval: float = 0.02,
                 trainer_device: jax.Device | None = None):
        self.edit_fn = edit_fn
        self.order = np.asarray(order)
        self.device = device
        self.trainer_device = trainer_device
        self.poll_interval = poll_interval
        self.utilisation = Utilisation()
        self._queue: queue.Queue[EditedView] = queue.Queue(maxsize=max(1, capacity))
        self._lock = threading.Lock()
        self._scene = None  # (scene, step)
        self._scene_ready = threading.Event()
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="jaxedit-editor", daemon=True)
        self._started = False

    def start(self) -> "AsyncEditSource":
        if not self._started:
            self._started = True
            self._thread.start()
        return self

    def __enter__(self):
        return self.start()

    def __exit__(self, exc_type, exc, tb):
        self.close(raise_error=exc_type is None)
        return False

    def close(self, raise_error: bool = True, timeout: float = 60.0) -> None:
        """Stop the editor thread and join it; re-raise its failure if any."""
        self._stop.set()
        self._scene_ready.set()
        if self._started and self._thread.is_alive():
            t0 = time.perf_counter()
            while self._thread.is_alive() and time.perf_counter() - t0 < timeout:
                self._drain_nowait()
                self._thread.join(self.poll_interval)
            waited = time.perf_counter() - t0
            self.utilisation.trainer_waits += 1
            self.utilisation.trainer_wait_s += waited
            if self._thread.is_alive():
                raise EditorThreadError(f"editor thread did not stop within {timeout:.0f} s")
        if raise_error:
            self._raise_if_failed()

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def publish(self, scene, step: int) -> None:
        """Make ``scene`` (a pytree of arrays, immutable) the one the editor renders next."""
        with self._lock:
            self._scene = (scene, step)
        self._scene_ready.set()

    def poll(self) -> list[EditedView]:
        """Every edit produced since the last poll (never blocks)."""
        self._raise_if_failed()
        out = self._drain_nowait()
        self.utilisation.polls += 1
        self.utilisation.empty_polls += not out
        self.utilisation.consumed += len(out)
        return out

    def due(self, step: int) -> bool:
        """Every step, so the editor always works from a fresh render."""
        return step >= 0

    def next_due(self, step: int) -> int:
        return step + 1

    def exchange(self, step: int, scene) -> list[EditedView]:
        """Publish the trainer's scene at ``step`` and collect finished edits."""
        self.publish(scene, step)
        return self.poll()

    def collect(self) -> list[EditedView]:
        """Nothing: the thread's edits are taken at the exchanges (every step)."""
        return []

    def wait_for(self, predicate: Callable[[], bool], timeout: float | None = None,
                 on_edits: Callable[[list[EditedView]], None] | None = None) -> bool:
        """Block until ``predicate()`` holds, feeding arrivals to ``on_edits``; its final
        value (False on timeout)."""
        if predicate():
            return True
        t0 = time.perf_counter()
        self.utilisation.trainer_waits += 1
        try:
            while not predicate():
                self._raise_if_failed()
                if not self._thread.is_alive():
                    break
                if timeout is not None and time.perf_counter() - t0 > timeout:
                    break
                try:
                    first = self._queue.get(timeout=self.poll_interval)
                except queue.Empty:
                    continue
                got = [first] + self._drain_nowait()
                self.utilisation.consumed += len(got)
                if on_edits is not None:
                    on_edits(got)
            self._raise_if_failed()
            return predicate()
        finally:
            self.utilisation.trainer_wait_s += time.perf_counter() - t0

    def _drain_nowait(self) -> list[EditedView]:
        out = []
        while True:
            try:
                out.append(self._queue.get_nowait())
            except queue.Empty:
                return out

    def _raise_if_failed(self) -> None:
        if self._error is not None:
            raise EditorThreadError(f"the editor failed: {self._error!r}") from self._error

    def _latest_scene(self):
        waited = 0.0
        if not self._scene_ready.is_set():
            t0 = time.perf_counter()
            while not self._scene_ready.wait(self.poll_interval):
                if self._stop.is_set():
                    break
            waited = time.perf_counter() - t0
            self.utilisation.editor_waits += 1
            self.utilisation.editor_wait_s += waited
        with self._lock:
            return self._scene

    def _put(self, item: EditedView) -> bool:
        t0 = None
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=self.poll_interval)
                break
            except queue.Full:
                if t0 is None:
                    t0 = time.perf_counter()
                    self.utilisation.editor_waits += 1
        if t0 is not None:
            self.utilisation.editor_wait_s += time.perf_counter() - t0
        return not self._stop.is_set()

    def _run(self) -> None:
        n = len(self.order)
        i = 0
        try:
            while not self._stop.is_set():
                latest = self._latest_scene()
                if latest is None or self._stop.is_set():
                    break
                scene, scene_step = latest
                if self.device is not None:
                    scene = jax.device_put(scene, self.device)
                job = EditJob(int(self.order[i % n]), i, scene_step)
                t0 = time.perf_counter()
                image = as_view(self.edit_fn(job, scene), self.trainer_device)
                dt = time.perf_counter() - t0
                self.utilisation.edits += 1
                self.utilisation.editor_seconds += dt
                if not self._put(EditedView(job, image, dt, scene_step)):
                    break
                i += 1
        except BaseException as e:  # surfaces in the trainer's thread
            self._error = e


def make_source(edit_fn: EditFn, order: np.ndarray, *, asynchronous: bool, every: int = 10,
                initial_sweep: bool = False, device=None, capacity: int = 4,
                trainer_device=None, edit_many: EditManyFn | None = None,
                pipelined: bool = False, sweep_every: int | None = None):
    """The edit source for a subtask.

    Args:
      asynchronous: :class:`AsyncEditSource` (one view at a time, from the newest scene).
      pipelined: :class:`PipelinedEditSource` instead of :class:`SyncEditSource`.
      sweep_every: every view every that many steps (:class:`SweepEditSource`).

    Raises:
      ValueError: ``sweep_every`` with ``asynchronous``.
    """
    if sweep_every is not None:
        if asynchronous:
            raise ValueError("sweeps are deterministic: not asynchronous")
        return SweepEditSource(edit_fn, order, every=sweep_every,
                               trainer_device=trainer_device, edit_many=edit_many)
    if asynchronous:
        return AsyncEditSource(edit_fn, order, device=device, capacity=capacity,
                               trainer_device=trainer_device)
    kind = PipelinedEditSource if pipelined else SyncEditSource
    return kind(edit_fn, order, every=every, initial_sweep=initial_sweep,
                trainer_device=trainer_device, edit_many=edit_many)
