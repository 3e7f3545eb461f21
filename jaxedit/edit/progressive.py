"""The ProEdit driver: progressive editing through a schedule of subtasks.

Paper sections 3.2-3.3 and appendices B, D. The scene goes through

    s_in --r_0 (refine, e(0))--> s_0 --r_1--> s_1 ... --r_n--> s_n --consolidate (e(1))--> s_out

where every arrow is one *subtask*: a seeded, resumable transformation of the
training state. A subtask with ratio r:

1. sets every Gaussian's opacity to the cull threshold and trains ``warmup``
   steps without densify/cull, so Gaussians on the right surface earn opacity
   and wrong ones are culled at the next maintenance (paper 3.3 (1));
2. runs the iterative dataset update: edited views of the *current* renders
   (``image`` = current render, ``original`` = original photo, embedding
   e(r) = r E(p) + (1 - r) E("")) replace the training images as they arrive
   from an edit source (:mod:`jaxedit.edit.buffer`: deterministic inline or a
   producer thread); the SDEdit timestep follows HiFA's annealing
   t(i) = t_max - (t_max - t_min) sqrt(i / N) within the subtask;
3. trains with the budgeted adaptive density control (paper 3.3 (2), app. D);
4. ends when the running mean of the training loss has not decreased for
   ``patience`` steps after every view was edited at least once, or when the
   ``max_steps`` guard fires (recorded as ``converged: False``).

Modes (rows of the paper's tables): ``proedit`` (difficulty-aware schedule),
``nd`` (no decomposition: one edit subtask 0 -> 1, with the same r_0 / r_n and
adaptive 3DGS, the paper's ablation), ``in2n`` (Instruct-NeRF2NeRF on 3DGS: one
subtask at r = 1, no opacity reset, classic densify thresholds, one view edited
every 10 steps with timesteps drawn from 0.02-0.98, a fixed number of steps).

Everything random is derived from one key with ``fold_in`` of (subtask index,
purpose, step), so the deterministic mode reproduces bits, and a run resumed
from the checkpoint written inside any subtask ends with the same bits as an
uninterrupted run. Side effects (files, threads, progress) stay in
:func:`run_edit` and its helpers; the numerics are the trainer's pure steps.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import time
from pathlib import Path
from typing import Any, Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import DataError
from ..io.files import atomic_path, atomic_write_text
from .buffer import EditJob, Utilisation, make_source, pick_devices, view_order
from .editors import interpolate_embedding
from .simulated import view_key  # (run key, view, ratio, iteration) -> key, for any editor

MODES = ("proedit", "nd", "in2n")
CHECKPOINT_NAME = "checkpoint.npz"

# fold_in "purposes" of the per-subtask key: one stream per use, never shared.
_ORDER, _TRAIN, _VIEWS, _EDIT = 1, 2, 3, 4


# ---------------------------------------------------------------------------
# Configuration and plan
# ---------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class ProEditConfig:
    """Knobs of the driver (defaults follow the paper where it gives a value).

    Attributes:
      mode: "proedit" | "nd" | "in2n".
      threshold: d_threshold of the scheduler, per view: the difficulty is the mean over
        the difficulty views of the per-view distance (the paper's eq. 3 sum divided by
        |V|), so the threshold does not change with the number of views (None:
        ``target_subtasks``, else d(0, 1) / 4).
      target_subtasks: find the threshold that gives this many subtasks (a 1-D root
        find; the paper reports ~4 for texture and ~8 for geometry edits).
      subtasks: override with N uniform ratios (paper: ~4 texture, ~8 geometry).
      schedule_method: "bisect" (paper) or "root" (optimistix placement).
      max_depth: bisection depth limit.
      refine_first / consolidate: the extra subtasks r_0 and r_n (appendix B).
      warmup: W, steps after the opacity reset without densify/cull.
      patience: P, steps without a new minimum of the running mean loss.
      loss_window: length of the running mean.
      min_delta: relative decrease that counts as "decreased".
      max_steps: per-subtask guard.
      anneal_steps: N of the HiFA annealing (default: max_steps).
      timestep_range: (t_min, t_max) of SDEdit (paper 0.45-0.85).
      guidance: (text, image) classifier-free guidance scales.
      edit_every: trainer steps between edits in the deterministic mode.
      initial_sweep: edit every view at the start of a subtask (deterministic mode).
      asynchronous: producer thread instead of the deterministic schedule.
      checkpoint_every: steps between checkpoints inside a subtask.
      difficulty_views: size of the fixed, seeded subset of training views the difficulty
        d(r_a, r_b) is taken over (None: all of them, up to
        ``DIFFICULTY_VIEWS_DEFAULT_MAX``; each view costs one editor call per ratio).
      curve_points: grid size of the reported d(0, r) curve.
      turntable_frames: frames of each snapshot's turntable (0: none).
      background: render background (the editor sees renders on it).
      stop_on_plateau: end a subtask on the loss plateau (ProEdit); False runs
        exactly ``max_steps`` (IN2N trains for a fixed number of iterations).
    """

    mode: str = "proedit"
    threshold: float | None = None
    target_subtasks: int | None = None
    subtasks: int | None = None
    schedule_method: str = "bisect"
    max_depth: int = 4
    refine_first: bool = True
    consolidate: bool = True
    warmup: int = 30
    patience: int = 60
    loss_window: int = 20
    min_delta: float = 1e-3
    max_steps: int = 600
    anneal_steps: int | None = None
    timestep_range: tuple[float, float] = (0.45, 0.85)
    guidance: tuple[float, float] = (7.5, 1.5)
    edit_every: int = 10
    initial_sweep: bool = True
    asynchronous: bool = False
    checkpoint_every: int = 50
    difficulty_views: int | None = None
    curve_points: int = 9
    turntable_frames: int = 0
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    stop_on_plateau: bool = True

    def __post_init__(self):
        if self.mode not in MODES:
            raise DataError("--mode", f"unknown mode {self.mode!r}; choose from {', '.join(MODES)}")
        if self.threshold is not None and not self.threshold > 0:
            raise DataError("--threshold", f"must be > 0, got {self.threshold}")
        if self.subtasks is not None and self.subtasks < 1:
            raise DataError("--subtasks", f"must be >= 1, got {self.subtasks}")
        if self.target_subtasks is not None and self.target_subtasks < 1:
            raise DataError("--target-subtasks", f"must be >= 1, got {self.target_subtasks}")
        if self.difficulty_views is not None and self.difficulty_views < 1:
            raise DataError("--difficulty-views", f"must be >= 1, got {self.difficulty_views}")
        lo, hi = self.timestep_range
        if not 0.0 <= lo <= hi <= 1.0:
            raise DataError("timestep_range", f"need 0 <= t_min <= t_max <= 1, got {lo}, {hi}")
        for name in ("patience", "loss_window", "max_steps", "edit_every", "checkpoint_every"):
            if getattr(self, name) < 1:
                raise DataError(name, f"must be >= 1, got {getattr(self, name)}")

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
    """One subtask: ``ratio`` r_i and the measured difficulty d(r_{i-1}, r_i) (None: not an edit step).

    kind: "refine" (r_0, null embedding), "edit" or "consolidate" (r_n, e(1)).
    """

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
      ratios: the schedule r_0 = start_ratio < r_1 < ... < r_n = 1.
      difficulties: d(r_{i-1}, r_i) for i = 1..n (or None).
      start_ratio: ratio the scene already has (continuing from a snapshot).
    Returns:
      proedit/nd: r_0 refine (if asked), r_1..r_n, r_n consolidate (if asked);
      in2n: a single edit subtask at r = 1.
    """
    ratios = [float(r) for r in ratios]
    if mode == "in2n":
        return (SubtaskSpec(0, "r1", 1.0, None, "edit"),)
    if len(ratios) < 2 or abs(ratios[-1] - 1.0) > 1e-9 or any(
            b <= a for a, b in zip(ratios, ratios[1:])):
        raise DataError("schedule", f"ratios must increase strictly to 1, got {ratios}")
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


