"""Properties of the subtask scheduler (bisection + pruning, root placement, uniform)."""

import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from jaxedit.edit.schedule import (Schedule, decompose, decompose_root, for_target_subtasks,
                                   prune_ratios, spread, uniform)
from jaxedit.errors import DataError

KNOTS = 16


def monotone_difficulty(increments):
    """d(a, b) = |F(b) - F(a)| for the piecewise-linear increasing F with these increments."""
    inc = np.asarray(increments, np.float64) + 1e-3
    knots = np.concatenate([[0.0], np.cumsum(inc)]) / np.sum(inc)  # F(1) = 1
    xs = np.linspace(0.0, 1.0, len(knots))

    def d(a, b):
        return float(abs(np.interp(b, xs, knots) - np.interp(a, xs, knots)))

    return d


def noisy(d, amplitude):
    """Non-monotone, deterministic noise on top of d, still d(r, r) = 0 and symmetric."""

    def nd(a, b):
        if a == b:
            return 0.0
        lo, hi = min(a, b), max(a, b)
        return d(a, b) + amplitude * abs(math.sin(997.0 * lo + 131.0 * hi))

    return nd


def check_schedule(s: Schedule, d, threshold, start=0.0):
    r = s.ratios
    assert r[0] == start and r[-1] == 1.0
    assert all(b > a for a, b in zip(r, r[1:]))
    assert len(s.difficulties) == len(r) - 1
    for (a, b), da in zip(zip(r, r[1:]), s.difficulties):
        assert da == pytest.approx(d(a, b), abs=1e-12)
    if not s.depth_limit_hit:
        assert all(x <= threshold for x in s.difficulties)
    else:
        assert any(x > threshold for x in s.difficulties)


def assert_nothing_removable(s: Schedule, d, threshold):
    r = s.ratios
    for i in range(1, len(r) - 1):
        assert d(r[i - 1], r[i + 1]) > threshold, f"r_{i} = {r[i]} is removable"


increments = st.lists(st.floats(0.0, 1.0), min_size=KNOTS, max_size=KNOTS)


@settings(max_examples=60, deadline=None)
@given(increments, st.floats(0.02, 0.8), st.integers(2, 8), st.floats(0.0, 0.05))
def test_bisection_properties(inc, threshold, max_depth, noise):
    d = noisy(monotone_difficulty(inc), noise)
    asked_full, asked_pruned = set(), set()
    full = decompose(recording(d, asked_full), threshold=threshold, max_depth=max_depth,
                     prune=False)
    check_schedule(full, d, threshold)
    # unpruned: every interval is dyadic, and only intervals at the depth limit may exceed
    for (a, b), x in zip(zip(full.ratios, full.ratios[1:]), full.difficulties):
        if x > threshold:
            assert b - a == pytest.approx(2.0 ** -max_depth)
    pruned = decompose(recording(d, asked_pruned), threshold=threshold, max_depth=max_depth)
    check_schedule(pruned, d, threshold)
    assert set(pruned.ratios) <= set(full.ratios)
    assert pruned.depth_limit_hit == full.depth_limit_hit
    assert_nothing_removable(pruned, d, threshold)
    assert decompose(d, threshold=threshold, max_depth=max_depth) == pruned  # deterministic
    # evaluations counts exactly the distinct pairs the difficulty was asked for; pruning
    # asks for the bisection's pairs and then its own checks
    assert full.evaluations == len(asked_full) and pruned.evaluations == len(asked_pruned)
    assert asked_full <= asked_pruned


def recording(difficulty, asked: set):
    """``difficulty`` that adds every pair (r_a, r_b) it is asked for to ``asked``."""
    def d(a, b):
        asked.add((float(a), float(b)))
        return difficulty(a, b)
    return d


def test_bisection_linear_is_exact():
    d = lambda a, b: abs(b - a)  # noqa: E731
    s = decompose(d, threshold=0.25)
    assert s.ratios == (0.0, 0.25, 0.5, 0.75, 1.0) and not s.depth_limit_hit
    # 7 bisection intervals; of the 3 pruning checks only d(0.25, 0.75) is new
    assert s.evaluations == 7 + 1
    assert decompose(d, threshold=2.0).ratios == (0.0, 1.0)


def test_step_difficulty_reports_depth_limit():
    d = lambda a, b: abs(float(b > 0.3) - float(a > 0.3)) + 0.1 * abs(b - a)  # noqa: E731
    s = decompose(d, threshold=0.5, max_depth=5)
    assert s.depth_limit_hit
    bad = [(a, b) for (a, b), x in zip(zip(s.ratios, s.ratios[1:]), s.difficulties) if x > 0.5]
    assert len(bad) == 1 and bad[0][0] < 0.3 < bad[0][1] and bad[0][1] - bad[0][0] == 2 ** -5


