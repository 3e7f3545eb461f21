"""The report's matplotlib plots, each as a PNG data URI."""

from __future__ import annotations

import numpy as np

from .images import _figure_uri
from .rundir import _is_number


def difficulty_plot(schedule: dict) -> str:
    """PNG data URI: d(0, r) with the chosen ratios, and each subtask's difficulty."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    curve = sorted((float(r), float(d)) for r, d in (schedule.get("difficulty_curve") or [])
                   if r is not None and d is not None)
    subtasks = schedule.get("subtasks", [])
    ratios = [float(s["ratio"]) for s in subtasks]
    threshold = schedule.get("threshold")
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(10, 3.4), gridspec_kw={"width_ratios": [3, 2]})
    if curve:
        rs, ds = np.array(curve).T
        ax0.plot(rs, ds, "-", color="#555555", lw=1.5, label="d(0, r) measured", zorder=1)
        ax0.plot(rs, ds, ".", color="#555555", ms=5, zorder=1)
        marks = np.interp(ratios, rs, ds) if ratios else []
        ax0.scatter(ratios, marks, s=55, color="#d62728", zorder=3, label="chosen ratios r_i")
        # One label per distinct ratio (r_n repeats r = 1 to consolidate).
        groups: dict[float, list[str]] = {}
        for s, r, d in zip(subtasks, ratios, marks):
            groups.setdefault(round(r, 6), []).append(str(s.get("name", "")))
        for r, names_at in groups.items():
            ax0.annotate(", ".join(names_at), (r, float(np.interp(r, rs, ds))),
                         textcoords="offset points", xytext=(-4 if r > 0.9 else 0, 7),
                         ha="right" if r > 0.9 else "center", fontsize=8)
    else:
        ax0.text(0.5, 0.5, "no difficulty curve recorded\n(uniform or single-subtask schedule)",
                 ha="center", va="center", transform=ax0.transAxes, color="#777777")
    for r in ratios:
        ax0.axvline(r, color="#d62728", ls=":", lw=0.8, zorder=0)
    ax0.set_xlim(-0.02, 1.02)
    ax0.set_xlabel("ratio r")
    ax0.set_ylabel("difficulty $d(0, r)$")
    ax0.set_title("Difficulty of reaching r from the original")
    if curve:
        ax0.legend(loc="upper left", fontsize=8)
    diffs = [s.get("difficulty") for s in subtasks]
    names = [str(s.get("name", i)) for i, s in enumerate(subtasks)]
    xs = np.arange(len(subtasks))
    ax1.bar(xs, [d if d is not None else 0.0 for d in diffs],
            color=["#1f77b4" if d is not None else "#cccccc" for d in diffs])
    if threshold is not None:
        ax1.axhline(float(threshold), color="#d62728", ls="--", lw=1, label=f"threshold {threshold:g}")
        ax1.legend(loc="best", fontsize=8)
    ax1.set_xticks(xs, names, rotation=45 if len(xs) > 6 else 0, fontsize=8)
    ax1.set_ylabel("$d(r_{i-1}, r_i)$")
    ax1.set_title("Difficulty of each subtask")
    fig.tight_layout()
    return _figure_uri(fig)


def tree_plot(branches: list[dict], threshold) -> str:
    """PNG data URI: each branch's steps as d(r_{i-1}, r_i) at r_i, one line a branch, the
    threshold dashed. ``branches``: [{"name", "start_ratio", "steps": [(r, d)]}]."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.2))
    for b in branches:
        steps = [(float(r), float(d)) for r, d in b["steps"] if d is not None]
        if steps:
            rs, ds = np.array(steps).T
            ax.plot(rs, ds, "o-", ms=4, lw=1.2, label=str(b["name"]))
    if threshold is not None:
        ax.axhline(float(threshold), color="#d62728", ls="--", lw=1, label=f"threshold {threshold:g}")
    ax.set_xlabel("ratio r (on the branch's path)")
    ax.set_ylabel("$d(r_{i-1}, r_i)$")
    ax.set_title("Difficulty of each branch's steps")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    return _figure_uri(fig)


def training_plot(records: list[dict]) -> str | None:
    """PNG data URI: loss, PSNR and Gaussian count over the training steps."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    keys = [k for k in ("loss", "psnr", "num_gaussians")
            if any(_is_number(r.get(k)) for r in records)]
    if not keys or not any(_is_number(r.get("step")) for r in records):
        return None
    fig, axes = plt.subplots(1, len(keys), figsize=(3.6 * len(keys), 2.8), squeeze=False)
    for ax, k in zip(axes[0], keys):
        pts = [(r["step"], r[k]) for r in records if _is_number(r.get("step")) and _is_number(r.get(k))]
        xs, ys = zip(*pts)
        ax.plot(xs, ys, lw=1.2, color="#1f77b4")
        ax.set_xlabel("step")
        ax.set_title({"loss": "training loss", "psnr": "training PSNR (dB)",
                      "num_gaussians": "Gaussians"}[k], fontsize=10)
        if k == "loss" and min(ys) > 0:
            ax.set_yscale("log")
    fig.tight_layout()
    return _figure_uri(fig)