def train_view(key: jax.Array, step: int, num_views: int) -> int:
    """The view trained at ``step``: epochs of seeded permutations (pure in (key, step))."""
    epoch, pos = divmod(int(step), num_views)
    perm = jax.random.permutation(jax.random.fold_in(key, epoch), num_views)
    return int(perm[pos])


# ---------------------------------------------------------------------------
# Convergence: running mean of the loss, patience
# ---------------------------------------------------------------------------
class LossTracker(NamedTuple):
    """Running mean of the last ``window`` losses and steps since its last minimum.

    recent: float [window] ring buffer; count: losses seen; best: lowest running
    mean so far (inf before the window is full); since_best: steps since then.
    """

    recent: np.ndarray
    count: int
    best: float
    since_best: int

    @staticmethod
    def init(window: int) -> "LossTracker":
        return LossTracker(np.zeros((window,), np.float64), 0, math.inf, 0)

    def mean(self) -> float:
        n = min(self.count, len(self.recent))
        return float(np.mean(self.recent[:n])) if n else math.inf


def track_loss(tracker: LossTracker, loss: float, *, min_delta: float) -> LossTracker:
    """Add one loss; a running mean below best * (1 - min_delta) resets the patience counter."""
    recent = tracker.recent.copy()
    recent[tracker.count % len(recent)] = loss
    t = LossTracker(recent, tracker.count + 1, tracker.best, tracker.since_best)
    if t.count < len(recent):
        return t
    mean = t.mean()
    if mean < t.best * (1.0 - min_delta) or not math.isfinite(t.best):
        return t._replace(best=mean, since_best=0)
    return t._replace(since_best=t.since_best + 1)


# ---------------------------------------------------------------------------
# Data the driver works on
# ---------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class EditData:
    """Views of the scene being edited.

    Attributes:
      train_images: float32 [N, H, W, 3], the original photos of the training views.
      train_cameras: batched Camera [N].
      test_images: float32 [M, H, W, 3], held-out originals (never trained on).
      test_cameras: batched Camera [M].
    """

    train_images: np.ndarray
    train_cameras: Any
    test_images: np.ndarray
    test_cameras: Any

    def __post_init__(self):
        if self.train_images.ndim != 4 or self.train_images.shape[-1] != 3:
            raise DataError("train_images", f"need float [N, H, W, 3], got {self.train_images.shape}")
        if len(self.train_cameras) != len(self.train_images):
            raise DataError("train_cameras", f"{len(self.train_cameras)} cameras for "
                                             f"{len(self.train_images)} images")
        if len(self.test_cameras) != len(self.test_images):
            raise DataError("test_cameras", f"{len(self.test_cameras)} cameras for "
                                            f"{len(self.test_images)} images")

    @staticmethod
    def from_dataset(dataset) -> "EditData":
        """From a :func:`jaxedit.io.load_nerfstudio` dataset (train/test split)."""
        images = np.asarray(dataset.images, np.float32)
        train = np.asarray(dataset.train_indices)
        test = np.asarray(dataset.test_indices)
        if len(test) == 0:  # no held-out split: score on the training views, say so
            test = train
        return EditData(images[train], dataset.cameras[train], images[test], dataset.cameras[test])


