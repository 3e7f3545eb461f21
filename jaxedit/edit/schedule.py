"""Subtask schedules: ratios 0 = r_0 < ... < r_n = 1 from a deterministic difficulty
``(r_a, r_b) -> float`` (ProEdit 3.2 bisection, greedy root placement, uniform, or the
threshold that gives N subtasks)."""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Callable, Mapping
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..errors import DataError

DifficultyFn = Callable[[float, float], float]


@dataclasses.dataclass(frozen=True)
class Schedule:
    """A subtask decomposition.

    Attributes:
      ratios: (r_0, ..., r_n = 1), strictly increasing; r_0 > 0 when continuing an edit.
      difficulties: (d(r_0, r_1), ..., d(r_{n-1}, r_n)); NaN where not measured.
      depth_limit_hit: True when some difficulty may exceed the threshold.
      evaluations: number of distinct (r_a, r_b) pairs evaluated.
      method: "bisection", "root" or "uniform".
      threshold: the difficulty threshold used (None for ``uniform``).
      target_subtasks: the count :func:`for_target_subtasks` searched for, else None.
    """

    ratios: tuple[float, ...]
    difficulties: tuple[float, ...]
    depth_limit_hit: bool = False
    evaluations: int = 0
    method: str = "bisection"
    threshold: float | None = None
    target_subtasks: int | None = None

    def __post_init__(self):
        r = self.ratios
        if len(r) < 2 or not 0.0 <= r[0] < 1.0 or r[-1] != 1.0:
            raise DataError("schedule.ratios",
                            f"must start in [0, 1) (0 unless continuing) and end at 1, "
                            f"got {list(r)}")
        if any(b <= a for a, b in zip(r, r[1:])):
            raise DataError("schedule.ratios", f"must be strictly increasing, got {list(r)}")
        if len(self.difficulties) != len(r) - 1:
            raise DataError("schedule.difficulties",
                            f"need {len(r) - 1} values (one per subtask), "
                            f"got {len(self.difficulties)}")

    @property
    def num_subtasks(self) -> int:
        return len(self.ratios) - 1

    def to_dict(self) -> dict:
        """JSON-ready dict (NaN difficulties become None)."""
        return {"ratios": list(self.ratios),
                "difficulties": [None if math.isnan(d) else d for d in self.difficulties],
                "depth_limit_hit": self.depth_limit_hit, "evaluations": self.evaluations,
                "method": self.method, "threshold": self.threshold,
                "target_subtasks": self.target_subtasks}

    @classmethod
    def from_dict(cls, d: Mapping) -> Schedule:
        try:
            return cls(ratios=tuple(float(r) for r in d["ratios"]),
                       difficulties=tuple(float("nan") if x is None else float(x)
                                          for x in d["difficulties"]),
                       depth_limit_hit=bool(d.get("depth_limit_hit", False)),
                       evaluations=int(d.get("evaluations", 0)), method=str(d.get("method", "")),
                       threshold=None if d.get("threshold") is None else float(d["threshold"]),
                       target_subtasks=(None if d.get("target_subtasks") is None
                                        else int(d["target_subtasks"])))
        except (KeyError, TypeError, ValueError) as e:
            raise DataError("schedule", f"malformed schedule ({e})") from None


def _check_threshold(threshold) -> float:
    t = float(threshold)
    if not (math.isfinite(t) and t > 0):
        raise DataError("threshold", f"must be a finite number > 0, got {threshold!r}")
    return t


def _measure(difficulty: DifficultyFn, cache: Mapping, a: float, b: float) -> tuple[float, Mapping]:
    key = (a, b)
    if key in cache:
        return cache[key], cache
    d = float(difficulty(a, b))
    if not math.isfinite(d) or d < 0:
        raise DataError("difficulty", f"d({a:g}, {b:g}) = {d!r} is not a finite number >= 0")
    return d, {**cache, key: d}


