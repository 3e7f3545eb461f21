"""The pre-registered mechanism test (``docs/mechanism-preregistration.md``), computed from the
per-edit logs of an ablation's ``runs.jsonl``.

Every figure here is the one the pre-registration defines, from a record's ``edit_outcomes``
(the training edits in order: ``subtask``, ``step``, ``view``, ``ratio``, ``outcome``) only:

* a **sweep**: an exchange (one subtask and step) that edited every training view; a
  subtask's *initial* sweep is its first. Its **split** is 1 - the share of its
  outcome-classed edits in its most common outcome, undefined (None) when fewer than half of
  its edits are classed to an outcome;
* a run's **early split**: the split of its first edit subtask's (ratio > 0) initial sweep
  whose split is defined;
* its **edit consistency**: the share of its outcome-classed edits, from that sweep on, in
  the run's most common outcome (over the same edits);
* its **keep rate**: over consecutive outcome-classed edits of the same view, the share
  whose outcome equals the previous one (pooled over the run's views).

:func:`study` then makes the registered contrasts (ProEdit minus a control, paired by seed:
Student-t intervals with a Wilcoxon signed-rank test beside each, Holm over the primary
family) and says for each prediction whether it held, was refuted, was not shown, or could not
be tested, with the reason.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from typing import Iterable, Sequence

import numpy as np

from jaxedit_lab.outcome_class import OTHER, UNEDITED
from jaxedit.metrics import paired_differences, percentile_interval

#: The controls of M (primary family), and the scheduler's comparison (P4).
CONTROLS = ("nd_k", "nd_equal")
UNIFORM = "uniform"
LEAD = "proedit"
#: A control's edits "split" in a seed when its early split is at least this...
SPLIT = 0.25
#: ...and M can only be tested where they do in at least this many seeds.
MIN_SPLIT_SEEDS = 5
#: Not testable: the reconstruction's held-out PSNR below this (dB).
MIN_RECON_PSNR = 25.0
#: Not testable: more than this share of every method's training edits "other" or "unedited".
MAX_UNSEEN = 0.5
BOOTSTRAP = 10_000
LEVEL = 0.95


def _is_outcome(label) -> bool:
    return isinstance(label, (int, np.integer)) and not isinstance(label, bool)


def sweeps(log: Sequence[dict], views: int) -> list[tuple[int, int, list]]:
    """The initial sweep of every subtask that has one: ``(subtask, step, its edits)`` in order.

    Args:
      log: a record's ``edit_outcomes``.
      views: the number of training views (a sweep edits every one of them at one step).
    """
    groups: dict[tuple[int, int], list] = defaultdict(list)
    for e in log:
        groups[(e["subtask"], e["step"])].append(e)
    first: dict[int, tuple[int, int, list]] = {}
    for (subtask, step), edits in sorted(groups.items()):
        if len({e["view"] for e in edits}) >= views and subtask not in first:
            first[subtask] = (subtask, step, edits)
    return [first[s] for s in sorted(first)]


def split(edits: Sequence[dict]) -> float | None:
    """1 - the share of the outcome-classed ``edits`` in their most common outcome; None when
    fewer than half of the edits are classed to an outcome."""
    classed = [e["outcome"] for e in edits if _is_outcome(e["outcome"])]
    if not edits or len(classed) < len(edits) / 2:
        return None
    return 1.0 - Counter(classed).most_common(1)[0][1] / len(classed)


def first_defined_sweep(log: Sequence[dict], views: int) -> tuple[int, int, float] | None:
    """``(subtask, step, split)`` of the first edit subtask's initial sweep whose split is
    defined (edit subtasks: ratio > 0), or None."""
    for subtask, step, edits in sweeps(log, views):
        if edits[0]["ratio"] > 0:
            s = split(edits)
            if s is not None:
                return subtask, step, s
    return None


def edit_figures(log: Sequence[dict] | None, views: int) -> dict:
    """A run's ``early_split``, ``edit_consistency``, ``keep_rate`` (None where undefined) and
    the share of its edits classed ``other`` or ``unedited`` (``unseen_share``)."""
    if not log:
        return {"early_split": None, "edit_consistency": None, "keep_rate": None,
                "unseen_share": None, "edits": 0}
    first = first_defined_sweep(log, views)
    consistency = None
    if first is not None:
        after = [e["outcome"] for e in log if (e["subtask"], e["step"]) >= first[:2]
                 and _is_outcome(e["outcome"])]
        consistency = Counter(after).most_common(1)[0][1] / len(after)
    last: dict[int, object] = {}
    kept = pairs = 0
    for e in log:
        if _is_outcome(e["outcome"]):
            if e["view"] in last:
                pairs += 1
                kept += last[e["view"]] == e["outcome"]
            last[e["view"]] = e["outcome"]
    unseen = sum(e["outcome"] in (OTHER, UNEDITED) for e in log) / len(log)
    return {"early_split": None if first is None else first[2],
            "edit_consistency": consistency, "keep_rate": kept / pairs if pairs else None,
            "unseen_share": unseen, "edits": len(log)}


# ---------------------------------------------------------------------------- statistics

def _paired(a: Sequence[float], b: Sequence[float]) -> dict | None:
    """ProEdit minus control over the seeds where both are defined: the t interval of
    :func:`jaxedit.metrics.paired_differences`, its two-sided p, and Wilcoxon's p."""
    from scipy import stats

    pairs = [(x, y) for x, y in zip(a, b) if x is not None and y is not None]
    if len(pairs) < 2:
        return None
    x, y = np.asarray(pairs, np.float64).T
    d = paired_differences(x, y, level=LEVEL)
    diff = x - y
    if np.all(diff == diff[0]):  # no spread: the test is degenerate
        p_t = 1.0 if diff[0] == 0 else 0.0
        p_w = 1.0 if diff[0] == 0 else None
    else:
        p_t = float(stats.ttest_rel(x, y).pvalue)
        p_w = float(stats.wilcoxon(diff).pvalue)
    return {**d, "p_t": p_t, "p_wilcoxon": p_w}