def test_prune_removes_smallest_merge_first_and_everything_removable():
    # both interior ratios are removable on their own but not together: the greedy order
    # removes the one with the smaller merged difficulty, d(0, 2/3) = 0.25 < d(1/3, 1) = 0.3
    values = {0.0: 0.0, 1 / 3: 0.1, 2 / 3: 0.25, 1.0: 0.4}
    d = lambda a, b: abs(values[b] - values[a])  # noqa: E731
    s = prune_ratios([0.0, 1 / 3, 2 / 3, 1.0], d, threshold=0.3)
    assert s.ratios == (0.0, 2 / 3, 1.0)
    assert s.difficulties == pytest.approx((0.25, 0.15))
    assert_nothing_removable(s, d, 0.3)
    assert s.depth_limit_hit is False
    # a jump that no pruning can hide stays, and is reported
    F = lambda r: 0.1 * r + (0.8 if r > 0.5 else 0.0)  # noqa: E731
    d2 = lambda a, b: abs(F(b) - F(a))  # noqa: E731
    s2 = prune_ratios([0.0, 0.25, 0.5, 0.75, 1.0], d2, threshold=0.3)
    assert s2.ratios == (0.0, 0.5, 0.75, 1.0) and s2.depth_limit_hit
    assert_nothing_removable(s2, d2, 0.3)


root_increments = st.lists(st.floats(0.05, 1.0), min_size=KNOTS, max_size=KNOTS)


@settings(max_examples=25, deadline=None)
@given(root_increments, st.floats(0.08, 0.6))
def test_root_placement_properties(inc, threshold):
    d = monotone_difficulty(inc)
    res = 2.0 ** -8
    s = decompose_root(d, threshold=threshold, resolution=res, balance=0, prune=False)
    check_schedule(s, d, threshold)
    assert not s.depth_limit_hit
    for a, b in zip(s.ratios, s.ratios[1:-1]):
        # greedy maximality on the grid: one grid step further is over the threshold
        assert d(a, min(b + res, 1.0)) > threshold
        assert abs(b / res - round(b / res)) < 1e-9  # on the grid
    # the greedy cover is never longer than the paper's decomposition at the same resolution
    assert s.num_subtasks <= decompose(d, threshold=threshold, max_depth=8).num_subtasks
    assert decompose_root(d, threshold=threshold, resolution=res, balance=0, prune=False) == s
    # balancing keeps the count, never raises the largest difficulty, narrows the spread
    asked = set()
    balanced = decompose_root(recording(d, asked), threshold=threshold, resolution=res)
    check_schedule(balanced, d, threshold)
    assert_nothing_removable(balanced, d, threshold)
    assert balanced.num_subtasks == s.num_subtasks
    assert max(balanced.difficulties) <= max(s.difficulties)
    assert min(balanced.difficulties) >= min(s.difficulties) - 1e-12
    assert balanced.evaluations == len(asked)


def test_root_placement_step_and_noise():
    step = lambda a, b: abs(float(b > 0.3) - float(a > 0.3)) + 0.1 * abs(b - a)  # noqa: E731
    s = decompose_root(step, threshold=0.5, resolution=1 / 64)
    check_schedule(s, step, 0.5)
    assert s.depth_limit_hit and s.method == "root"
    d = noisy(monotone_difficulty(np.linspace(0.2, 1.0, KNOTS)), 0.03)
    s = decompose_root(d, threshold=0.2)
    check_schedule(s, d, 0.2)
    assert_nothing_removable(s, d, 0.2)
    assert spread(s)["max"] <= 0.2


def test_uniform_and_validation():
    u = uniform(4)
    assert u.ratios == (0.0, 0.25, 0.5, 0.75, 1.0) and all(math.isnan(x) for x in u.difficulties)
    assert Schedule.from_dict(u.to_dict()).ratios == u.ratios
    assert u.to_dict()["difficulties"] == [None] * 4
    m = uniform(3, lambda a, b: (b - a) ** 2)
    assert m.difficulties == pytest.approx((1 / 9,) * 3) and m.evaluations == 3
    assert Schedule.from_dict(m.to_dict()) == m
    for bad in (0, -1, 2.5):
        with pytest.raises(DataError, match="subtasks"):
            uniform(bad)
    with pytest.raises(DataError, match="threshold"):
        decompose(lambda a, b: 0.0, threshold=0.0)
    with pytest.raises(DataError, match="increasing"):
        Schedule((0.0, 0.5, 0.5, 1.0), (0.1, 0.0, 0.1))
    with pytest.raises(DataError, match="end at 1"):
        Schedule((0.0, 0.9), (0.1,))
    with pytest.raises(DataError, match="start"):
        uniform(2, start=1.0)
    with pytest.raises(DataError, match="difficulty"):
        decompose(lambda a, b: float("nan"), threshold=0.1)


def test_root_placement_surfaces_difficulty_errors():
    def d(a, b):
        if max(a, b) > 0.6 and max(a, b) < 1.0:
            raise DataError("editor", "boom")
        return abs(b - a)

    with pytest.raises(DataError, match="boom"):
        decompose_root(d, threshold=0.3)