class _BisectState(NamedTuple):
    worklist: tuple[tuple[float, float, int], ...]  # intervals (a, b, depth) still to examine
    accepted: tuple[tuple[float, float, float, bool], ...]  # (a, b, d(a, b), limit hit)
    cache: Mapping


def _bisect_step(state: _BisectState, difficulty: DifficultyFn, threshold: float,
                 max_depth: int) -> _BisectState:
    (a, b, depth), rest = state.worklist[0], state.worklist[1:]
    d, cache = _measure(difficulty, state.cache, a, b)
    if d <= threshold or depth >= max_depth:
        return _BisectState(rest, state.accepted + ((a, b, d, d > threshold),), cache)
    m = 0.5 * (a + b)  # dyadic midpoints are exact in binary floating point
    return _BisectState(((a, m, depth + 1), (m, b, depth + 1)) + rest, state.accepted, cache)


def _prune(ratios: tuple[float, ...], diffs: tuple[float, ...], difficulty: DifficultyFn,
           threshold: float, cache: Mapping):
    """Remove interior ratios r_i with d(r_{i-1}, r_{i+1}) <= threshold, smallest first."""
    while True:
        best = None
        for i in range(1, len(ratios) - 1):
            m, cache = _measure(difficulty, cache, ratios[i - 1], ratios[i + 1])
            if m <= threshold and (best is None or m < best[0]):
                best = (m, i)
        if best is None:
            return ratios, diffs, cache
        m, i = best
        ratios = ratios[:i] + ratios[i + 1:]
        diffs = diffs[:i - 1] + (m,) + diffs[i + 1:]


def _check_start(start) -> float:
    r = float(start)
    if not 0.0 <= r < 1.0:
        raise DataError("start", f"the first ratio must be in [0, 1), got {start!r}")
    return r


#: The bisection's depth limit (``ProEditConfig.max_depth``): at most 2^4 = 16 subtasks.
MAX_DEPTH = 4


def decompose(difficulty: DifficultyFn, *, threshold: float, max_depth: int = MAX_DEPTH,
              prune: bool = True, start: float = 0.0) -> Schedule:
    """The paper's decomposition: bisection of [start, 1], then pruning.

    Args:
      difficulty: deterministic ``(r_a, r_b) -> float >= 0``.
      threshold: d_threshold > 0.
      max_depth: intervals of length 2^-max_depth are accepted whatever their difficulty.
      prune: run the pruning pass.
      start: the ratio already reached when continuing an edit.

    Raises DataError on a bad threshold, depth, start or difficulty value.
    """
    threshold = _check_threshold(threshold)
    if int(max_depth) < 0:
        raise DataError("max_depth", f"must be >= 0, got {max_depth}")
    start = _check_start(start)
    state = _BisectState(((start, 1.0, 0),), (), {})
    while state.worklist:
        state = _bisect_step(state, difficulty, threshold, int(max_depth))
    accepted = sorted(state.accepted)
    ratios = (start,) + tuple(b for _, b, _, _ in accepted)
    diffs = tuple(d for _, _, d, _ in accepted)
    cache = state.cache
    if prune:
        ratios, diffs, cache = _prune(ratios, diffs, difficulty, threshold, cache)
    hit = any(d > threshold for d in diffs)
    return Schedule(ratios, diffs, hit, len(cache), "bisection", threshold)


def prune_ratios(ratios, difficulty: DifficultyFn, *, threshold: float) -> Schedule:
    """Pruning pass alone on any ratio sequence (e.g. a schedule changed by the user)."""
    threshold = _check_threshold(threshold)
    ratios = tuple(float(r) for r in ratios)
    cache: Mapping = {}
    diffs = []
    for a, b in zip(ratios, ratios[1:]):
        d, cache = _measure(difficulty, cache, a, b)
        diffs.append(d)
    ratios, diffs, cache = _prune(ratios, tuple(diffs), difficulty, threshold, cache)
    return Schedule(ratios, diffs, any(d > threshold for d in diffs), len(cache), "pruned",
                    threshold)


