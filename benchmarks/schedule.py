"""Subtask scheduling: the paper's bisection + pruning vs root placement vs uniform.

For synthetic difficulty functions d(a, b) = |F(b) - F(a)| (+ noise) and for the simulated
editor on crops of skimage's astronaut, record per method: number of subtasks, difficulty
evaluations, editor calls (distinct ratios x views: each ratio is edited once per view), the
spread of the adjacent difficulties (min, max, coefficient of variation) and wall time.

    python benchmarks/schedule.py [--smoke] [--out DIR]     -> DIR/schedule.json
"""

from __future__ import annotations

import math
import time

import numpy as np

from common import parse_args, peak_rss_mb, write_json


class CountingDifficulty:
    """A synthetic d(a, b) = |F(b) - F(a)| + noise that counts distinct ratios (views = 1)."""

    def __init__(self, F, noise: float = 0.0):
        self.F, self.noise, self.ratios = F, noise, set()

    def __call__(self, a, b):
        self.ratios.update((a, b))
        if a == b:
            return 0.0
        lo, hi = min(a, b), max(a, b)
        return abs(self.F(b) - self.F(a)) + self.noise * abs(math.sin(997.0 * lo + 131.0 * hi))

    @property
    def editor_calls(self):
        return len(self.ratios)


SYNTHETIC = {
    "linear": lambda r: r,
    "quadratic": lambda r: r * r,
    "logistic": lambda r: 1 / (1 + math.exp(-12 * (r - 0.6))),
    "ramp+step": lambda r: 0.6 * r + (0.3 if r > 0.45 else 0.0),
}


def methods(max_depth: int):
    from jaxedit.edit.schedule import decompose, decompose_root

    return {
        "bisection": lambda d, thr: decompose(d, threshold=thr, max_depth=max_depth),
        f"root@2^-{max_depth}": lambda d, thr: decompose_root(d, threshold=thr,
                                                              resolution=2.0 ** -max_depth),
        "root@2^-8": lambda d, thr: decompose_root(d, threshold=thr, resolution=2.0 ** -8),
        "root@2^-8,b0": lambda d, thr: decompose_root(d, threshold=thr, resolution=2.0 ** -8,
                                                      balance=0),
    }


def record(schedule, editor_calls, seconds):
    from jaxedit.edit.schedule import spread

    return {"subtasks": schedule.num_subtasks, "evaluations": schedule.evaluations,
            "editor_calls": editor_calls, "depth_limit_hit": schedule.depth_limit_hit,
            "seconds": round(seconds, 4), **{f"d_{k}": v for k, v in spread(schedule).items()},
            "ratios": [round(r, 6) for r in schedule.ratios]}


def astronaut_views(count: int, size: int) -> np.ndarray:
    """``count`` overlapping crops of the astronaut, like views of a panning camera."""
    import skimage.data
    import skimage.transform

    img = skimage.data.astronaut()
    views = []
    for k in range(count):
        x0 = 60 + 40 * k
        crop = img[10:330, x0:x0 + 320]
        views.append(skimage.transform.resize(crop, (size, size), anti_aliasing=True))
    return np.asarray(views, np.float32)


def main(argv=None):
    args = parse_args(__doc__.splitlines()[0], argv)
    from jaxedit.edit.difficulty import DifficultyOracle
    from jaxedit.edit.schedule import uniform
    from jaxedit_lab.simulated import SimulatedEditor

    max_depth = 5 if args.smoke else 6
    thresholds = (0.25, 0.1) if args.smoke else (0.3, 0.15, 0.08)
    synthetic = {}
    for name, F in SYNTHETIC.items():
        for noise in ((0.0,) if args.smoke else (0.0, 0.02)):
            for thr in thresholds:
                row = {}
                for mname, fn in methods(max_depth).items():
                    d = CountingDifficulty(F, noise)
                    t0 = time.perf_counter()
                    s = fn(d, thr)
                    row[mname] = record(s, d.editor_calls, time.perf_counter() - t0)
                synthetic[f"{name} noise={noise} thr={thr}"] = row

    editor = SimulatedEditor()
    size, nviews = (32, 2) if args.smoke else (64, 4)
    views = astronaut_views(nviews, size)
    prompts = editor.instructions[:2] if args.smoke else editor.instructions
    editor_rows = {}
    for prompt in prompts:
        probe = DifficultyOracle(editor, views, prompt)
        full = probe(0.0, 1.0)
        # the paper: ~4 subtasks for texture edits, ~8 for geometry; thresholds relative to d(0, 1)
        for frac in ((0.3,) if args.smoke else (0.3, 0.15)):
            thr = frac * full
            row = {"d(0,1)": full}
            for mname, fn in methods(max_depth).items():
                oracle = DifficultyOracle(editor, views, prompt)
                t0 = time.perf_counter()
                s = fn(oracle, thr)
                row[mname] = record(s, oracle.editor_calls, time.perf_counter() - t0)
            oracle = DifficultyOracle(editor, views, prompt)
            n = row["bisection"]["subtasks"]
            t0 = time.perf_counter()
            row[f"uniform({n})"] = record(uniform(n, oracle), oracle.editor_calls,
                                          time.perf_counter() - t0)
            editor_rows[f"{prompt!r} thr={frac}*d(0,1)"] = row

    print(f"{'case':58s} {'method':12s} {'n':>3s} {'calls':>6s} {'evals':>6s} {'d_max':>7s} "
          f"{'d_cv':>6s} {'sec':>7s}")
    for table in (synthetic, editor_rows):
        for case, row in table.items():
            for mname, rec in row.items():
                if not isinstance(rec, dict):
                    continue
                print(f"{case[:58]:58s} {mname:12s} {rec['subtasks']:3d} {rec['editor_calls']:6d} "
                      f"{rec['evaluations']:6d} {rec['d_max']:7.3f} {rec['d_cv']:6.3f} "
                      f"{rec['seconds']:7.2f}")
    write_json(args.out, "schedule", {
        "smoke": args.smoke, "max_depth": max_depth,
        "note": "editor_calls: synthetic = distinct ratios (1 view); simulated editor = "
                "distinct (ratio, view) pairs. Timings on a shared, noisy CPU.",
        "synthetic": synthetic, "simulated_editor": {"views": nviews, "size": size,
                                                     "cases": editor_rows},
        "peak_rss_mb": peak_rss_mb()})


if __name__ == "__main__":
    main()
