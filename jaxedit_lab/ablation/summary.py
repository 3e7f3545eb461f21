"""The ablation's statistics: per-seed values, means with Student-t 95% CIs, paired
differences ProEdit - other, and their Markdown tables (pure functions of the run records).

Records are paired by (scene, instruction, seed) within an editor variant. The reference
levels (:data:`REFERENCES`, one record per scene and instruction, ``seed`` -1) do not depend
on the seed: :func:`expand_references` copies them to every seed, so they appear as rows
with the same value for each seed and ProEdit - reference as a paired difference (its
interval is ProEdit's own spread)."""

from __future__ import annotations

from jaxedit.metrics import mean_ci, paired_differences
from jaxedit_lab.ablation.methods import METHODS
from jaxedit_lab.ablation.report import ablation_table

#: The reference levels: the unedited reconstruction and the ceiling (a scene trained
#: directly on one outcome's targets).
REFERENCES = ("unedited", "ceiling")
#: Metrics summarised with confidence intervals.
METRICS = ("psnr_best", "ssim_best", "mode_mixing", "outcome_agreement", "agreement_final",
           "multiview_consistency", "psnr_vs_target", "plateau_share", "total_steps",
           "editor_calls", "hottest_calls", "sweeps", "initial_sweeps", "resets",
           "guard_ended", "maintenance", "cpu_seconds")


def expand_references(runs: list[dict]) -> list[dict]:
    """``runs`` with every reference record (``seed`` -1) copied to each seed its (variant,
    scene, instruction) has among the method runs (references with no runs are dropped)."""
    out = [r for r in runs if not r.get("reference")]
    seeds: dict[tuple, set] = {}
    for r in out:
        seeds.setdefault((r["editor_modes"], r["scene"], r["prompt"]), set()).add(r["seed"])
    for r in runs:
        if r.get("reference"):
            for seed in sorted(seeds.get((r["editor_modes"], r["scene"], r["prompt"]), ())):
                out.append(dict(r, seed=seed))
    return out
#: The ``prompt`` of the rows that average the instructions per seed first.
ALL = "all"


def _values(runs, *, prompts, method, metric, seeds) -> list[float] | None:
    """Per-seed values of one scene and editor setting, averaged over ``prompts`` (one prompt,
    or the complete ones for "all"); None if a seed lacks any of them."""
    out = []
    for seed in seeds:
        vals = [r[metric] for r in runs if r["method"] == method and r["seed"] == seed
                and r["prompt"] in prompts and r.get(metric) is not None]
        if len(vals) != len(prompts):
            return None
        out.append(sum(vals) / len(vals))
    return out


def summarise(runs: list[dict]) -> tuple[list[dict], list[dict]]:
    """(summary rows, paired-difference rows) of the run records; see the module docstring."""
    summary, differences = [], []
    runs = expand_references(runs)
    groups = sorted({(r["editor_modes"], r["scene"]) for r in runs})
    for modes, scene in groups:
        mine = [r for r in runs if r["editor_modes"] == modes and r["scene"] == scene]
        prompts = list(dict.fromkeys(r["prompt"] for r in mine))
        methods = [m for m in METHODS + REFERENCES if any(r["method"] == m for r in mine)]
        seeds = sorted({r["seed"] for r in mine})
        # An interrupted run has a partial last instruction: each row uses the seeds that
        # every method finished (so differences stay paired), "all" the complete instructions.
        done = {(r["prompt"], r["seed"]) for r in mine
                if all(any(q["prompt"] == r["prompt"] and q["seed"] == r["seed"]
                           and q["method"] == m for q in mine) for m in methods)}
        finished = {p: [sd for sd in seeds if (p, sd) in done] for p in prompts}
        complete = [p for p in prompts if len(finished[p]) == len(seeds)]
        for prompt in prompts + ([ALL] if len(complete) > 1 else []):
            over = complete if prompt == ALL else [prompt]
            use = seeds if prompt == ALL else finished[prompt]
            if not use:
                continue
            for metric in METRICS:
                base = None
                for method in methods:
                    vals = _values(mine, prompts=over, method=method, metric=metric, seeds=use)
                    if vals is None:
                        continue
                    key = {"editor_modes": modes, "scene": scene, "prompt": prompt,
                           "method": method, "metric": metric}
                    summary.append(key | mean_ci(vals))
                    if method == "proedit":
                        base = vals
                    elif base is not None:
                        differences.append(key | paired_differences(base, vals))
    return summary, differences


def tables(summary: list[dict], differences: list[dict], *,
           metrics=("psnr_best", "outcome_agreement", "mode_mixing", "plateau_share",
                    "editor_calls", "hottest_calls")) -> str:
    """Markdown: per editor-modes setting and metric, (scene, instruction) x methods with
    mean ± 95% CI, then the paired differences proedit - other (``*``: CI excludes 0)."""
    text = []
    for modes in sorted({r["editor_modes"] for r in summary}):
        for metric in metrics:
            digits = 3 if metric.startswith(("ssim", "mode", "outcome", "plateau")) else 2
            header, rows = ablation_table(summary, differences, editor_modes=modes,
                                          metric=metric, digits=digits)
            text.append(f"\n### editor modes = {modes}: {metric} (mean ± 95% CI over seeds)\n")
            text.append("| " + " | ".join(header) + " |")
            text.append("|" + "---|" * len(header))
            text += ["| " + " | ".join(row) + " |" for row in rows]
    text.append("\n`*`: the 95% CI of the paired difference excludes 0.")
    return "\n".join(text) + "\n"