# ---------------------------------------------------------------------------
# Rendering with the overflow protocol
# ---------------------------------------------------------------------------
class Renderer:
    """Render single views over a fixed background, never truncated.

    Outside jit, :func:`jaxedit.raster.render` sizes its intersection buffer
    itself (counting first, caching the size, redoing a frame that overflowed),
    so a frame is complete whatever the scene's growth.
    """

    def __init__(self, background=(1.0, 1.0, 1.0)):
        self.background = jnp.asarray(background, jnp.float32)

    def __call__(self, gaussians, camera):
        """RenderOutput of one camera."""
        from ..raster import render

        return render(gaussians, camera, background=self.background)

    def rgb(self, gaussians, camera) -> np.ndarray:
        return np.asarray(self(gaussians, camera).rgb, np.float32)

    def views(self, gaussians, cameras) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rgb [N,H,W,3], alpha [N,H,W], depth [N,H,W]) of a batched camera."""
        outs = [self(gaussians, cameras[i]) for i in range(len(cameras))]
        return (np.stack([np.asarray(o.rgb, np.float32) for o in outs]),
                np.stack([np.asarray(o.alpha, np.float32) for o in outs]),
                np.stack([np.asarray(o.depth, np.float32) for o in outs]))


# ---------------------------------------------------------------------------
# Metrics of an edited scene
# ---------------------------------------------------------------------------
def image_scores(renders: np.ndarray, targets: np.ndarray) -> dict:
    """Mean PSNR (dB) and SSIM (scikit-image) of renders vs targets, float [N, H, W, 3] in [0, 1]."""
    from skimage.metrics import structural_similarity

    psnrs, ssims = [], []
    for a, b in zip(np.clip(renders, 0, 1), np.clip(targets, 0, 1)):
        mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
        psnrs.append(-10.0 * np.log10(max(mse, 1e-10)))  # identical images: 100 dB, not inf
        ssims.append(structural_similarity(b, a, channel_axis=-1, data_range=1.0,
                                           win_size=min(7, min(a.shape[:2]) // 2 * 2 - 1)))
    return {"psnr": float(np.mean(psnrs)), "ssim": float(np.mean(ssims))}


def reprojection_consistency(rgb: np.ndarray, alpha: np.ndarray, depth: np.ndarray, cameras,
                             *, min_alpha: float = 0.5) -> float:
    """Multi-view consistency of renders: PSNR (dB) of colours carried between neighbouring views.

    Each pixel of view i with alpha > min_alpha is lifted to 3D with its rendered
    depth, projected into view i+1 (cyclically) and compared with the colour
    there (nearest pixel, only where that view also sees a surface at the same
    depth within 5%). View-dependent colour that overfits inconsistent edits,
    floaters and depth errors all lower it. Returns NaN when no pixel is co-visible.

    Args:
      rgb: float [N, H, W, 3]; alpha, depth: float [N, H, W]; cameras: batched [N].
    """
    n, h, w = depth.shape
    if n < 2:
        return float("nan")
    ys, xs = np.mgrid[0:h, 0:w]
    pix = np.stack([xs + 0.5, ys + 0.5, np.ones_like(xs, dtype=np.float64)], -1).reshape(-1, 3)
    err, count = 0.0, 0
    w2c = np.asarray(cameras.world_to_camera, np.float64)
    k = np.asarray(cameras.intrinsics(), np.float64)
    for i in range(n):
        j = (i + 1) % n
        ok = alpha[i].reshape(-1) > min_alpha
        if not ok.any():
            continue
        rays = pix[ok] @ np.linalg.inv(k[i]).T
        cam_pts = rays * depth[i].reshape(-1)[ok, None]
        c2w = np.linalg.inv(w2c[i])
        world = cam_pts @ c2w[:3, :3].T + c2w[:3, 3]
        pj = world @ w2c[j][:3, :3].T + w2c[j][:3, 3]
        z = pj[:, 2]
        uv = pj @ k[j].T
        front = z > 1e-6
        u = np.floor(uv[:, 0] / np.where(front, z, 1)).astype(np.int64)
        v = np.floor(uv[:, 1] / np.where(front, z, 1)).astype(np.int64)
        inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        u, v, zi = u[inside], v[inside], z[inside]
        seen = (alpha[j][v, u] > min_alpha) & (np.abs(depth[j][v, u] - zi) < 0.05 * zi)
        if not seen.any():
            continue
        ci = rgb[i].reshape(-1, 3)[ok][inside][seen]
        cj = rgb[j][v[seen], u[seen]]
        err += float(np.sum((ci - cj) ** 2))
        count += ci.size
    if count == 0:
        return float("nan")
    mse = max(err / count, 1e-10)
    return float(-10.0 * np.log10(mse))


# ---------------------------------------------------------------------------
# Checkpoints: the whole driver state, atomically, bit-exact
# ---------------------------------------------------------------------------
def _flatten(tree) -> dict[str, np.ndarray]:
    leaves = jax.tree_util.tree_flatten_with_path(tree)[0]
    return {jax.tree_util.keystr(p): np.asarray(v) for p, v in leaves}


def _unflatten(template, arrays: dict[str, np.ndarray], where: str):
    paths, treedef = jax.tree_util.tree_flatten_with_path(template)
    leaves = []
    for p, ref in paths:
        k = jax.tree_util.keystr(p)
        if k not in arrays:
            raise DataError(where, f"checkpoint lacks {k} (saved by another version?)")
        a = arrays[k]
        if isinstance(ref, jax.Array) and jax.dtypes.issubdtype(ref.dtype, jax.dtypes.prng_key):
            a = jax.random.wrap_key_data(a)
        else:
            a = jnp.asarray(a)
        leaves.append(a)
    return jax.tree_util.tree_unflatten(treedef, leaves)


def _key_data(tree):
    """Replace typed PRNG keys by their raw data so they can be saved."""
    def fn(x):
        if isinstance(x, jax.Array) and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
            return jax.random.key_data(x)
        return x
    return jax.tree_util.tree_map(fn, tree)


@dataclasses.dataclass
class DriverState:
    """Where a run is: everything needed to continue it exactly.

    Attributes:
      subtask: index of the current subtask in the plan.
      step: steps already taken inside it (0: not started, opacity not yet reset).
      train: the trainer's state pytree (Gaussians, optimiser, densify stats).
      images: float32 [N, H, W, 3], the training images as of now (edited views).
      edited: bool [N], views edited at least once in the current subtask.
      tracker: the loss tracker of the current subtask.
      records: one dict per finished subtask (schedule.json entries).
      seconds: wall time spent in the current subtask before the last restart.
      utilisation: buffer counters summed over the run.
    """

    subtask: int
    step: int
    train: Any
    images: np.ndarray
    edited: np.ndarray
    tracker: LossTracker
    records: list
    seconds: float = 0.0
    utilisation: Utilisation = dataclasses.field(default_factory=Utilisation)


def save_checkpoint(path: str | os.PathLike, st: DriverState, meta: dict) -> None:
    """Write the driver state to ``path`` (npz, atomic: a crash never leaves half a file)."""
    arrays = {f"train/{k}": v for k, v in _flatten(_key_data(st.train)).items()}
    arrays["images"] = st.images
    arrays["edited"] = st.edited
    arrays["tracker_recent"] = st.tracker.recent
    info = {"subtask": st.subtask, "step": st.step, "records": st.records,
            "seconds": st.seconds, "utilisation": st.utilisation.as_dict(),
            "tracker": [st.tracker.count, st.tracker.best, st.tracker.since_best],
            "max_intersections": getattr(st.train, "max_intersections", None), "meta": meta}
    arrays["info"] = np.frombuffer(json.dumps(info).encode(), np.uint8)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)


def load_checkpoint(path: str | os.PathLike, train_template) -> tuple[DriverState, dict]:
    """Read a checkpoint written by :func:`save_checkpoint` (state, meta).

    ``train_template`` is any trainer state of the same structure (shapes may
    differ: capacity grows during a run); its typed PRNG keys are restored.
    """
    path = Path(path)
    try:
        with np.load(path) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError) as e:
        raise DataError(path, f"cannot read checkpoint ({e})") from None
    try:
        info = json.loads(arrays.pop("info").tobytes().decode())
    except (KeyError, ValueError):
        raise DataError(path, "not a jaxedit edit checkpoint (no info record)") from None
    train = _unflatten(train_template, {k[6:]: v for k, v in arrays.items()
                                        if k.startswith("train/")}, str(path))
    if info.get("max_intersections") is not None and hasattr(train, "max_intersections"):
        train = dataclasses.replace(train, max_intersections=int(info["max_intersections"]))
    count, best, since = info["tracker"]
    st = DriverState(subtask=info["subtask"], step=info["step"], train=train,
                     images=arrays["images"], edited=arrays["edited"],
                     tracker=LossTracker(arrays["tracker_recent"], count, best, since),
                     records=info["records"], seconds=info["seconds"],
                     utilisation=Utilisation(**info["utilisation"]))
    return st, info["meta"]


# ---------------------------------------------------------------------------
# The trainer of a subtask: jaxedit.train's pure step with ProEdit's density control
# ---------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class TrainSettings:
    """Optimisation settings of the editing trainer (Splatfacto learning rates, constant).

    Attributes:
      scene_extent: world size (None: ``jaxedit.train.scene_extent`` of the train cameras).
      adaptive: ProEdit's budgeted creation (True) or classic 3DGS thresholds (False, IN2N).
      cull_alpha: the cull threshold, which is also the opacity every Gaussian gets
        at a subtask start (Splatfacto's cull_alpha_thresh 0.1 keeps the scene
        visible to the editor; gsplat's 0.005 would blank it).
      warmup: W, steps after the subtask start without density control.
      max_gaussians: the hard cap (None: :func:`default_max_gaussians` of the input).
      budget_*: the creation budget t(n, N) (see ``jaxedit.densify.creation_budget``).
        ASSUMPTION: the paper (appendix "Gaussian Creation Strategy") gives only the form
        "t(n) of the culled count n and the total N", no constants; 16 / 2% / 10% are ours.
      refine_every: steps between maintenance steps. ASSUMPTION: 50, where Splatfacto
        (whose defaults the paper follows) uses 100; our CPU subtasks are a few hundred
        steps, not the paper's 10-20 minutes.
      sh_degree: SH degree trained (the input scene's, all degrees on from the start).
      lr_means, lr_sh_dc, lr_opacity: Adam learning rates (Splatfacto's by default;
        the higher-order SH get lr_sh_dc / 20). Splatfacto's are tuned for ~30k
        steps; short CPU runs of a few hundred steps per subtask need a larger
        colour rate to follow the edits at all (the ablation uses 10x).
    """

    scene_extent: float | None = None
    adaptive: bool = True
    cull_alpha: float = 0.1
    warmup: int = 30
    refine_every: int = 50
    max_gaussians: int | None = None
    budget_min_new: int = 16
    budget_growth: float = 0.02
    budget_max_fraction: float = 0.1
    sh_degree: int = 3
    lr_means: float = 1.6e-4
    lr_sh_dc: float = 2.5e-3
    lr_opacity: float = 0.05
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def train_config(self):
        """The :class:`jaxedit.train.TrainConfig` these settings describe."""
        from ..train import DensifyConfig, TrainConfig

        if self.adaptive:  # ProEdit: creation budget; opacity resets at subtask starts only
            mode = dict(budget=True, budget_min_new=self.budget_min_new,
                        budget_growth=self.budget_growth,
                        budget_max_fraction=self.budget_max_fraction, reset_every=0)
        else:  # IN2N / IGS2GS: Splatfacto's classic thresholds and periodic opacity reset
            mode = dict(budget=False, reset_every=3000)
        dens = DensifyConfig(refine_every=self.refine_every, warmup=self.warmup, stop_at=2 ** 30,
                             cull_alpha=self.cull_alpha, max_gaussians=self.max_gaussians, **mode)
        bg = tuple(float(c) for c in self.background)
        background = {(1.0, 1.0, 1.0): "white", (0.0, 0.0, 0.0): "black"}.get(bg)
        if background is None:
            raise DataError("background", f"the trainer supports white or black, got {bg}")
        # Constant means learning rate (no decay across subtasks), every SH degree from step 1.
        return TrainConfig(iterations=2 ** 30, lr_means=self.lr_means,
                           lr_means_final=self.lr_means, lr_sh_dc=self.lr_sh_dc,
                           lr_sh_rest=self.lr_sh_dc / 20, lr_opacity=self.lr_opacity,
                           sh_degree=self.sh_degree, sh_degree_interval=1,
                           background=background, densify=dens)


#: Room the default cap leaves above a small input (Gaussians).
CAP_MIN_ROOM = 10_000


def default_max_gaussians(num_input: int) -> int:
    """The edit's default hard cap: twice the input's Gaussians, at least CAP_MIN_ROOM more.

    Reconstructions by Splatfacto or gsplat hold 0.3-3M Gaussians; a fixed cap below that
    would leave ProEdit's creation budget no room, so geometry edits could only recolour.
    """
    return max(2 * int(num_input), int(num_input) + CAP_MIN_ROOM)


def resolve_max_gaussians(settings: TrainSettings, num_input: int) -> TrainSettings:
    """``settings`` with its cap resolved for an input of ``num_input`` Gaussians (never below)."""
    cap = settings.max_gaussians
    if cap is None:
        return dataclasses.replace(settings, max_gaussians=default_max_gaussians(num_input))
    if int(cap) < int(num_input):
        raise DataError("--max-gaussians", f"{cap} is below the input scene's {num_input} "
                        "Gaussians (the cap never removes Gaussians)")
    return settings


class SubtaskTrainer:
    """The driver's view of :mod:`jaxedit.train`: init, subtask restart, one step.

    ``step`` is :func:`jaxedit.train.step_with_retry` (a pure jitted step, redone
    with a larger intersection buffer or capacity when it asks for it), on the
    view and key the driver chose. ``restart`` is paper 3.3 (1): every opacity to
    the cull threshold (moments zeroed), fresh density statistics, and the
    density-control clock restarted so that the first ``warmup`` steps of the
    subtask have no densify/cull.
    """

    def __init__(self, settings: TrainSettings = TrainSettings(), num_input: int | None = None):
        """``num_input``: the input scene's Gaussian count, to resolve a cap left as None."""
        if settings.max_gaussians is None:
            if num_input is None:
                raise DataError("max_gaussians", "unresolved: pass num_input or a cap")
            settings = resolve_max_gaussians(settings, num_input)
        self.settings = settings
        self.config = settings.train_config()

    def init(self, gaussians, cameras=None):
        """A fresh train state; with ``cameras``, its tile buffer is sized to what they need.

        The step's cost grows with the intersection buffer (it is sorted every
        step), so measure the views instead of guessing from the capacity; a
        scene that grows later overflows once and the step is redone larger.
        """
        from .. import train
        from ..raster import render
        from ..raster.render import next_capacity

        sh = min(self.settings.sh_degree, gaussians.sh_degree)
        config = dataclasses.replace(self.config, sh_degree=sh)
        cap = None
        if cameras is not None and len(cameras):
            needed = max(int(render(gaussians, cameras[i]).num_intersections)
                         for i in range(len(cameras)))
            cap = next_capacity(max(int(needed * 1.5), 1024))
        return train.init_state(gaussians, config, self.settings.scene_extent,
                                max_intersections=cap)

    def restart(self, state):
        from .. import densify

        g, opt = densify.opacity_reset(state.gaussians, state.opt_state, self.settings.cull_alpha)
        strategy = state.config.densify.strategy(state.scene_extent, state.config.iterations)
        return dataclasses.replace(state, gaussians=g, opt_state=opt,
                                   densify_stats=strategy.init(g), densify_origin=state.step)

    @staticmethod
    def gaussians(state):
        return state.gaussians

    def step(self, state, image, camera, key):
        """(state, loss float, metrics) after one optimiser + density-control step."""
        from .. import train

        batch = train.Batch(image=jnp.asarray(image, jnp.float32), camera=camera)
        state, metrics = train.step_with_retry(state, batch, key)
        return state, float(metrics["loss"]), metrics


# ---------------------------------------------------------------------------
# Running subtasks
# ---------------------------------------------------------------------------
@dataclasses.dataclass
class EditContext:
    """Everything a run reads but never changes.

    Attributes:
      editor: an :class:`jaxedit.edit.Editor`.
      prompt: the instruction p.
      data: the views (:class:`EditData`).
      config: :class:`ProEditConfig`.
      trainer: :class:`SubtaskTrainer`.
      renderer: :class:`Renderer` used for the editor's inputs and the snapshots.
      key: the run key (``jax.random.key(seed)``).
      editor_device: device of the editor (async mode), see :func:`pick_devices`.
    """

    editor: Any
    prompt: str
    data: EditData
    config: ProEditConfig
    trainer: SubtaskTrainer
    renderer: Renderer
    key: jax.Array
    editor_device: Any = None

    def __post_init__(self):
        self.e_prompt = np.asarray(self.editor.encode(self.prompt))
        self.e_null = np.asarray(self.editor.encode(""))


def make_edit_fn(ctx: EditContext, spec: SubtaskSpec) -> Callable[[EditJob, Any], np.ndarray]:
    """``(job, scene) -> edited view`` of subtask ``spec``: render the view, edit it with e(r).

    The editor sees ``image`` = the current render, ``original`` = the original
    photo, embedding e(r); the key is (run key | subtask, view, ratio, iteration);
    the timestep follows HiFA's annealing over ``anneal_steps`` (IN2N mode: the
    fixed range, from which the editor draws).
    """
    cfg = ctx.config
    ratio = 0.0 if spec.kind == "refine" else spec.ratio
    embedding = interpolate_embedding(ctx.e_prompt, ctx.e_null, ratio)
    sub_key = jax.random.fold_in(jax.random.fold_in(ctx.key, spec.index), _EDIT)
    anneal_n = cfg.anneal_steps or cfg.max_steps
    renderer = ctx.renderer

    def edit_fn(job: EditJob, scene) -> np.ndarray:
        camera = ctx.data.train_cameras[job.view]
        render = renderer.rgb(scene, camera)
        if cfg.mode == "in2n":
            t_range = tuple(cfg.timestep_range)
        else:
            t = anneal_timestep(job.step, anneal_n, *cfg.timestep_range)
            t_range = (t, t)
        key = view_key(sub_key, job.view, ratio, job.iteration)
        return ctx.editor.edit(render, ctx.data.train_images[job.view], embedding, key,
                               timestep_range=t_range, guidance=tuple(cfg.guidance))

    return edit_fn


def initial_state(ctx: EditContext, gaussians, images: np.ndarray | None = None) -> DriverState:
    """A run at its very beginning: the input scene, the original photos as training images."""
    images = ctx.data.train_images if images is None else images
    # Room to densify from the start (growth means a recompile), but not much more: the
    # step's cost grows with the capacity. 1.5x, a multiple of 256.
    want = -(-int(1.5 * int(gaussians.num_alive())) // 256) * 256
    capacity = min(max(want, gaussians.capacity), max(ctx.trainer.settings.max_gaussians,
                                                     gaussians.capacity))
    if capacity > gaussians.capacity:
        from ..gaussians import grow

        gaussians = grow(gaussians, capacity)
    return DriverState(subtask=0, step=0, train=ctx.trainer.init(gaussians, ctx.data.train_cameras),
                       images=np.array(images, np.float32, copy=True),
                       edited=np.zeros((len(images),), bool),
                       tracker=LossTracker.init(ctx.config.loss_window), records=[])


def run_subtask(ctx: EditContext, st: DriverState, spec: SubtaskSpec, *,
                callback: Callable | None = None, checkpoint: Callable | None = None,
                progress: Callable | None = None) -> tuple[DriverState, dict]:
    """Train subtask ``spec`` from ``st`` (possibly resumed mid-way) until it converges.

    Args:
      callback: ``callback(spec, step, loss)`` after every step (may raise, e.g. to stop).
      checkpoint: ``checkpoint(st)`` every ``checkpoint_every`` steps.
      progress: ``progress(spec, step, loss, st)`` after every step.
    Returns:
      (state at the end of the subtask, {"steps", "converged", "seconds", "utilisation"}).
    """
    cfg, data, trainer = ctx.config, ctx.data, ctx.trainer
    n = len(data.train_images)
    key_sub = jax.random.fold_in(ctx.key, spec.index)
    adaptive = cfg.mode != "in2n"
    warmup = trainer.settings.warmup
    if st.step == 0:
        if adaptive:
            st.train = trainer.restart(st.train)
        st.edited = np.zeros((n,), bool)
        st.tracker = LossTracker.init(cfg.loss_window)
        st.seconds = 0.0
    order = view_order(n, jax.random.fold_in(key_sub, _ORDER))
    source = make_source(make_edit_fn(ctx, spec), order, asynchronous=cfg.asynchronous,
                         every=cfg.edit_every, initial_sweep=cfg.initial_sweep,
                         device=ctx.editor_device)
    views_key = jax.random.fold_in(key_sub, _VIEWS)
    train_key = jax.random.fold_in(key_sub, _TRAIN)
    started = time.perf_counter() - st.seconds
    converged = False

    from ..train import put_image

    # The training views live on the device; an edited view lands there in place, so a
    # step uploads nothing (st.images keeps the host copy that checkpoints store).
    device_images = [jax.device_put(np.asarray(st.images, np.float32))]

    def take(arrivals):
        for e in arrivals:
            st.images[e.job.view] = e.image
            st.edited[e.job.view] = True
            device_images[0] = put_image(device_images[0], e.job.view, st.images[e.job.view])

    with source:
        while True:
            s = st.step
            if s >= warmup:  # no edits while the reset opacities settle (paper 3.3 (1))
                take(source.exchange(s - warmup, trainer.gaussians(st.train)))
            v = train_view(views_key, s, n)
            image = device_images[0][v]
            st.train, loss, _ = trainer.step(st.train, image, data.train_cameras[v],
                                             jax.random.fold_in(train_key, s))
            if s >= warmup:
                st.tracker = track_loss(st.tracker, loss, min_delta=cfg.min_delta)
            st.step = s + 1
            st.seconds = time.perf_counter() - started
            if progress is not None:
                progress(spec, st.step, loss, st)
            if callback is not None:
                callback(spec, st.step, loss)
            plateau = (cfg.stop_on_plateau and st.tracker.count >= cfg.loss_window
                       and st.tracker.since_best >= cfg.patience)
            if plateau and not st.edited.all():
                if source.deterministic:
                    pass  # the fixed rule will edit the missing views; keep training
                else:
                    # The loss settled on a partly stale dataset: wait for the missing views.
                    source.wait_for(lambda: bool(st.edited.all()), timeout=600, on_edits=take)
                    st.tracker = st.tracker._replace(since_best=0)
                    plateau = False
            if plateau and st.edited.all():
                converged = True
                break
            if st.step >= cfg.max_steps:
                converged = not cfg.stop_on_plateau  # a fixed budget ends where it should
                if not st.edited.all() and not source.deterministic:
                    # Never end a subtask on a dataset the editor has not fully updated to
                    # e(r_i): a slow editor makes the trainer wait here (counted).
                    source.wait_for(lambda: bool(st.edited.all()), timeout=600, on_edits=take)
                break
            if checkpoint is not None and st.step % cfg.checkpoint_every == 0:
                checkpoint(st)
    st.seconds = time.perf_counter() - started  # including the final waits and the join
    st.utilisation = st.utilisation.add(source.utilisation)
    return st, {"steps": st.step, "converged": converged, "seconds": st.seconds,
                "utilisation": source.utilisation.as_dict()}


# ---------------------------------------------------------------------------
# Schedules
# ---------------------------------------------------------------------------
DEFAULT_SUBTASKS = 4  # default threshold = d(0, 1) / 4 (paper: ~4 subtasks for texture edits)
#: Difficulty views by default: every training view up to this many (an editor call per
#: view and ratio: 16 views x 17 ratios of a depth-4 bisection is ~270 edits, about 9
#: minutes of InstructPix2Pix at ~2 s per edit), else a seeded subset of this size.
DIFFICULTY_VIEWS_DEFAULT_MAX = 16
#: fold_in purpose of the difficulty view subset's key.
_DIFFICULTY_VIEWS = 5


def difficulty_view_subset(num_views: int, count: int | None, key) -> tuple[int, ...]:
    """The fixed, seeded subset of ``count`` view indices (sorted) the difficulty is taken over.

    ``count`` None: all views up to :data:`DIFFICULTY_VIEWS_DEFAULT_MAX`. A subset is a
    uniform draw without replacement from ``key``, so it depends on the run seed only.
    """
    if num_views <= 0:
        raise DataError("views", "need at least one original view")
    count = min(num_views, DIFFICULTY_VIEWS_DEFAULT_MAX if count is None else int(count))
    if count >= num_views:
        return tuple(range(num_views))
    chosen = jax.random.choice(jax.random.fold_in(key, _DIFFICULTY_VIEWS), num_views, (count,),
                               replace=False)
    return tuple(sorted(int(v) for v in np.asarray(chosen)))


def difficulty_oracle(ctx: EditContext, originals: np.ndarray, seed: int, distance=None):
    """The memoised d(r_a, r_b) over the difficulty views' renders of the input scene.

    ``distance``: the perceptual distance (e.g. :func:`jaxedit.lpips.lpips_distance`);
    None is the oracle's default (multi-scale SSIM). The reduction over views is the
    mean (eq. 3's sum / |V|), so thresholds are per view.
    """
    from .difficulty import DifficultyOracle

    views = difficulty_view_subset(len(originals), ctx.config.difficulty_views, ctx.key)
    return DifficultyOracle(ctx.editor, originals, ctx.prompt, views=views, distance=distance,
                            guidance=tuple(ctx.config.guidance), seed=seed, reduction="mean")


def distance_name(distance) -> str:
    """What schedule.json and the log call a difficulty distance."""
    from .difficulty import ms_ssim_distance

    distance = ms_ssim_distance if distance is None else distance
    return getattr(distance, "name", getattr(distance, "__name__", type(distance).__name__))


def make_schedule(ctx: EditContext, oracle, *, start_ratio: float = 0.0):
    """(Schedule, plan ratios from ``start_ratio``, their difficulties) per the config."""
    from . import schedule as sched

    cfg = ctx.config
    if cfg.mode == "nd":
        s = sched.uniform(1, oracle)
    elif cfg.mode == "in2n":
        s = sched.uniform(1, None)
    elif cfg.subtasks is not None:
        s = sched.uniform(cfg.subtasks, oracle)
    elif cfg.threshold is None and cfg.target_subtasks is not None:
        method = sched.decompose_root if cfg.schedule_method == "root" else sched.decompose
        kwargs = {} if cfg.schedule_method == "root" else {"max_depth": cfg.max_depth}
        s = sched.for_target_subtasks(oracle, cfg.target_subtasks, method=method, **kwargs)
    else:
        # No threshold given: a quarter of the whole task's difficulty, i.e. about the
        # paper's ~4 subtasks for texture edits (more where d(0, r) is uneven).
        threshold = (cfg.threshold if cfg.threshold is not None
                     else max(oracle(0.0, 1.0) / DEFAULT_SUBTASKS, 1e-6))
        method = sched.decompose_root if cfg.schedule_method == "root" else sched.decompose
        kwargs = {} if cfg.schedule_method == "root" else {"max_depth": cfg.max_depth}
        s = method(oracle, threshold=threshold, **kwargs)
    ratios = [start_ratio] + [r for r in s.ratios if r > start_ratio + 1e-9]
    if start_ratio > 0.0:
        diffs = [oracle(a, b) if oracle is not None else None for a, b in zip(ratios, ratios[1:])]
    else:
        diffs = [None if math.isnan(d) else float(d) for d in s.difficulties]
    return s, ratios, diffs


# ---------------------------------------------------------------------------
# Snapshots and metrics
# ---------------------------------------------------------------------------
def scene_metrics(ctx: EditContext, gaussians, ratio: float) -> dict:
    """Numbers of one scene state at the held-out views.

    psnr/ssim_vs_target: renders vs the editor's noise-free target at r = 1 (None
    when the editor has no ground truth, e.g. a real diffusion model);
    psnr/ssim_vs_subtask_target: vs the target at this subtask's ratio;
    multiview_consistency: :func:`reprojection_consistency` of the renders (dB);
    num_gaussians.
    """
    rgb, alpha, depth = ctx.renderer.views(gaussians, ctx.data.test_cameras)
    out = {"ratio": float(ratio), "num_gaussians": int(gaussians.num_alive()),
           "multiview_consistency": reprojection_consistency(rgb, alpha, depth,
                                                             ctx.data.test_cameras)}
    target = getattr(ctx.editor, "target", None)
    if target is None:
        out.update(psnr_vs_target=None, ssim_vs_target=None)
        return out
    originals = ctx.data.test_images
    full = np.stack([target(o, 1.0, ctx.prompt) for o in originals])
    sc = image_scores(rgb, full)
    out.update(psnr_vs_target=sc["psnr"], ssim_vs_target=sc["ssim"])
    part = np.stack([target(o, ratio, ctx.prompt) for o in originals])
    sc = image_scores(rgb, part)
    out.update(psnr_vs_subtask_target=sc["psnr"], ssim_vs_subtask_target=sc["ssim"])
    return out


def write_scene_snapshot(ctx: EditContext, directory: Path, gaussians, *, ratio: float) -> dict:
    """scene.ply, renders/, depth/, (turntable.webp) and metrics.json of one scene state."""
    from .. import viz

    directory = Path(directory)
    viz.write_snapshot(directory, gaussians, ctx.data.test_cameras,
                       background=tuple(ctx.config.background),
                       turntable_frames=ctx.config.turntable_frames,
                       render_fn=lambda g, cam, **kw: ctx.renderer(g, cam))
    metrics = scene_metrics(ctx, gaussians, ratio)
    atomic_write_text(directory / "metrics.json", json.dumps(metrics, indent=2) + "\n")
    return metrics


def edit_fit(ctx: EditContext, st: DriverState) -> float:
    """PSNR (dB) of the final renders against the last edited training images.

    How well one 3D scene explains all the edited views: low when the edits
    disagree across views (the multi-view inconsistency the scene had to average).
    """
    g = ctx.trainer.gaussians(st.train)
    rgb = np.stack([ctx.renderer.rgb(g, ctx.data.train_cameras[i])
                    for i in range(len(st.images))])
    return image_scores(rgb, st.images)["psnr"]


# ---------------------------------------------------------------------------
# A whole run, with its run directory
# ---------------------------------------------------------------------------
def _plan_to_json(plan) -> list:
    return [dataclasses.asdict(p) for p in plan]


def _plan_from_json(items) -> tuple[SubtaskSpec, ...]:
    return tuple(SubtaskSpec(**p) for p in items)


def _snapshot_ratio(directory: Path) -> float:
    path = Path(directory) / "metrics.json"
    try:
        return float(json.loads(path.read_text())["ratio"])
    except FileNotFoundError:
        raise DataError(path, "not a snapshot directory of an edit run (no metrics.json)") from None
    except (KeyError, TypeError, ValueError) as e:
        raise DataError(path, f"malformed snapshot metrics ({e})") from None


def run_edit(editor, prompt: str, data: EditData, gaussians, *, config: ProEditConfig,
             settings: TrainSettings | None = None, seed: int = 0,
             run_dir: str | os.PathLike | None = None, resume: bool = False,
             resume_from: str | os.PathLike | None = None, select=None,
             callback: Callable | None = None, progress: Callable | None = None,
             report: bool = True, log: Callable[[str], None] | None = None,
             distance: Callable | None = None) -> dict:
    """Edit ``gaussians`` progressively (see the module docstring); returns the run summary.

    Args:
      editor, prompt: the 2D editor and the instruction.
      data: original photos and cameras (train views edited, test views held out).
      gaussians: the input scene (a reconstruction of ``data``).
      config / settings: driver and trainer knobs.
      seed: the run seed (every random draw derives from it).
      run_dir: where schedule.json, metrics.json, snapshots and the checkpoint go
        (None: in memory only, no files).
      resume: continue the run in ``run_dir`` from its checkpoint (exactly, in
        the deterministic mode).
      resume_from: a snapshot directory (``subtasks/NN_rX.XXX``) to continue from
        with this config's schedule (the ratios above the snapshot's).
      select: ratio (float) or subtask index (int) whose snapshot becomes
        ``run_dir/selected.ply``.
      callback: ``callback(spec, step, loss)`` after every training step.
      progress: ``progress(spec, step, loss, state)`` after every training step.
      distance: perceptual distance of the difficulty (default multi-scale SSIM; pass
        :func:`jaxedit.lpips.lpips_distance` for the paper's LPIPS).
    Returns:
      {"schedule": schedule.json contents, "metrics": metrics.json contents, "gaussians": final}.
    """
    log = log or (lambda msg: None)
    if not str(prompt).strip() and config.mode != "in2n":
        raise DataError("--prompt", "empty instruction")
    run_dir = None if run_dir is None else Path(run_dir)
    from ..train import scene_extent

    settings = settings or TrainSettings()
    if settings.scene_extent is None:
        # Rounded: the extent is a static field of the train state, and cameras that went
        # through a file differ in the last bits; equal rigs should share one compiled step.
        extent = float(f"{scene_extent(data.train_cameras):.4g}")
        settings = dataclasses.replace(settings, scene_extent=extent)
    settings = dataclasses.replace(settings, adaptive=config.mode != "in2n",
                                   warmup=config.warmup, background=tuple(config.background))
    settings = resolve_max_gaussians(settings, int(gaussians.num_alive()))
    trainer = SubtaskTrainer(settings)
    trainer_device, editor_device = pick_devices()
    ctx = EditContext(editor, prompt, data, config, trainer, Renderer(config.background),
                      jax.random.key(seed), editor_device)
    wall0 = time.perf_counter()
    ckpt = None if run_dir is None else run_dir / CHECKPOINT_NAME
    if resume and (ckpt is None or not ckpt.exists()):
        raise DataError(ckpt or "--out", "no checkpoint to resume from")

    if resume:
        st, meta = load_checkpoint(ckpt, trainer.init(gaussians))
        plan = _plan_from_json(meta["plan"])
        header = meta["header"]
        wall0 -= meta.get("wall_time_s", 0.0)
        log(f"resuming subtask {st.subtask} at step {st.step} from {ckpt}")
    else:
        start_ratio, start_scene, images = 0.0, gaussians, None
        if resume_from is not None:
            from ..io import load_ply

            snap = Path(resume_from)
            start_ratio = _snapshot_ratio(snap)
            start_scene = load_ply(snap / "scene.ply")
            # The dataset the snapshot was trained on is best approximated by its renders.
            images = np.stack([ctx.renderer.rgb(start_scene, data.train_cameras[i])
                               for i in range(len(data.train_images))])
            log(f"continuing from {snap} (r = {start_ratio:.3f})")
        originals = np.stack([ctx.renderer.rgb(gaussians, data.train_cameras[i])
                              for i in range(len(data.train_images))])
        oracle = (None if config.mode == "in2n"
                  else difficulty_oracle(ctx, originals, seed, distance))
        if oracle is not None:
            log(f"difficulty distance: {distance_name(distance)}")
        schedule, ratios, diffs = make_schedule(ctx, oracle, start_ratio=start_ratio)
        resumed = resume_from is not None
        if start_ratio >= 1.0 - 1e-9:
            ratios, diffs = [1.0], []
        plan = (plan_subtasks(config.mode, ratios, diffs, start_ratio=start_ratio,
                              refine_first=config.refine_first and not resumed,
                              consolidate=config.consolidate)
                if len(ratios) > 1 or config.mode == "in2n" else
                plan_subtasks("proedit", [0.0, 1.0], [None], refine_first=False,
                              consolidate=config.consolidate)[-1:])
        curve = []
        if oracle is not None:
            grid = np.linspace(0.0, 1.0, max(config.curve_points, 2))
            curve = [[r, d] for r, d in oracle.curve(sorted(set(map(float, grid)) | set(ratios)))]
        if schedule.depth_limit_hit:
            log(f"WARNING: the scheduler hit its depth limit (max_depth {config.max_depth}, at "
                f"most {2 ** config.max_depth} subtasks): some subtask is harder than the "
                f"threshold {schedule.threshold:.4g}")
        if schedule.target_subtasks is not None:
            log(f"threshold {schedule.threshold:.4g} gives {schedule.num_subtasks} subtasks "
                f"(target {schedule.target_subtasks})")
        header = {"prompt": prompt, "editor": getattr(editor, "name", type(editor).__name__),
                  "mode": config.mode, "threshold": schedule.threshold,
                  "target_subtasks": schedule.target_subtasks,
                  "difficulty": None if oracle is None else {
                      "distance": distance_name(distance),
                      "reduction": "mean over views (paper eq. 3's sum / |V|; the threshold "
                                   "is per view)",
                      "views": list(oracle.views), "num_views": len(oracle.views),
                      "of_training_views": len(data.train_images)},
                  "schedule_method": schedule.method, "depth_limit_hit": schedule.depth_limit_hit,
                  "difficulty_evaluations": schedule.evaluations,
                  "editor_calls_for_schedule": getattr(oracle, "editor_calls", 0),
                  "difficulty_curve": curve, "seed": seed,
                  "distance": None if oracle is None else distance_name(distance),
                  "resumed_from": None if resume_from is None else str(resume_from),
                  "start_ratio": start_ratio, "asynchronous": config.asynchronous,
                  "config": {k: v for k, v in dataclasses.asdict(config).items()}}
        st = initial_state(ctx, start_scene, images)
        if run_dir is not None:
            write_scene_snapshot(ctx, run_dir / "original", gaussians, ratio=0.0)

    def schedule_json(records) -> dict:
        done = {r["index"] for r in records}
        pending = [{"index": p.index, "name": p.name, "ratio": p.ratio, "difficulty": p.difficulty,
                    "kind": p.kind, "steps": None, "seconds": None, "converged": None,
                    "snapshot": None} for p in plan if p.index not in done]
        return {**header, "subtasks": list(records) + pending}

    def meta() -> dict:
        return {"plan": _plan_to_json(plan), "header": header,
                "wall_time_s": time.perf_counter() - wall0}

    def save(state):
        if ckpt is not None:
            save_checkpoint(ckpt, state, meta())

    if run_dir is not None:
        atomic_write_text(run_dir / "schedule.json", json.dumps(schedule_json(st.records), indent=2) + "\n")
        save(st)

    for spec in plan[st.subtask:]:
        log(f"subtask {spec.index} {spec.name} ({spec.kind}) r = {spec.ratio:.3f}")
        st, info = run_subtask(ctx, st, spec, callback=callback, checkpoint=save,
                               progress=progress)
        g = trainer.gaussians(st.train)
        record = {"index": spec.index, "name": spec.name, "kind": spec.kind, "ratio": spec.ratio,
                  "difficulty": spec.difficulty, "steps": info["steps"],
                  "seconds": info["seconds"], "converged": info["converged"],
                  "num_gaussians": int(g.num_alive()), "snapshot": None, "metrics": None}
        if not info["converged"]:
            log(f"subtask {spec.name}: max_steps guard ({config.max_steps}) fired before the "
                f"loss plateaued")
        if run_dir is not None:
            rel = Path("subtasks") / spec.dirname
            record["metrics"] = write_scene_snapshot(ctx, run_dir / rel, g, ratio=spec.ratio)
            record["snapshot"] = str(rel / "scene.ply")
        st.records = st.records + [record]
        st.subtask += 1
        st.step = 0
        st.seconds = 0.0
        if run_dir is not None:
            atomic_write_text(run_dir / "schedule.json",
                              json.dumps(schedule_json(st.records), indent=2) + "\n")
            save(st)

    final = trainer.gaussians(st.train)
    metrics = scene_metrics(ctx, final, 1.0 if plan else 0.0)
    metrics.update(edit_fit_psnr=edit_fit(ctx, st), wall_time_s=time.perf_counter() - wall0,
                   total_steps=int(sum(r["steps"] for r in st.records)),
                   subtasks=len(st.records),
                   all_converged=bool(all(r["converged"] for r in st.records)),
                   utilisation=st.utilisation.as_dict(), mode=config.mode,
                   asynchronous=config.asynchronous)
    sched_json = schedule_json(st.records)
    if run_dir is not None:
        atomic_write_text(run_dir / "metrics.json", json.dumps(metrics, indent=2) + "\n")
        if select is not None:
            select_snapshot(run_dir, select)
        if report:
            try:
                from ..report import write_report
            except ImportError:
                log("jaxedit.report unavailable: no report.html")
            else:
                write_report(run_dir)
    return {"schedule": sched_json, "metrics": metrics, "gaussians": final}


def select_snapshot(run_dir: str | os.PathLike, which) -> Path:
    """Make ``run_dir/selected.ply`` the snapshot of a subtask, chosen by ratio or index.

    ``which``: an int (subtask index, negative counts from the end) or a float
    ratio (the last subtask with the nearest ratio; a string is parsed: "2" is
    an index, "0.5" a ratio). Also writes ``selected.json``. Returns the path.
    """
    run_dir = Path(run_dir)
    path = run_dir / "schedule.json"
    try:
        subtasks = [s for s in json.loads(path.read_text())["subtasks"] if s.get("snapshot")]
    except FileNotFoundError:
        raise DataError(path, "no schedule.json: not an edit run directory") from None
    except (KeyError, ValueError) as e:
        raise DataError(path, f"malformed schedule ({e})") from None
    if not subtasks:
        raise DataError(path, "no finished subtask to select")
    if isinstance(which, str):
        try:
            which = int(which) if which.lstrip("-").isdigit() else float(which)
        except ValueError:
            raise DataError("--select", f"expected a subtask index or a ratio, got {which!r}") from None
    if isinstance(which, (int, np.integer)) and not isinstance(which, bool):
        by_index = {s["index"]: s for s in subtasks}
        idx = int(which) if which >= 0 else subtasks[int(which)]["index"] if -len(subtasks) <= which else None
        if idx not in by_index:
            raise DataError("--select", f"no finished subtask {which}; have "
                                        f"{sorted(by_index)}")
        chosen = by_index[idx]
    else:
        r = float(which)
        if not 0.0 <= r <= 1.0:
            raise DataError("--select", f"ratio must be in [0, 1], got {r}")
        best = min(abs(s["ratio"] - r) for s in subtasks)
        chosen = [s for s in subtasks if abs(s["ratio"] - r) == best][-1]
    src = run_dir / chosen["snapshot"]
    dst = run_dir / "selected.ply"
    with atomic_path(dst) as tmp:
        shutil.copyfile(src, tmp)
    atomic_write_text(run_dir / "selected.json",
                      json.dumps({"index": chosen["index"], "name": chosen["name"],
                                  "ratio": chosen["ratio"], "snapshot": chosen["snapshot"]},
                                 indent=2) + "\n")
    return dst