def spearman_bootstrap(x: Sequence[float], y: Sequence[float], *, seed: int = 0,
                       resamples: int = BOOTSTRAP) -> dict | None:
    """Spearman's rho of paired samples with a percentile bootstrap interval over the pairs
    (``resamples`` draws, seeded) and a two-sided bootstrap p (twice the smaller tail share
    at 0)."""
    from scipy import stats

    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    if len(x) < 3 or np.all(x == x[0]) or np.all(y == y[0]):
        return None
    rho = float(stats.spearmanr(x, y).statistic)
    i = np.random.default_rng(seed).integers(0, len(x), (resamples, len(x)))
    # Spearman's rho of every resample at once: Pearson's of the (tie-averaged) ranks.
    rx, ry = (stats.rankdata(v[i], axis=1) for v in (x, y))
    rx, ry = rx - rx.mean(1, keepdims=True), ry - ry.mean(1, keepdims=True)
    norm = np.sqrt((rx ** 2).sum(1) * (ry ** 2).sum(1))
    spread = norm > 0  # a resample without spread has no rank correlation
    draws = (rx * ry).sum(1)[spread] / norm[spread]
    low, high = percentile_interval(draws, level=LEVEL)
    p = float(min(1.0, 2 * min(np.mean(draws <= 0), np.mean(draws >= 0))))
    return {"rho": rho, "low": float(low), "high": float(high), "p": p, "n": int(len(x)),
            "resamples": int(len(draws))}


def holm(pvalues: dict) -> dict:
    """Holm's step-down adjusted p-values of a family ``{name: p}`` (None entries skipped)."""
    named = sorted(((p, n) for n, p in pvalues.items() if p is not None))
    m, running, out = len(named), 0.0, {}
    for i, (p, name) in enumerate(named):
        running = max(running, min(1.0, (m - i) * p))
        out[name] = running
    return out


# ---------------------------------------------------------------------------- the study

def _by_seed(records: Iterable[dict], prompt: str, method: str) -> dict[int, dict]:
    return {r["seed"]: r for r in records
            if r["prompt"] == prompt and r["method"] == method and not r.get("reference")}