def test_continue_from_a_snapshot_ratio():
    d = monotone_difficulty(np.linspace(0.1, 1.0, KNOTS))
    for s in (decompose(d, threshold=0.15, start=0.3),
              decompose_root(d, threshold=0.15, start=0.3), uniform(3, d, start=0.3)):
        assert s.ratios[0] == 0.3 and s.ratios[-1] == 1.0
        check_schedule(s, d, 0.15 if s.method != "uniform" else 10.0, start=0.3)
    assert uniform(2, start=0.5).ratios == (0.5, 0.75, 1.0)


# --------------------------------------------------------------------------- target subtasks
@settings(max_examples=8, deadline=None, derandomize=True)
@given(inc=increments, target=st.integers(1, 12))
def test_target_subtasks_finds_a_threshold_within_one_subtask(inc, target):
    d = monotone_difficulty(inc)
    s = for_target_subtasks(d, target, max_depth=5)
    assert s.target_subtasks == target and s.method == "bisection"
    assert abs(s.num_subtasks - target) <= 1
    check_schedule(s, d, s.threshold)
    # It is an ordinary decomposition at the threshold it reports.
    assert decompose(d, threshold=s.threshold, max_depth=5).ratios == s.ratios


@pytest.mark.parametrize("target", [2, 4, 7])
def test_target_subtasks_edits_no_ratio_finer_than_its_answer_needs(target):
    # An oracle's cost is one edit per distinct ratio: the search must not probe the finest
    # grid first, only ratios a decomposition half an octave below its answer would probe.
    def ratios_probed(fn):
        seen = set()

        def d(a, b):
            seen.update((a, b))
            return base(a, b)
        return fn(d), seen

    base = monotone_difficulty(np.linspace(0.2, 1.0, KNOTS))
    s, searched = ratios_probed(lambda d: for_target_subtasks(d, target, max_depth=6))
    _, finer = ratios_probed(lambda d: decompose(d, threshold=s.threshold / 2 ** 0.5, max_depth=6))
    assert abs(s.num_subtasks - target) <= 1
    assert searched <= finer, sorted(searched - finer)
    assert len(searched) < 2 ** 6 + 1



@pytest.mark.parametrize("target", [2, 4, 8])
def test_an_exact_target_probes_only_its_own_schedule_at_its_tightest_threshold(target):
    """A threshold of the search that gives exactly ``target`` subtasks ends it: no ratio
    beyond what the answer's decomposition probes (here d(0, 1) / target gives them at
    once), and the lowest threshold of the search's grid that still gives those steps."""
    base = lambda a, b: abs(b - a) ** 1.05  # noqa: E731  (2^k equal steps, each under 2^-k)
    searched, own = set(), set()
    s = for_target_subtasks(recording(base, searched), target, max_depth=6)
    assert s.num_subtasks == target
    decompose(recording(base, own), threshold=s.threshold, max_depth=6)
    assert {r for pair in searched for r in pair} == {r for pair in own for r in pair} == {
        i / target for i in range(target + 1)}
    step = 2.0 ** -12  # the search's grid of y, threshold d(0, 1) 2^(-24 (1 - y))
    y = 1.0 + math.log2(s.threshold / (1.0 + 1e-9)) / 24.0
    below = 2.0 ** (-24.0 * (1.0 - (round(y / step) - 1) * step)) * (1.0 + 1e-9)
    assert below < max(s.difficulties) <= s.threshold
    assert decompose(base, threshold=below, max_depth=6).num_subtasks > target

def test_target_subtasks_beyond_the_depth_limit_gives_the_finest_schedule_and_says_so():
    d = monotone_difficulty(np.ones(KNOTS))
    s = for_target_subtasks(d, 40, max_depth=3)
    assert s.num_subtasks == 8 and s.depth_limit_hit and s.target_subtasks == 40
    assert Schedule.from_dict(s.to_dict()) == s


def test_target_subtasks_with_root_placement():
    d = monotone_difficulty(np.linspace(0.1, 1.0, KNOTS))
    s = for_target_subtasks(d, 5, method=decompose_root)
    assert s.method == "root" and abs(s.num_subtasks - 5) <= 1


def test_target_subtasks_rejects_bad_targets():
    with pytest.raises(DataError, match="target_subtasks"):
        for_target_subtasks(monotone_difficulty(np.ones(KNOTS)), 0)


# --------------------------------------------------------------------------- the demo's scene
@pytest.fixture(scope="module")
def face_oracle():
    """d(r_a, r_b) of the demo's instruction on renders of the demo's scene (48 px)."""
    from jaxedit import scenes
    from jaxedit.edit.difficulty import DifficultyOracle
    from jaxedit_lab.simulated import SimulatedEditor

    scene = scenes.get_scene("face")
    cams, train, _ = scenes.scene_cameras(scene, views=6, test_views=0, size=48)
    views = scenes.render_scene(scene, cams[train], supersample=1)
    return DifficultyOracle(SimulatedEditor(), views, "turn him into a bronze statue",
                            reduction="mean")


@pytest.mark.parametrize("target", [4, 8])
def test_target_subtasks_on_the_demo_scene(face_oracle, target):
    s = for_target_subtasks(face_oracle, target, max_depth=4)
    assert abs(s.num_subtasks - target) <= 1, (s.ratios, s.threshold)
    assert s.target_subtasks == target
