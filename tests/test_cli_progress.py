"""experiments.progress: nested bars (rich), ETA, modes (bar / log / quiet / off), threads."""

from __future__ import annotations

import io
import re
import threading

import pytest

from experiments import progress as P


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


@pytest.fixture(autouse=True)
def _reset_settings():
    yield
    P.configure()


def test_nested_fraction_and_eta_in_log_mode():
    clock, out = Clock(), io.StringIO()
    with P.Progress(4, "edit", mode="log", stream=out, log_interval=5.0, clock=clock) as root:
        with root.child(10, "r0") as sub:
            clock.t += 2.0
            sub.update(1)  # the first step (compiling, say): the rates are measured from here
            assert sub.eta() is None and root.eta() is None
            clock.t += 4.0
            sub.update(4, loss=0.5)  # half of the first of 4 subtasks after 6 s, 4 s measured
            assert root.fraction == pytest.approx(0.125)
            assert root.eta() == pytest.approx(4.0 * 0.875 / 0.1)
            assert sub.eta() == pytest.approx(4.0 * 0.5 / 0.4)
            clock.t += 6.0
            sub.update(5)
        root.update(1)
        assert root.fraction == pytest.approx(0.25)
    text = out.getvalue()
    lines = text.splitlines()
    assert lines[0] == "start edit (4 steps)"
    # The periodic line shows the tree: parent then child with postfix.
    assert re.search(r"edit 0/4 \[#+-+\]\s+12% 0:06<0:35 \| r0 5/10 .* loss=0.5", text)
    assert "done r0 10/10 in 0:12 loss=0.5" in lines
    assert lines[-1] == "done edit 1/4 in 0:12"
    assert "\r" not in text  # log mode never uses carriage returns


def test_bar_mode_draws_nested_rich_bars_and_leaves_done_lines():
    clock, out = Clock(), io.StringIO()
    with P.Progress(2, "edit", mode="bar", stream=out, clock=clock) as root:
        display = root._display
        with root.child(100, "r0.500") as sub:
            clock.t += 2.0
            sub.update(51, psnr=31.234567)
            tasks = {t.description.strip(): t for t in display.rich.tasks}
            assert set(tasks) == {"edit", "r0.500"}
            assert tasks["r0.500"].description.startswith("  ")  # indented under its parent
            assert tasks["r0.500"].completed == pytest.approx(0.51)
            assert tasks["edit"].completed == pytest.approx(0.255)  # counts the child's share
            assert tasks["r0.500"].fields["postfix"] == "psnr=31.23"
            assert tasks["r0.500"].fields["count"] == "51/100"
        assert [t.description for t in display.rich.tasks] == ["edit"]  # the child's bar went
        root.update(1)
    text = out.getvalue()
    assert "done r0.500 51/100 in 0:02 psnr=31.23" in text
    assert "done edit 1/2 in 0:02" in text


def test_quiet_logs_rarely_and_off_is_silent():
    out = io.StringIO()
    P.configure(quiet=True, stream=out)
    clock = Clock()
    with P.Progress(3, "x", clock=clock) as bar:
        for _ in range(3):
            clock.t += 15.0  # 45 s in all: under the quiet 60 s interval
            bar.update(1)
    assert out.getvalue().splitlines() == ["start x (3 steps)", "done x 3/3 in 0:45"]
    P.configure(mode="off", stream=out)
    with P.Progress(3, "silent") as bar:
        bar.update(3)
    assert "silent" not in out.getvalue()


def test_ambient_nesting_unknown_total_and_errors():
    clock, out = Clock(), io.StringIO()
    with P.Progress(2, "demo", mode="log", stream=out, log_interval=1e9, clock=clock) as demo:
        with P.nested(demo):
            inner = P.Progress(None, "stage")  # created by a command that knows nothing of demo
            assert inner.parent is demo and inner.mode == "log"
            clock.t += 4.0
            inner.update(8)
            assert "stage 8 [0:04, ?/s]" in demo.line()  # one advance: no rate yet
            clock.t += 4.0
            inner.update(8)
            assert "stage 16 [0:08, 2/s]" in demo.line()
            clock.t += 28.0
            assert "stage 16 [0:36, 4s/it]" in demo.line()  # slow work reads as s/it
            inner.close()
        assert P.Progress(1, "after", mode="off").parent is None
    assert P.format_seconds(3725) == "1:02:05" and P.format_seconds(None) == "?"
    with pytest.raises(ValueError):
        P.Progress(-1)
    with pytest.raises(ValueError):
        P.configure(mode="fancy")