def study(records: Sequence[dict], *, views: int, recon_psnr: float | None) -> dict:
    """The registered figures and verdicts of a mechanism study's records (``runs.jsonl``).

    Args:
      records: the study's records (one scene); reference levels (``seed`` -1) included.
      views: training views of the scene.
      recon_psnr: the reconstruction's held-out PSNR (dB), for the testability check.
    Returns:
      ``{"per_run": [...], "instructions": {prompt: {...}}, "family": {...}}``; see
      ``docs/mechanism-preregistration.md`` for what each verdict means.
    """
    runs = [r for r in records if not r.get("reference") and r.get("edit_outcomes") is not None]
    per_run = [{"prompt": r["prompt"], "method": r["method"], "seed": r["seed"],
                "psnr_best": r["psnr_best"], "mode_mixing": r["mode_mixing"],
                **edit_figures(r["edit_outcomes"], views)} for r in runs]
    figures = {(f["prompt"], f["method"], f["seed"]): f for f in per_run}
    prompts = sorted({r["prompt"] for r in runs})
    family_p: dict[str, float | None] = {}
    result: dict[str, dict] = {}
    for prompt in prompts:
        lead = _by_seed(runs, prompt, LEAD)
        refs = {r["method"]: r for r in records if r.get("reference") and r["prompt"] == prompt}
        out: dict = {"seeds": sorted(lead), "controls": {}}
        testable = []
        if recon_psnr is not None and recon_psnr < MIN_RECON_PSNR:
            testable.append(f"the reconstruction's held-out PSNR {recon_psnr:.1f} dB < "
                            f"{MIN_RECON_PSNR}")
        if "ceiling" in refs and "unedited" in refs and \
                refs["ceiling"]["psnr_best"] <= refs["unedited"]["psnr_best"]:
            testable.append("the ceiling is not above the unedited reconstruction")
        unseen = {}
        for method in (LEAD, *CONTROLS, UNIFORM):
            shares = [figures[(prompt, method, s)]["unseen_share"]
                      for s in _by_seed(runs, prompt, method)]
            if shares:
                unseen[method] = float(np.mean(shares))
        out["unseen_share"] = unseen
        if unseen and min(unseen.values()) > MAX_UNSEEN:
            testable.append("more than half of every method's training edits are 'other' or "
                            "'unedited' (" + ", ".join(f"{m} {v:.0%}" for m, v in unseen.items())
                            + "): the measure cannot see outcomes at the trainer's timesteps")
        out["not_testable"] = testable
        for control in CONTROLS:
            ctl = _by_seed(runs, prompt, control)
            seeds = sorted(set(lead) & set(ctl))
            get = lambda m, s, k: figures[(prompt, m, s)][k]  # noqa: E731
            splits = [get(control, s, "early_split") for s in seeds]
            split_seeds = sum(x is not None and x >= SPLIT for x in splits)
            c = {"seeds": seeds, "control_early_split": splits,
                 "control_split_seeds": split_seeds,
                 "lead_early_split": [get(LEAD, s, "early_split") for s in seeds]}
            for key in ("edit_consistency", "keep_rate", "mode_mixing", "psnr_best"):
                c[key] = _paired([get(LEAD, s, key) for s in seeds],
                                 [get(control, s, key) for s in seeds])
            lead_psnr = [get(LEAD, s, "psnr_best") - get(control, s, "psnr_best") for s in seeds]
            defined = [(x, d) for x, d in zip(splits, lead_psnr) if x is not None]
            c["psnr_lead"] = lead_psnr
            c["rho_lead_vs_split"] = spearman_bootstrap(*zip(*defined)) if len(defined) >= 3 \
                else None
            unsplit = [d for x, d in zip(splits, lead_psnr) if x == 0]
            c["lead_where_no_split"] = _paired(unsplit, [0.0] * len(unsplit))
            out["controls"][control] = c
            family_p[f"{prompt} | {control} | P1"] = None if c["edit_consistency"] is None \
                else c["edit_consistency"]["p_t"]
            family_p[f"{prompt} | {control} | P2"] = None if c["psnr_best"] is None \
                else c["psnr_best"]["p_t"]
            family_p[f"{prompt} | {control} | P3"] = None if c["rho_lead_vs_split"] is None \
                else c["rho_lead_vs_split"]["p"]
        uni = _by_seed(runs, prompt, UNIFORM)
        seeds = sorted(set(lead) & set(uni))
        out["uniform"] = {"seeds": seeds, "psnr_best": _paired(
            [lead[s]["psnr_best"] for s in seeds], [uni[s]["psnr_best"] for s in seeds]),
            "same_run": sum(uni[s].get("same_run_as") == LEAD for s in seeds)}
        result[prompt] = out
    adjusted = holm(family_p)
    for prompt, out in result.items():
        for control, c in out["controls"].items():
            c["holm"] = {p: adjusted.get(f"{prompt} | {control} | {p}") for p in ("P1", "P2", "P3")}
            c["verdicts"] = _verdicts(c, out["not_testable"])
        out["P4"] = _scheduler_verdict(out["uniform"])
    return {"per_run": per_run, "instructions": result,
            "family": {"size": sum(p is not None for p in family_p.values()),
                       "p": family_p, "holm": adjusted}}


