"""The ablation run's page: its sections, table, plot and note, plugged into the library's
``write_report`` through its ``sections`` seam."""

from __future__ import annotations

import functools
from pathlib import Path

from jaxedit.errors import DataError
from jaxedit.pipelines.report import (escape, figure_uri, image_uri, img, is_number, kv_table,
                                      load_thumb, read_json, reproduce, table, write_report)

#: The methods in the order of the tables and the plot.
ABLATION_METHODS = ("proedit", "nd", "nd_equal", "nd_replay", "nd_k", "uniform", "in2n",
                    "nd_equal_steps", "unedited", "ceiling")
_METHOD_COLOURS = {"proedit": "#d62728", "nd": "#1f77b4", "nd_equal": "#2ca02c",
                   "nd_k": "#17becf", "uniform": "#ff7f0e", "in2n": "#9467bd",
                   "nd_equal_steps": "#8c564b"}


def _summary_index(rows: list[dict]) -> dict:
    return {(r["editor_modes"], r["scene"], r["prompt"], r["method"], r["metric"]): r
            for r in rows}


def ablation_plot(summary: list[dict], *, metrics=("psnr_best", "mode_mixing")) -> str | None:
    """PNG data URI: each method's mean and CI per editor-modes setting (rows) and metric."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    index = _summary_index(summary)
    modes = sorted({r["editor_modes"] for r in summary})
    metrics = [m for m in metrics if any(r["metric"] == m for r in summary)]
    if not modes or not metrics:
        return None
    groups = list(dict.fromkeys((r["scene"], r["prompt"]) for r in summary))
    methods = [m for m in ABLATION_METHODS if any(r["method"] == m for r in summary)]
    fig, axes = plt.subplots(len(modes), len(metrics), squeeze=False,
                             figsize=(max(8.0, 0.55 * len(groups) * len(metrics) + 3),
                                      2.9 * len(modes)))
    width = 0.8 / max(len(methods), 1)
    for i, k in enumerate(modes):
        for j, metric in enumerate(metrics):
            ax = axes[i][j]
            for n, method in enumerate(methods):
                xs, ys, es = [], [], []
                for g, (scene, prompt) in enumerate(groups):
                    r = index.get((k, scene, prompt, method, metric))
                    if r is not None:
                        xs.append(g + (n - (len(methods) - 1) / 2) * width)
                        ys.append(r["mean"])
                        es.append(r["ci"] or 0.0)
                ax.errorbar(xs, ys, yerr=es, fmt="o", ms=4, capsize=2, lw=1,
                            color=_METHOD_COLOURS.get(method, "#555555"), label=method)
            ax.set_xticks(range(len(groups)),
                          [f"{sc}: {pr[:18]}" for sc, pr in groups], rotation=40, ha="right",
                          fontsize=7)
            ax.set_title(f"editor modes = {k}: {metric}", fontsize=9)
            ax.set_ylabel("0: one mode, 1: even blend" if metric == "mode_mixing"
                          else "higher is better", fontsize=8)
            ax.tick_params(axis="y", labelsize=8)
            for g in range(1, len(groups)):
                ax.axvline(g - 0.5, color="#eeeeee", lw=0.8, zorder=0)
    axes[0][0].legend(fontsize=7, loc="best")
    fig.tight_layout()
    return figure_uri(fig)


def ablation_table(summary: list[dict], differences: list[dict], *, editor_modes: int,
                   metric: str, digits: int = 2) -> tuple[list[str], list[list[str]]]:
    """(header, rows) of plain-text cells: one row per (scene, instruction), the mean ± 95% CI
    of every method, then the paired difference proedit - other (``*``: its CI excludes 0)."""
    index, dindex = _summary_index(summary), _summary_index(differences)
    groups = list(dict.fromkeys((r["scene"], r["prompt"]) for r in summary
                                if r["editor_modes"] == editor_modes))
    methods = [m for m in ABLATION_METHODS
               if (editor_modes, *groups[0], m, metric) in index] if groups else []
    others = [m for m in methods if m != "proedit"]

    def cell(r, mark=False):
        if r is None:
            return "-"
        ci = "" if r["ci"] is None else f" ± {r['ci']:.{digits}f}"
        sig = mark and r["ci"] is not None and abs(r["mean"]) > r["ci"]
        return f"{r['mean']:.{digits}f}{ci}" + (" *" if sig else "")

    header = ["scene", "instruction"] + methods + [f"proedit − {m}" for m in others]
    rows = [[scene, prompt] + [cell(index.get((editor_modes, scene, prompt, m, metric)))
                               for m in methods]
            + [cell(dindex.get((editor_modes, scene, prompt, m, metric)), True) for m in others]
            for scene, prompt in groups]
    return header, rows


#: What the simulated ablation can and cannot show (shown on every ablation page).
SIMULATION_NOTE = (
    "The editor here is jaxedit's simulated editor, a test instrument with known noise-free "
    "targets, not InstructPix2Pix. With <b>editor modes = 1</b> each instruction has one "
    "outcome and views differ only by noise that shrinks as the render approaches the target; "
    "with <b>editor modes = K &gt; 1</b> each edit call draws one of K discrete, individually "
    "3D-consistent outcomes, with probabilities that follow how close the current render is "
    "to each (jaxedit_lab.simulated, section 4). The ablation therefore tests how the editing "
    "machinery (schedule, iterative dataset update, adaptive 3DGS) responds to divergent modes "
    "of a known size. It cannot show how large a real diffusion model's feasible output space "
    "is, how its modes are distributed, or how the difficulty measure tracks them; scores are "
    "against the simulated targets only, on small CPU-sized scenes.")


def ablation_sections(run_dir: Path, ablation: dict, *, thumb_px: int, max_views: int,
                      turntable_px: int, max_frames: int) -> list[tuple[str, str, str]]:
    """[(anchor, title, html)] of an ablation run directory with its parsed ``ablation.json``
    ({settings, runs, summary, differences}, views/*.png); DataError when malformed."""
    path = run_dir / "ablation.json"
    if not (isinstance(ablation, dict) and isinstance(ablation.get("runs"), list)
            and isinstance(ablation.get("summary", []), list)
            and isinstance(ablation.get("differences", []), list)):
        raise DataError(path, "must be an object {settings, runs: [...], summary: [...], "
                              "differences: [...]} (python -m experiments ablation)")
    need = ("editor_modes", "scene", "prompt", "method", "metric", "mean", "ci")
    for name in ("summary", "differences"):
        for i, r in enumerate(ablation.get(name, [])):
            if not isinstance(r, dict) or any(k not in r for k in need) \
                    or not is_number(r["mean"]) or not (r["ci"] is None or is_number(r["ci"])):
                raise DataError(path, f"{name}[{i}] needs {', '.join(need)} (numbers for "
                                      f"mean and ci)")
    summary, differences = ablation.get("summary", []), ablation.get("differences", [])
    settings = ablation.get("settings") or {}
    config = read_json(run_dir / "config.json", required=False)
    note = SIMULATION_NOTE if settings.get("editor", "simulated") == "simulated" else (
        f"The editor here is {escape(str(settings.get('editor')))}; outcomes are its "
        "instructions' outcome targets (jaxedit_lab.ablation.outcomes).")
    body = (f"<p>{note}</p><p>{len(ablation['runs'])} edit runs; means and "
            "Student-t 95% confidence intervals over seeds; differences are paired by seed "
            "(proedit minus the other method); &ldquo;all&rdquo; averages the instructions of "
            "a seed first.</p>" + reproduce(config))
    if settings:
        body += "<h3>Settings</h3>" + kv_table(settings)
    sections = [("instruction", "Ablation", body)]
    if not summary:
        sections.append(("metrics", "Statistics", '<p class="missing">no summary yet (the run '
                                                  "has not finished)</p>"))
        return sections

    body = ""
    for k in sorted({r["editor_modes"] for r in summary}):
        for metric, digits in (("psnr_best", 2), ("ssim_best", 3), ("outcome_agreement", 3),
                               ("mode_mixing", 3), ("plateau_share", 3),
                               ("multiview_consistency", 2), ("total_steps", 0)):
            header, rows = ablation_table(summary, differences, editor_modes=k, metric=metric,
                                          digits=digits)
            if not rows or len(header) <= 2:
                continue
            body += (f"<h3>editor modes = {k}: {escape(metric)}</h3>"
                     + table([escape(h) for h in header],
                             [[escape(c) for c in row] for row in rows], "ablation"))
    body += ("<p>psnr_best / ssim_best: best over modes of the per-scene score against that "
             "mode's noise-free target at r = 1 (higher is better); mode_mixing: 0 when the "
             "result is one mode, 1 for an even blend of all; multiview_consistency: "
             "reprojection PSNR between neighbouring test views (dB). <b>*</b>: the 95% CI of "
             "the paired difference excludes 0.</p>")
    plot = ablation_plot(summary)
    if plot:
        body += img(plot, "means and 95% CIs per method", "plot")
    sections.append(("metrics", "Statistics", body))

    views = sorted((run_dir / "views").glob("*.png")) if (run_dir / "views").is_dir() else []
    if views:
        methods = settings.get("methods") or list(ABLATION_METHODS)
        rows = [[f"<b>{escape(p.stem)}</b>",
                 img(image_uri(load_thumb(p, 6 * thumb_px)), p.stem)] for p in views]
        body = (f"<p>Seed 0, test views. Rows of each image: the noise-free target of every "
                f"mode at r = 1, then the final scene of {escape(', '.join(methods))}.</p>"
                + table(["run", "targets, then methods"], rows, "compare"))
        sections.append(("compare", "Views", body))
    return sections


def write_ablation_report(run_dir, *, title: str | None = None, **kwargs) -> Path:
    """Write ``report.html`` of an ablation run directory (``ablation.json``, from
    ``python -m experiments ablation``); ``kwargs`` as the library's ``write_report``."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise DataError(run_dir, "run directory does not exist")
    ablation = read_json(run_dir / "ablation.json")
    return write_report(run_dir, title=title or f"jaxedit ablation: {run_dir.name}",
                        sections=functools.partial(ablation_sections, ablation=ablation),
                        **kwargs)