def test_threaded_updates_are_counted_exactly():
    out = io.StringIO()
    bar = P.Progress(4000, "threads", mode="bar", stream=out)
    workers = [threading.Thread(target=lambda: [bar.update(1) for _ in range(1000)])
               for _ in range(4)]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    bar.close()
    assert bar.n == 4000 and "threads 4000/4000" in out.getvalue()


def test_track_wraps_iterables():
    out = io.StringIO()
    P.configure(mode="log", stream=out)
    assert [x * 2 for x in P.track(range(3), desc="items")] == [0, 2, 4]
    assert "done items 3/3" in out.getvalue()


def test_weighted_units_give_a_fair_fraction():
    clock = Clock()
    with P.Progress(3, "stages", mode="off", clock=clock, weights=[1, 3, 6]) as bar:
        bar.update(1)
        assert bar.fraction == pytest.approx(0.1)
        with bar.child(4, "long") as sub:
            sub.update(2)
            assert bar.fraction == pytest.approx(0.1 + 0.3 * 0.5)
        bar.update(2)
        assert bar.fraction == 1.0
    with pytest.raises(ValueError, match="weights"):
        P.Progress(2, weights=[1.0])


# ---------------------------------------------------------------- issue 36: honest ETAs


def test_eta_and_rate_are_measured_after_the_first_advance():
    """The first unit's time (compilation) and work reported at once do not make the rate."""
    clock = Clock()
    with P.Progress(10, "steps", mode="off", clock=clock) as bar:
        clock.t += 100.0  # the first step compiles
        bar.update(1)
        assert bar.eta() is None and "<?" in bar.segment()  # not 100 s * 9
        clock.t += 0.1
        bar.update(1)
        assert bar.eta() is None  # under MIN_SPAN: no rate from two updates close together
        clock.t += 1.9
        bar.update(2)  # 3 steps in 2 s since the first
        assert bar.eta() == pytest.approx(6 * 2.0 / 3)
        assert "0:04" in bar.segment()
    with P.Progress(None, "edit", mode="off", clock=clock) as edit:
        clock.t += 140.0
        sub = edit.child(None, "s1")
        sub.update(16)  # a subtask's bar opens with the steps its first chunk ran
        assert "?/s" in sub.segment() and "e+" not in sub.segment()
        clock.t += 8.0
        sub.update(16)
        assert "s1 32 [0:08, 2/s]" in sub.segment()


def test_training_bar_starts_a_resumed_run_at_its_step_untimed():
    from collections import namedtuple

    Event = namedtuple("Event", "desc step total loss psnr gaussians")
    clock, out = Clock(), io.StringIO()
    with P.Progress(1, "run", mode="log", stream=out, log_interval=1e9, clock=clock) as root, \
            P.nested(root):
        on_event = P.training_bar()
        on_event(Event("reconstruct", 500, 1000, float("nan"), float("nan"), 10))
        bar = root._child
        assert bar.n == 500 and bar.eta() is None and root.eta() is None
        clock.t += 30.0  # the first chunk after the resume compiles
        on_event(Event("reconstruct", 516, 1000, 0.1, 20.0, 10))
        assert bar.eta() is None
        clock.t += 2.0
        on_event(Event("reconstruct", 532, 1000, 0.1, 20.0, 10))
        assert bar.eta() == pytest.approx(468 * 2.0 / 16)
        on_event.close()


def test_bar_mode_shows_the_measured_eta():
    clock, out = Clock(), io.StringIO()
    with P.Progress(10, "steps", mode="bar", stream=out, clock=clock) as bar:
        (task,) = bar._display.rich.tasks
        clock.t += 50.0
        bar.update(1)
        assert task.fields["eta"] == "?"
        clock.t += 1.0
        bar.update(1)
        assert task.fields["eta"] == "0:08"