def _above(d: dict | None, adjusted_p: float | None = None) -> bool:
    """The interval lies above 0 (after Holm where ``adjusted_p`` is given)."""
    if d is None or d["low"] is None:
        return False
    return d["low"] > 0 and (adjusted_p is None or adjusted_p < 1 - LEVEL)


def _verdicts(c: dict, not_testable: list[str]) -> dict:
    """P1-P3 for one (instruction, control): "held", "refuted", "not shown" or "not
    testable", each with its reason."""
    if not_testable:
        why = "; ".join(not_testable)
        return {p: ["not testable", why] for p in ("P1", "P2", "P3")}
    if c["control_split_seeds"] < MIN_SPLIT_SEEDS:
        why = (f"the control's early split reached {SPLIT} in {c['control_split_seeds']} "
               f"seeds (fewer than {MIN_SPLIT_SEEDS}): nothing for small steps to hold")
        return {p: ["not testable", why] for p in ("P1", "P2", "P3")}
    cons, keep = c["edit_consistency"], c["keep_rate"]
    if _above(cons, c["holm"]["P1"]) and _above(keep):
        p1 = ["held", "ProEdit's edit consistency (Holm) and keep rate are higher"]
    elif any(d is not None and d["high"] is not None and d["high"] <= 0 for d in (cons, keep)):
        p1 = ["refuted", "the control's edits split and ProEdit's consistency or keep rate is "
                         "not higher (interval at or below 0)"]
    else:
        p1 = ["not shown", "the intervals hold 0 on at least one of consistency and keep rate"]
    psnr, mix = c["psnr_best"], c["mode_mixing"]
    if p1[0] != "held":
        p2 = ["not testable", "P1 did not hold"]
    elif _above(psnr, c["holm"]["P2"]) and mix is not None and mix["high"] is not None \
            and mix["high"] < 0:
        p2 = ["held", "ProEdit mixes less and scores higher PSNR to the best outcome (Holm)"]
    elif psnr is not None and psnr["low"] is not None and psnr["low"] <= 0:
        p2 = ["refuted", "the edits stay consistent, and the PSNR interval holds 0 or lies "
                         "below it"]
    else:
        p2 = ["not shown", "PSNR higher but mixing not lower, or the correction removed it"]
    rho, flat = c["rho_lead_vs_split"], c["lead_where_no_split"]
    lead_exists = _above(psnr, c["holm"]["P2"])
    if rho is None:
        p3 = ["not testable", "fewer than 3 seeds with a defined early split, or no spread"]
    elif lead_exists and (rho["low"] <= 0 <= rho["high"]):
        p3 = ["refuted", "a lead exists but it does not grow with the control's split"]
    elif lead_exists and flat is not None and flat["low"] is not None and flat["low"] > 0:
        p3 = ["refuted", "the lead is there where the control's edits never split"]
    elif rho["low"] > 0 and c["holm"]["P3"] is not None and c["holm"]["P3"] < 1 - LEVEL:
        p3 = ["held", "the lead grows with the control's early split (Holm)"]
    else:
        p3 = ["not shown", "rho's interval holds 0 and there is no lead to explain"]
    return {"P1": p1, "P2": p2, "P3": p3}


def _scheduler_verdict(u: dict) -> list[str]:
    d = u["psnr_best"]
    if d is None or d["low"] is None:
        return ["not testable", "fewer than 2 paired seeds"]
    if d["low"] > 0:
        return ["scheduler ahead", "ProEdit beats uniform ratios (interval above 0)"]
    if d["high"] < 0:
        return ["uniform ahead", "uniform ratios beat the difficulty-aware schedule"]
    return ["no difference", "the interval of ProEdit minus uniform holds 0, as registered"]