def split_ratio(difficulty: DifficultyFn, a: float, b: float, *, iterations: int = 1,
                grid: int = 1024) -> tuple[float, float, float]:
    """(x, d(a, x), d(x, b)): the split a < x < b where d(a, x) ~ d(x, b).

    Probes the midpoint, then ``iterations`` regula falsi steps (Illinois) on
    g(x) = d(a, x) - d(x, b), which runs from -d(a, b) at a to d(a, b) at b; probes lie on
    the grid a + k (b - a) / ``grid``. Returns the probe whose harder half is the easiest.
    """
    a, b = float(a), float(b)
    if not b > a:
        raise DataError("ratio", f"a step must go up, got {a:g} -> {b:g}")
    whole, cache = _measure(difficulty, {}, a, b)
    lo, g_lo, hi, g_hi = a, -whole, b, whole
    # kept: steps in a row that moved the same end (< 0: lo); from the second, the end left
    # in place has its g halved (Illinois), so the secant does not stall on one side
    best, kept = None, 0
    for step in range(max(int(iterations), 0) + 1):
        x = 0.5 * (lo + hi) if step == 0 else lo + (hi - lo) * g_lo / (g_lo - g_hi)
        x = a + (b - a) * round((x - a) / (b - a) * grid) / grid
        if not lo < x < hi:
            break
        d1, cache = _measure(difficulty, cache, a, x)
        d2, cache = _measure(difficulty, cache, x, b)
        if best is None or max(d1, d2) < max(best[1], best[2]):
            best = (x, d1, d2)
        g = d1 - d2
        if g == 0.0:
            break
        if g < 0.0:
            lo, g_lo, kept = x, g, (kept - 1 if kept < 0 else -1)
            g_hi = g_hi / 2 if kept < -1 else g_hi
        else:
            hi, g_hi, kept = x, g, (kept + 1 if kept > 0 else 1)
            g_lo = g_lo / 2 if kept > 1 else g_lo
    return best


def decompose_interval(difficulty: DifficultyFn, lo: float, hi: float, *, threshold: float,
                       max_depth: int = MAX_DEPTH) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """:func:`decompose` rescaled to [lo, hi]: (ratios lo < ... < hi, their difficulties)."""
    lo, hi = float(lo), float(hi)
    if not hi > lo:
        raise DataError("ratio", f"an interval must go up, got {lo:g} -> {hi:g}")

    def at(u: float) -> float:
        return hi if u == 1.0 else lo + u * (hi - lo)

    s = decompose(lambda u, v: difficulty(at(u), at(v)), threshold=threshold,
                  max_depth=max_depth)
    return tuple(at(u) for u in s.ratios), tuple(s.difficulties)


def _quantise(y: float, lo: float, resolution: float) -> float:
    """Nearest point of the grid k * resolution, clipped to [lo, 1]; shared so memos hit."""
    q = round(float(y) / resolution) * resolution
    q = min(max(q, lo), 1.0)
    return 1.0 if 1.0 - q < 0.5 * resolution else round(q, 12)


# Module-level g, so the solve compiles once; the search in progress is named by a token.
_HOST_FNS: dict[int, Callable[[float], float]] = {}
_TOKENS = itertools.count(1)


def _host_g(y, token):
    return np.float32(_HOST_FNS[int(token)](float(y)))


def _g(y, token):
    return jax.pure_callback(_host_g, jax.ShapeDtypeStruct((), jnp.float32), y, token)


def _bracket_steps(resolution: float) -> int:
    return max(1, math.ceil(math.log2(1.0 / resolution))) + 1


