"""The budget ablation's pure parts: densify counters, statistics and the table.

(The end-to-end run is ``benchmarks/budget_ablation.py --smoke`` in CI; it edits the default
only, so the paired differences are checked here.)"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxedit.metrics import mean_ci


def _import_benchmark(name: str):
    """The benchmark script ``name``, which imports its sibling ``common``. The benchmarks
    folder is on sys.path only while it loads: left there, its ``lpips.py`` would shadow
    the lpips package for every later test."""
    folder = str(Path(__file__).resolve().parents[1] / "benchmarks")
    sys.path.insert(0, folder)
    try:
        return importlib.import_module(name)
    finally:
        sys.path.remove(folder)


ba = _import_benchmark("budget_ablation")


def records(seeds=4):
    """Synthetic edits: growth=0.05 creates 500 more and is 0.2 dB better on every seed."""
    rng = np.random.default_rng(0)
    out = []
    for seed in range(seeds):
        noise = rng.normal(0, 0.5)  # shared by the variants of a seed: pairing removes it
        for v, lead, extra in (("default", 0.0, 0), ("growth=0.05", 0.2, 500)):
            out.append({"variant": v, "seed": seed, "psnr_vs_target": 37.0 + noise + lead,
                        "created": 10_000 + 100 * seed + extra, "lpips_vs_target": None})
    return out


def test_paired_differences_remove_the_seed_noise():
    summary, diffs = ba.summarise(records(), ("default", "growth=0.05"),
                                  metrics=("psnr_vs_target", "created", "lpips_vs_target"))
    d = {(r["variant"], r["metric"]): r for r in diffs}
    assert d[("growth=0.05", "psnr_vs_target")]["mean"] == pytest.approx(0.2)
    assert d[("growth=0.05", "psnr_vs_target")]["ci"] == pytest.approx(0.0, abs=1e-9)
    assert d[("growth=0.05", "created")]["mean"] == pytest.approx(500)
    s = {(r["variant"], r["metric"]): r for r in summary}
    vals = [r["psnr_vs_target"] for r in records() if r["variant"] == "default"]
    assert s[("default", "psnr_vs_target")]["ci"] == pytest.approx(mean_ci(vals)["ci"])
    assert s[("default", "psnr_vs_target")]["median"] == pytest.approx(float(np.median(vals)))
    assert ("default", "lpips_vs_target") not in s  # missing scores are left out, not zeros


def test_summary_uses_only_seeds_every_variant_finished():
    runs = [r for r in records() if not (r["seed"] == 3 and r["variant"] == "growth=0.05")]
    summary, _ = ba.summarise(runs, ("default", "growth=0.05"), metrics=("created",))
    assert {r["n"] for r in summary} == {3}


def test_table_marks_differences_whose_ci_excludes_zero():
    variants = ("default", "growth=0.05")
    summary, diffs = ba.summarise(records(), variants, metrics=("psnr_vs_target", "created"))
    text = ba.table(summary, diffs, variants, metrics=("psnr_vs_target", "created"))
    row = next(line for line in text.splitlines() if line.startswith("| growth=0.05 - default"))
    assert "+0.20 ± 0.00 *" in row and "+500 ± 0 *" in row


def test_densify_totals_sum_the_subtask_tallies():
    subtasks = [{"density": {"refinements": 3, "created": 40, "culled": 7, "budget_limited": 2,
                             "cap_limited": 0, "shortfall": 0}},
                {"density": {"refinements": 2, "created": 5, "culled": 1, "budget_limited": 0,
                             "cap_limited": 1, "shortfall": 9}}]
    assert ba.densify_totals(subtasks) == {"created": 45, "culled": 8, "maintenance": 5,
                                           "budget_bound": 2, "cap_hits": 1}
