"""The plan of a ProEdit run: its configuration, its subtasks r_0 -> r_1 ... r_n -> consolidate
and the SDEdit timestep annealing within a subtask (paper 3.1, 3.3)."""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

from ..editors.diffusion import check_guidance
from ..errors import DataError, check_ranges, ranged
from .schedule import MAX_DEPTH

MODES = ("proedit", "nd", "in2n")


@dataclasses.dataclass(frozen=True)
class ProEditConfig:
    """Knobs of a progressive edit (defaults follow the paper where it gives a value).

    Attributes:
      mode: "proedit" (difficulty-aware), "nd" (one subtask 0 -> 1) or "in2n" (baseline).
      threshold: the scheduler's d_threshold (None: ``target_subtasks``, else d(0, 1) / 4).
      target_subtasks: find the threshold that gives this many subtasks.
      subtasks: override with N uniform ratios.
      schedule_method: "bisect" (paper) or "root" (optimistix placement).
      max_depth: bisection depth limit (:data:`jaxedit.edit.schedule.MAX_DEPTH`).
      refine_first: first run the extra subtask r_0 = 0, refining with the editor (appendix B).
      refine_reset: start r_0 with the opacity reset too (off: it would train to faded renders).
      consolidate: last run the extra subtask r_n = 1, consolidating the edit (appendix B).
      warmup: W, steps after the opacity reset without densify/cull.
      patience: P, steps without a new minimum of the running mean loss.
      loss_window: length of the running mean.
      min_delta: relative decrease that counts as "decreased".
      max_steps: per-subtask step guard (None: :func:`subtask_guard` of the scene).
      max_seconds: per-subtask wall-clock guard, not reproducible (None: none).
      anneal_steps: N of the HiFA annealing after the warm-up (None: :func:`anneal_horizon`).
      timestep_range: (t_min, t_max) of SDEdit (paper 0.45-0.85).
      guidance: (text, image) classifier-free guidance scales (None: the editor's own).
      edit_every: trainer steps between edits in the deterministic mode.
      sweep_every: edit every view every this many steps (None: one per ``edit_every``).
      initial_sweep: edit every view at the start of a subtask (deterministic mode).
      pipelined: make the deterministic edits on a worker thread, same bits (False: inline).
      asynchronous: a producer thread instead of the deterministic schedule (not reproducible).
      checkpoint_every: steps between checkpoints inside a subtask.
      difficulty_views: seeded subset of views the difficulty is taken over (None: default).
      curve_points: grid size of the reported d(0, r) curve.
      turntable_frames: frames of each snapshot's turntable (0: none).
      background: render background (the editor sees renders on it).
      stop_on_plateau: end a subtask on the loss plateau (False: run ``max_steps``, IN2N).
    """

    mode: str = "proedit"
    threshold: float | None = ranged(None, low=0, open=True)
    target_subtasks: int | None = ranged(None, low=1)
    subtasks: int | None = ranged(None, low=1)
    schedule_method: str = "bisect"
    max_depth: int = MAX_DEPTH
    refine_first: bool = True
    refine_reset: bool = False
    consolidate: bool = True
    warmup: int = ranged(30, low=0)
    patience: int = ranged(60, low=1)
    loss_window: int = ranged(20, low=1)
    min_delta: float = 1e-3
    max_steps: int | None = ranged(None, low=1)
    max_seconds: float | None = ranged(None, low=0, open=True)
    anneal_steps: int | None = ranged(None, low=1)
    timestep_range: tuple[float, float] = (0.45, 0.85)
    guidance: tuple[float, float] | None = None
    edit_every: int = ranged(10, low=1)
    sweep_every: int | None = ranged(None, low=1)
    initial_sweep: bool = True
    pipelined: bool = True
    asynchronous: bool = False
    checkpoint_every: int = ranged(50, low=1)
    difficulty_views: int | None = ranged(None, low=1)
    curve_points: int = 9
    turntable_frames: int = ranged(24, low=0)
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    stop_on_plateau: bool = True

    def __post_init__(self):
        if self.mode not in MODES:
            raise DataError("mode", f"unknown mode {self.mode!r}; choose from {', '.join(MODES)}")
        check_ranges(self)
        if self.guidance is not None:
            object.__setattr__(self, "guidance", check_guidance(self.guidance))
        lo, hi = self.timestep_range
        if not 0.0 <= lo <= hi <= 1.0:
            raise DataError("timestep_range", f"need 0 <= t_min <= t_max <= 1, got {lo}, {hi}")
        if self.sweep_every is not None and self.asynchronous:
            raise DataError("sweep_every", "sweeps are deterministic: not with asynchronous")

    @classmethod
    def for_mode(cls, mode: str, **overrides) -> "ProEditConfig":
        """Defaults of a mode; IN2N's schedule differs (no annealing, no sweep, 0.02-0.98)."""
        base: dict[str, Any] = {"mode": mode}
        if mode == "in2n":
            base.update(timestep_range=(0.02, 0.98), edit_every=10, initial_sweep=False,
                        refine_first=False, consolidate=False, warmup=0, stop_on_plateau=False)
        base.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**base)