def _bisect_host(host: Callable[[float], float], lower: float, upper: float,
                 resolution: float) -> tuple[float, float]:
    """Final bracket (lower, upper) of optimistix Bisection on host(lower) < 0 <= host(upper);
    throw=False since a step-shaped host never reaches atol."""
    errors: list[BaseException] = []

    def guarded(y):
        # keep the original exception (not XLA's wrapper) and raise it after the solve
        if errors:
            return 0.0
        try:
            return host(y)
        except Exception as e:  # noqa: BLE001 - re-raised below, unchanged
            errors.append(e)
            return 0.0

    token = next(_TOKENS)
    _HOST_FNS[token] = guarded
    try:
        solver = optx.Bisection(rtol=0.0, atol=0.25 * resolution, flip=False)
        sol = optx.root_find(_g, solver, jnp.float32(0.5 * (lower + upper)), args=jnp.int32(token),
                             options={"lower": jnp.float32(lower), "upper": jnp.float32(upper)},
                             throw=False, max_steps=_bracket_steps(resolution))
        lower, upper = float(sol.state.lower), float(sol.state.upper)
    finally:
        del _HOST_FNS[token]
    if errors:
        raise errors[0]
    return lower, upper


def _equalise(difficulty: DifficultyFn, cache: Mapping, a: float, x0: float, b: float,
              resolution: float):
    """(x, d(a, x), d(x, b), cache): x0 moved to where d(a, x) ~ d(x, b) if that lowers the max."""
    da, cache = _measure(difficulty, cache, a, x0)
    db, cache = _measure(difficulty, cache, x0, b)
    best = (max(da, db), x0, da, db)
    if b - a < 2.5 * resolution:
        return x0, da, db, cache
    box = {"cache": cache}

    def inside(y):
        return min(max(_quantise(y, a, resolution), a + resolution), b - resolution)

    def host(y):
        x = inside(y)
        d1, box["cache"] = _measure(difficulty, box["cache"], a, x)
        d2, box["cache"] = _measure(difficulty, box["cache"], x, b)
        return d1 - d2 if d1 != d2 else -1e-30

    lo, hi = _tighten(host, a, b, cache)
    if hi - lo > resolution:
        lo, hi = _bisect_host(host, lo, hi, resolution)
    cache = box["cache"]
    for y in (lo, hi):
        x = inside(y)
        d1, cache = _measure(difficulty, cache, a, x)
        d2, cache = _measure(difficulty, cache, x, b)
        if max(d1, d2) < best[0]:
            best = (max(d1, d2), x, d1, d2)
    return best[1], best[2], best[3], cache


def _tighten(fn: Callable[[float], float], lower: float, upper: float, cache: Mapping):
    """Shrink a bracket fn(lower) < 0 <= fn(upper) with cached ratios (no editor call)."""
    known = sorted({x for pair in cache for x in pair if lower < x < upper})
    for x in known:
        if fn(x) < 0:
            lower = x
        else:
            return lower, x
    return lower, upper


def _next_ratio(difficulty: DifficultyFn, cache: Mapping, r: float, threshold: float,
                resolution: float, width_hint: float | None):
    """(r', d(r, r'), resolution_hit, cache): the largest grid r' in (r, 1] with
    d(r, r') <= threshold; ``width_hint`` (the previous step) saves editor calls."""
    d1, cache = _measure(difficulty, cache, r, 1.0)
    if d1 <= threshold:
        return 1.0, d1, False, cache
    box = {"cache": cache}

    def host(y):
        d, box["cache"] = _measure(difficulty, box["cache"], r, _quantise(y, r, resolution))
        # Bisection keeps a lower end only where g < 0: d == threshold maps below 0
        return d - threshold if d > threshold else min(d - threshold, -1e-30)

    lower, upper = _tighten(host, r, 1.0, cache)
    if width_hint is not None and upper - lower > 2.0 * width_hint:
        guess = _quantise(lower + 2.0 * width_hint, r, resolution)
        if lower < guess < upper and host(guess) >= 0:
            upper = guess
    if _quantise(upper, r, resolution) - _quantise(lower, r, resolution) > resolution:
        lower, _ = _bisect_host(host, lower, upper, resolution)
    cache = box["cache"]
    # verify: a float32 rounding may have moved lower across the step
    cand = _quantise(lower, r, resolution)
    while cand > r:
        d, cache = _measure(difficulty, cache, r, cand)
        if d <= threshold:
            return cand, d, False, cache
        cand = _quantise(cand - resolution, r, resolution)
    # not even one grid step is admissible: take it and report it
    step = _quantise(r + resolution, r, resolution)
    d, cache = _measure(difficulty, cache, r, step)
    return step, d, True, cache


