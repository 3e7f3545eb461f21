"""Producer/consumer of edited views: determinism, hand-over, shutdown, failures."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import threading
import time

import jax
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from jaxedit.edit.buffer import (AsyncEditSource, EditJob, EditorThreadError,
                                 PipelinedEditSource, SyncEditSource, Utilisation, make_source,
                                 view_order)


def _fake_edit(job: EditJob, scene) -> np.ndarray:
    # The "edit" encodes the job and the scene value so tests can check what was used.
    value = float(np.asarray(scene).reshape(-1)[0])
    return np.full((2, 2, 3), job.view + 0.001 * job.iteration + value, np.float32)


@settings(max_examples=25, deadline=None)
@given(n=st.integers(1, 7), every=st.integers(1, 5), sweep=st.booleans(), seed=st.integers(0, 99))
def test_sync_rule_is_a_pure_function_of_the_step(n, every, sweep, seed):
    order = view_order(n, jax.random.key(seed))
    assert sorted(order.tolist()) == list(range(n))
    src = SyncEditSource(_fake_edit, order, every=every, initial_sweep=sweep)
    jobs = [j for s in range(every * 3 * n + 1) for j in src.jobs_at(s)]
    # iterations are 0, 1, 2, ... without gaps; views cycle through `order`
    assert [j.iteration for j in jobs] == list(range(len(jobs)))
    assert [j.view for j in jobs] == [int(order[i % n]) for i in range(len(jobs))]
    # every view edited within the first sweep (n edits)
    assert {j.view for j in jobs[:n]} == set(range(n))
    # a second source (e.g. after resume) issues the same jobs at the same steps
    again = SyncEditSource(_fake_edit, order, every=every, initial_sweep=sweep)
    assert all(src.jobs_at(s) == again.jobs_at(s) for s in range(0, 4 * every))


def test_sync_exchange_edits_the_scene_of_that_step_and_counts():
    src = SyncEditSource(_fake_edit, np.array([2, 0, 1]), every=2)
    got = src.exchange(0, np.array([10.0]))
    assert [(e.job.view, e.scene_step) for e in got] == [(2, 0)]
    assert float(got[0].image[0, 0, 0]) == pytest.approx(12.0)
    assert src.exchange(1, np.array([0.0])) == []
    got = src.exchange(2, np.array([20.0]))
    assert float(got[0].image[0, 0, 0]) == pytest.approx(20.001)
    u = src.utilisation
    assert (u.edits, u.consumed, u.polls, u.empty_polls) == (2, 2, 3, 1)


def test_pipelined_edits_the_scene_of_the_exchange_and_hands_it_over_at_collect():
    started, release = threading.Event(), threading.Event()

    def slow_edit(job, scene):
        started.set()
        assert release.wait(10)
        return _fake_edit(job, scene)

    with PipelinedEditSource(slow_edit, np.array([2, 0, 1]), every=2) as src:
        assert src.collect() == []  # nothing begun yet
        assert src.exchange(0, np.array([10.0])) == []  # begun, not waited for
        assert started.wait(10)  # on the worker, while this thread goes on
        with pytest.raises(RuntimeError, match="collect"):
            src.exchange(2, np.array([20.0]))  # one edit in flight at a time
        release.set()
        got = src.collect()
        assert [(e.job.view, e.job.step, e.scene_step) for e in got] == [(2, 0, 0)]
        assert float(got[0].image[0, 0, 0]) == pytest.approx(12.0)  # the scene of step 0
        assert src.exchange(1, np.array([0.0])) == [] and src.collect() == []  # none due
        src.exchange(2, np.array([20.0]))
        got = src.collect()
        assert float(got[0].image[0, 0, 0]) == pytest.approx(20.001)
    u = src.utilisation
    assert (u.edits, u.consumed, u.polls) == (2, 2, 3)
    assert u.trainer_waits <= 2 and u.editor_seconds > 0


def test_edits_are_pipelined_where_editor_and_trainer_run_side_by_side():
    from types import SimpleNamespace

    from jaxedit.edit.buffer import side_by_side

    cpu, gpu0, gpu1 = (SimpleNamespace(platform=p, id=i) for i, p in
                       enumerate(("cpu", "gpu", "gpu")))
    assert side_by_side(cpu, None) and side_by_side(cpu, cpu)  # a CPU's cores
    assert side_by_side(gpu0, gpu1)  # the editor on a device of its own
    assert not side_by_side(gpu0, gpu0) and not side_by_side(gpu0, None)  # one shared GPU


def test_pipelined_makes_the_sync_rules_edits_and_the_sweep_at_once():
    order = np.array([1, 0, 2])
    kw = dict(every=3, initial_sweep=True)
    sync, piped = SyncEditSource(_fake_edit, order, **kw), PipelinedEditSource(_fake_edit, order, **kw)
    with piped:
        for s in range(0, 13):
            scene = np.array([float(s)])
            want = sync.exchange(s, scene)
            got = piped.exchange(s, scene)
            if s == 0:  # the sweep: every view, returned by the exchange itself
                assert len(got) == 3 and piped.collect() == []
            else:
                assert got == []
                got = piped.collect()
            assert [(e.job, e.scene_step) for e in got] == [(e.job, e.scene_step) for e in want]
            assert all(np.array_equal(a.image, b.image) for a, b in zip(got, want))
    with PipelinedEditSource(_fake_edit, np.array([0]), every=3, initial_sweep=True) as one:
        assert len(one.exchange(0, np.array([1.0]))) == 1  # a sweep of one view: at once too


def test_pipelined_editor_error_is_raised_at_collect():
    with PipelinedEditSource(_failing_edit, np.array([0, 1, 2]), every=1) as src:
        for step in (0, 1):
            src.exchange(step, np.array([0.0]))
            src.collect()
        src.exchange(2, np.array([0.0]))
        with pytest.raises(Boom):  # the editor's own error, in the trainer's thread
            src.collect()


def test_async_produces_from_latest_scene_and_shuts_down():
    order = np.array([0, 1, 2])
    with AsyncEditSource(_fake_edit, order, capacity=2) as src:
        got = []
        t0 = time.perf_counter()
        step = 0
        while len(got) < 7 and time.perf_counter() - t0 < 20:
            got += src.exchange(step, np.array([100.0 * step]))
            step += 1
            time.sleep(0.002)
        assert src.running
    assert not src.running
    assert len(got) >= 7
    assert [e.job.iteration for e in got] == list(range(len(got)))
    assert [e.job.view for e in got] == [i % 3 for i in range(len(got))]
    for e in got:  # each edit saw a scene the trainer had published at its step
        assert float(e.image[0, 0, 0]) == pytest.approx(e.job.view + 0.001 * e.job.iteration
                                                         + 100.0 * e.scene_step)
    u = src.utilisation
    assert u.edits >= u.consumed == len(got)
    assert u.polls == step and u.editor_seconds >= 0.0


def test_async_full_queue_and_never_polling_trainer_do_not_deadlock():
    src = AsyncEditSource(_fake_edit, np.array([0]), capacity=1).start()
    src.publish(np.array([1.0]), 0)
    deadline = time.perf_counter() + 10
    while src.utilisation.editor_waits == 0 and time.perf_counter() < deadline:
        time.sleep(0.01)
    assert src.utilisation.editor_waits >= 1  # blocked on the full queue
    t0 = time.perf_counter()
    src.close()
    assert not src.running and time.perf_counter() - t0 < 5


def test_async_editor_waits_for_first_scene_and_close_before_publish():
    src = AsyncEditSource(_fake_edit, np.array([0, 1])).start()
    time.sleep(0.1)
    assert src.poll() == []
    src.close()
    assert not src.running
    assert src.utilisation.editor_waits == 1 and src.utilisation.edits == 0


class Boom(RuntimeError):
    pass


def _failing_edit(job, scene):
    if job.iteration == 2:
        raise Boom("editor exploded")
    return _fake_edit(job, scene)


def test_editor_exception_surfaces_in_trainer_thread():
    with pytest.raises(EditorThreadError) as info:
        with AsyncEditSource(_failing_edit, np.array([0, 1, 2])) as src:
            for step in range(100000):
                src.exchange(step, np.array([0.0]))
                time.sleep(0.001)
    assert isinstance(info.value.__cause__, Boom)
    assert not src.running


def test_editor_exception_surfaces_at_close():
    src = AsyncEditSource(_failing_edit, np.array([0, 1, 2]), capacity=8).start()
    src.publish(np.array([0.0]), 0)
    deadline = time.perf_counter() + 10
    while src.running and time.perf_counter() < deadline:
        time.sleep(0.01)
    with pytest.raises(EditorThreadError):
        src.close()


def test_keyboard_interrupt_in_trainer_stops_editor_and_propagates():
    with pytest.raises(KeyboardInterrupt):
        with AsyncEditSource(_fake_edit, np.array([0, 1])) as src:
            src.publish(np.array([0.0]), 0)
            time.sleep(0.05)
            raise KeyboardInterrupt
    assert not src.running
    assert threading.active_count() < 50


def test_wait_for_counts_trainer_waits_and_feeds_arrivals():
    seen = []
    with AsyncEditSource(_fake_edit, np.array([0, 1, 2])) as src:
        src.publish(np.array([0.0]), 0)
        ok = src.wait_for(lambda: len({e.job.view for e in seen}) == 3, timeout=20,
                          on_edits=seen.extend)
    assert ok
    assert src.utilisation.trainer_waits >= 1 and src.utilisation.trainer_wait_s > 0


def test_utilisation_add_and_make_source():
    u = Utilisation(edits=1, editor_seconds=0.5).add(Utilisation(edits=2, trainer_waits=3))
    assert u.as_dict()["edits"] == 3 and u.trainer_waits == 3 and u.editor_seconds == 0.5
    assert type(make_source(_fake_edit, np.array([0]), asynchronous=False)) is SyncEditSource
    with make_source(_fake_edit, np.array([0]), asynchronous=False, pipelined=True) as src:
        assert isinstance(src, PipelinedEditSource)
    assert isinstance(make_source(_fake_edit, np.array([0]), asynchronous=True), AsyncEditSource)


def test_editor_runs_on_its_own_device_with_two_devices():
    code = textwrap.dedent("""
        import jax, jax.numpy as jnp, numpy as np, time
        from jaxedit.edit.buffer import AsyncEditSource, pick_devices
        trainer_dev, editor_dev = pick_devices()
        assert len(jax.devices()) == 2 and trainer_dev != editor_dev
        seen = []
        render = jax.jit(lambda s: s * 2.0)
        def edit_fn(job, scene):
            out = render(scene)
            seen.append((scene.devices(), out.devices()))
            return np.zeros((2, 2, 3), np.float32)
        scene = jax.device_put(jnp.ones(3), trainer_dev)
        got = []
        with AsyncEditSource(edit_fn, np.array([0, 1]), device=editor_dev) as src:
            t0 = time.time()
            while len(got) < 2 and time.time() - t0 < 60:
                got += src.exchange(0, scene)
                time.sleep(0.01)
        assert len(got) >= 2
        assert all(a == {editor_dev} and b == {editor_dev} for a, b in seen), seen
        print("OK", trainer_dev, editor_dev)
    """)
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2",
               JAX_PLATFORMS="cpu")
    res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "OK" in res.stdout