@dataclasses.dataclass(frozen=True)
class SubtaskSpec:
    """One subtask: ``ratio`` r_i, difficulty d(r_{i-1}, r_i) (None: not an edit step) and
    ``kind`` "refine" (r_0), "edit" or "consolidate" (r_n, e(1))."""

    index: int
    name: str
    ratio: float
    difficulty: float | None
    kind: str

    @property
    def dirname(self) -> str:
        return f"{self.index:02d}_r{self.ratio:.3f}"


def plan_subtasks(mode: str, ratios: Sequence[float], difficulties: Sequence[float] | None = None,
                  *, refine_first: bool = True, consolidate: bool = True,
                  start_ratio: float = 0.0) -> tuple[SubtaskSpec, ...]:
    """The ordered subtasks of a run.

    Args:
      ratios: the schedule r_0 = start_ratio < r_1 < ... < r_n = 1 (ND-k: r_1 = ... = r_k = 1).
      difficulties: d(r_{i-1}, r_i) for i = 1..n (or None).
      start_ratio: ratio the scene already has (continuing from a snapshot).
    Returns:
      proedit/nd: r_0 refine (if asked), r_1..r_n, r_n consolidate (if asked);
      in2n: a single edit subtask at r = 1.
    """
    ratios = [float(r) for r in ratios]
    if mode == "in2n":
        return (SubtaskSpec(0, "r1", 1.0, None, "edit"),)
    repeats_of_one = mode == "nd" and all(r == 1.0 for r in ratios[1:])
    steps = list(zip(ratios, ratios[1:]))
    if len(ratios) < 2 or abs(ratios[-1] - 1.0) > 1e-9 or any(
            b <= a for a, b in (steps[:1] if repeats_of_one else steps)):
        raise DataError("schedule", f"ratios must increase strictly to 1 (ND: or stay at 1), "
                                    f"got {ratios}")
    diffs = list(difficulties) if difficulties is not None else [None] * (len(ratios) - 1)
    specs: list[SubtaskSpec] = []
    if refine_first:
        specs.append(SubtaskSpec(0, "r0", float(start_ratio), None, "refine"))
    for i, (r, d) in enumerate(zip(ratios[1:], diffs), start=1):
        specs.append(SubtaskSpec(len(specs), f"r{i}", r, None if d is None else float(d), "edit"))
    if consolidate:
        specs.append(SubtaskSpec(len(specs), "rn", 1.0, None, "consolidate"))
    return tuple(specs)


def anneal_timestep(step: int, total: int, t_min: float, t_max: float) -> float:
    """HiFA's annealing t(i) = t_max - (t_max - t_min) sqrt(i / N), clamped at t_min."""
    frac = min(max(step, 0) / max(total, 1), 1.0)
    return float(t_max - (t_max - t_min) * math.sqrt(frac))


#: The smallest step guard of a subtask (what every scene gets at least).
GUARD_MIN_STEPS = 600
#: Epochs over the training views the guard allows at the reference resolution.
GUARD_EPOCHS = 20
#: The side (sqrt of pixels) the epoch count is meant for; the guard grows above it.
GUARD_REFERENCE_SIDE = 256


def subtask_guard(num_views: int, height: int, width: int) -> int:
    """The default ``max_steps`` of a scene with ``num_views`` views of H x W:
    ``max(GUARD_MIN_STEPS, GUARD_EPOCHS * num_views * max(1, sqrt(H W) / 256))``."""
    side = math.sqrt(float(height) * float(width)) / GUARD_REFERENCE_SIDE
    return max(GUARD_MIN_STEPS, int(math.ceil(GUARD_EPOCHS * num_views * max(1.0, side))))


@dataclasses.dataclass(frozen=True)
class SubtaskLimits:
    """How long one subtask may train: :class:`ProEditConfig` resolved for a scene
    (:func:`subtask_limits`); the config itself stays as given.

    Attributes:
      max_steps: the step guard (the config's, or :func:`subtask_guard` of the scene).
      stop_on_plateau: the loss plateau ends the subtask (False: exactly ``max_steps``).
    """

    max_steps: int
    stop_on_plateau: bool


def step_guard(config: ProEditConfig, views_shape: Sequence[int]) -> int:
    """The run's step guard: ``config.max_steps``, or :func:`subtask_guard` of training
    views of shape ``views_shape`` (N, H, W, ...) when it is None."""
    if config.max_steps is not None:
        return int(config.max_steps)
    n, h, w = views_shape[:3]
    return subtask_guard(n, h, w)


def subtask_limits(config: ProEditConfig, views_shape: Sequence[int]) -> SubtaskLimits:
    """The limits of a subtask of a run on training views of shape ``views_shape``
    (N, H, W, ...): the run's guard and plateau test (a study's own limits:
    :attr:`jaxedit.edit.hooks.EditHooks.limits`)."""
    return SubtaskLimits(step_guard(config, views_shape), config.stop_on_plateau)


def anneal_horizon(config: ProEditConfig, max_steps: int) -> int:
    """Steps after the warm-up at which a subtask's annealed timestep reaches t_min.

    Half the room ``max_steps - warmup - patience - edit_every`` under the step guard
    (the rest refines at t_min), so it grows with the scene; ``config.anneal_steps``
    overrides, clamped to the room. Not the previous subtask's length: that estimate fulfils itself.
    """
    room = max_steps - config.warmup - config.patience - config.edit_every
    horizon = config.anneal_steps if config.anneal_steps is not None else room // 2
    return int(max(1, min(horizon, room)))