def decompose_root(difficulty: DifficultyFn, *, threshold: float, resolution: float = 2.0 ** -8,
                   max_subtasks: int = 64, balance: int = 1, prune: bool = True,
                   start: float = 0.0) -> Schedule:
    """Greedy placement: r_{i+1} = max{r' on the grid : d(r_i, r') <= threshold} (the fewest
    subtasks for d increasing in r').

    Args:
      difficulty, threshold, prune, start: as in :func:`decompose`.
      resolution: grid step of the ratios, in (0, 0.5].
      max_subtasks: after this many, the last step jumps to 1.
      balance: backward sweeps that equalise neighbouring difficulties; 0: none.

    Raises DataError on bad arguments.
    """
    threshold = _check_threshold(threshold)
    resolution = float(resolution)
    if not (0.0 < resolution <= 0.5):
        raise DataError("resolution", f"must be in (0, 0.5], got {resolution!r}")
    ratios, diffs, hit, cache = [_check_start(start)], [], False, {}
    while ratios[-1] < 1.0:
        r = ratios[-1]
        if len(ratios) > int(max_subtasks):
            d, cache = _measure(difficulty, cache, r, 1.0)
            nxt, d_next, step_hit = 1.0, d, d > threshold
        else:
            hint = r - ratios[-2] if len(ratios) > 1 else None
            nxt, d_next, step_hit, cache = _next_ratio(difficulty, cache, r, threshold, resolution,
                                                       hint)
        ratios.append(nxt)
        diffs.append(d_next)
        hit = hit or step_hit
    for _ in range(int(balance)):
        for i in range(len(ratios) - 2, 0, -1):
            ratios[i], diffs[i - 1], diffs[i], cache = _equalise(
                difficulty, cache, ratios[i - 1], ratios[i], ratios[i + 1], resolution)
    ratios, diffs = tuple(ratios), tuple(diffs)
    if prune:
        ratios, diffs, cache = _prune(ratios, diffs, difficulty, threshold, cache)
    return Schedule(ratios, diffs, hit or any(d > threshold for d in diffs), len(cache), "root",
                    threshold)


def for_target_subtasks(difficulty: DifficultyFn, target: int, *,
                        method: Callable[..., Schedule] = decompose,
                        resolution: float = 2.0 ** -12, start: float = 0.0,
                        **method_kwargs) -> Schedule:
    """The schedule of ``method`` whose subtask count is closest to ``target`` (bisection on
    the log-threshold; ties: fewer subtasks).

    Args:
      difficulty: as in :func:`decompose`.
      target: wanted number of subtasks, an integer >= 1.
      method: :func:`decompose` or :func:`decompose_root`.
      resolution: grid step of y.
      start, method_kwargs: passed to ``method``.

    Raises DataError on a bad target.
    """
    if int(target) != target or int(target) < 1:
        raise DataError("target_subtasks", f"must be an integer >= 1, got {target!r}")
    target = int(target)
    start = _check_start(start)
    d01 = float(difficulty(start, 1.0))
    if not d01 > 0.0:  # nothing to edit: one subtask whatever the threshold
        return dataclasses.replace(method(difficulty, threshold=1e-12, start=start,
                                          **method_kwargs), target_subtasks=target)
    octaves = 24.0
    found: dict[float, Schedule] = {}

    def schedule_at(y: float) -> Schedule:
        y = min(max(round(float(y) / resolution) * resolution, 0.0), 1.0)
        if y not in found:
            t = d01 * 2.0 ** (-octaves * (1.0 - y)) * (1.0 + 1e-9)
            found[y] = method(difficulty, threshold=t, start=start, **method_kwargs)
        return found[y]

    def h(y: float) -> float:
        return target + 0.5 - schedule_at(y).num_subtasks

    def threshold_at(k: int) -> float:  # schedule_at's threshold at grid point k
        return d01 * 2.0 ** (-octaves * (1.0 - k * resolution)) * (1.0 + 1e-9)

    def tightest(y: float) -> float:
        """The lowest grid y whose threshold covers schedule_at(y)'s hardest step: the same
        steps (decompositions are nested in the threshold), so no new probe."""
        hardest = max(schedule_at(y).difficulties)
        if not hardest > 0.0:
            return y
        k = max(0, math.ceil((1.0 + math.log2(hardest / d01) / octaves) / resolution))
        while k > 0 and threshold_at(k - 1) >= hardest:
            k -= 1
        while threshold_at(k) < hardest:
            k += 1
        low = min(k * resolution, y)
        return low if schedule_at(low).ratios == schedule_at(y).ratios else y

    lower, upper = _bracket_from_above(h, target, octaves)
    if lower is not None and lower == upper:  # exactly the target: no finer probe needed
        lower = upper = tightest(upper)
    elif lower is not None:
        lower, upper = _bisect_host(h, lower, upper, resolution)
    else:  # even the finest threshold gives at most ``target`` subtasks
        lower = 0.0
    candidates = [schedule_at(lower), schedule_at(upper)]
    best = min(candidates, key=lambda c: (abs(c.num_subtasks - target), c.num_subtasks))
    return dataclasses.replace(best, target_subtasks=target)


def _bracket_from_above(h: Callable[[float], float], target: int,
                        octaves: float) -> tuple[float | None, float]:
    """(lower, upper) with h(lower) < 0 <= h(upper), searched down from y = 1 half an octave
    of threshold at a time, starting at d(0, 1) / target; (y, y) at the first y that gives
    exactly ``target`` subtasks (h = 0.5); lower is None when h >= 0 down to y = 0.
    Decompositions' probes are nested in the threshold, so the search edits no ratio that
    the schedule at ``lower`` does not edit itself."""
    upper, y = 1.0, min(1.0, 1.0 - math.log2(target) / octaves)
    while True:
        value = h(y)
        if value < 0.0:
            return y, upper
        if value == 0.5:
            return y, y
        if y <= 0.0:
            return None, y
        upper, y = y, max(0.0, y - 0.5 / octaves)


def uniform(n: int, difficulty: DifficultyFn | None = None, *, start: float = 0.0) -> Schedule:
    """n equal subtasks from ``start``; difficulties NaN unless ``difficulty`` is given.
    Raises DataError unless n is an integer >= 1."""
    if int(n) != n or int(n) < 1:
        raise DataError("subtasks", f"must be an integer >= 1, got {n!r}")
    n = int(n)
    start = _check_start(start)
    ratios = tuple(start + i * (1.0 - start) / n for i in range(n)) + (1.0,)
    if difficulty is None:
        return Schedule(ratios, (float("nan"),) * n, False, 0, "uniform", None)
    cache: Mapping = {}
    diffs = []
    for a, b in zip(ratios, ratios[1:]):
        d, cache = _measure(difficulty, cache, a, b)
        diffs.append(d)
    return Schedule(ratios, tuple(diffs), False, len(cache), "uniform", None)


def spread(schedule: Schedule) -> dict:
    """Summary of the adjacent difficulties: min, max, mean, coefficient of variation."""
    d = np.asarray([x for x in schedule.difficulties if not math.isnan(x)], np.float64)
    if d.size == 0:
        return {"min": None, "max": None, "mean": None, "cv": None}
    mean = float(d.mean())
    return {"min": float(d.min()), "max": float(d.max()), "mean": mean,
            "cv": float(d.std() / mean) if mean > 0 else 0.0}
