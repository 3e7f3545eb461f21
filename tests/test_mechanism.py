"""The pre-registered mechanism test's figures and verdicts (jaxedit_lab.ablation.mechanism)
on hand-made per-edit logs whose answers are known."""

from __future__ import annotations

import json

import numpy as np
import pytest

from jaxedit_lab.ablation import mechanism as M

VIEWS = 4
PROMPT = "splash some colour on it"


def _log(*sweeps_and_edits):
    """Edits from ``(subtask, ratio, step, outcomes)``: one exchange each, the outcomes of
    views 0, 1, ... (a full list is a sweep)."""
    return [{"subtask": sub, "step": step, "view": v, "t": 0.5, "ratio": ratio, "outcome": o}
            for sub, ratio, step, outcomes in sweeps_and_edits
            for v, o in enumerate(outcomes)]


def test_split_consistency_and_keep_rate_of_a_known_log():
    log = _log((0, 0.25, 10, [0, 0, 1, "unedited"]),  # sweep: 3 of 4 classed, split 1/3
               (0, 0.25, 15, [0]),
               (0, 0.25, 20, [0, 0]),
               (1, 0.5, 10, [0, 0, 0, 0]))  # sweep, split 0
    assert [(s, st) for s, st, _ in M.sweeps(log, VIEWS)] == [(0, 10), (1, 10)]
    f = M.edit_figures(log, VIEWS)
    assert f["early_split"] == pytest.approx(1 / 3)
    assert f["edit_consistency"] == pytest.approx(9 / 10)  # classed from the sweep on: 9 x 0, 1 x 1
    # view 0: 0 0 0 0 (3 kept); view 1: 0 0 0 (2); view 2: 1 0 (0 of 1); view 3: unedited, 0
    assert f["keep_rate"] == pytest.approx(5 / 6)
    assert f["unseen_share"] == pytest.approx(1 / 11) and f["edits"] == 11


def test_a_sweep_mostly_unclassed_is_undefined_and_the_next_one_counts():
    log = _log((0, 0.0, 10, [0, 1, 2, 0]),  # the refine subtask (ratio 0) never counts
               (1, 0.25, 10, ["other", "unedited", "mixed", 1]),  # 1 of 4 classed: undefined
               (2, 0.5, 10, [2, 2, 1, 2]))
    assert M.split(log[4:8]) is None
    assert M.first_defined_sweep(log, VIEWS) == (2, 10, pytest.approx(0.25))
    f = M.edit_figures(log, VIEWS)
    assert f["early_split"] == pytest.approx(0.25)
    assert f["edit_consistency"] == pytest.approx(3 / 4)
    assert M.edit_figures([], VIEWS)["early_split"] is None


def test_holm_adjusts_step_down():
    adjusted = M.holm({"a": 0.01, "b": 0.04, "c": 0.03, "d": None})
    assert adjusted == pytest.approx({"a": 0.03, "c": 0.06, "b": 0.06})


def test_spearman_bootstrap_sees_a_monotone_link_and_not_noise():
    x = np.arange(12, dtype=float)
    up = M.spearman_bootstrap(x, x ** 2, resamples=500)
    assert up["rho"] == pytest.approx(1.0) and up["low"] > 0.8 and up["p"] < 0.05
    noise = M.spearman_bootstrap(x, np.random.default_rng(0).normal(size=12), resamples=500)
    assert noise["low"] < 0 < noise["high"]
    assert M.spearman_bootstrap([1, 1, 1], [1, 2, 3]) is None


def _record(method, seed, log, psnr, mixing, **extra):
    return {"prompt": PROMPT, "method": method, "seed": seed, "scene": "face", "psnr_best": psnr,
            "mode_mixing": mixing, "edit_outcomes": log, **extra}


def _study(split_seeds: int, n: int = 10):
    """ProEdit's edits always in outcome 0; nd_k's and nd_equal's first sweep split (two
    views in outcome 1) in ``split_seeds`` seeds, and then their scenes mix and score lower by
    an amount that grows with the seed; uniform is ProEdit's run."""
    rng = np.random.default_rng(1)
    records = [{"prompt": PROMPT, "method": m, "seed": -1, "reference": True, "psnr_best": p,
                "mode_mixing": 0.0, "edit_outcomes": None}
               for m, p in (("unedited", 20.0), ("ceiling", 28.0))]
    for seed in range(n):
        clean = _log((0, 0.25, 10, [0] * VIEWS), (0, 0.25, 15, [0, 0]), (1, 0.5, 10, [0] * VIEWS))
        records.append(_record("proedit", seed, clean, 25.0 + 0.01 * rng.normal(), 0.0))
        records.append(_record("uniform", seed, clean, records[-1]["psnr_best"], 0.0,
                               same_run_as="proedit"))
        splits = seed < split_seeds
        for method in M.CONTROLS:
            first = [0, 0, 1, 1] if splits else [0] * VIEWS
            later = [1, 0] if splits else [0, 0]
            log = _log((0, 1.0, 10, first), (0, 1.0, 15, later), (1, 1.0, 10, [0] * VIEWS))
            lead = (0.3 + 0.1 * seed) if splits else 0.01 * rng.normal()
            records.append(_record(method, seed, log, 25.0 - lead, 0.4 if splits else 0.0))
    return M.study(records, views=VIEWS, recon_psnr=30.0)


def test_the_planted_mechanism_is_found_prediction_by_prediction():
    out = _study(split_seeds=6)["instructions"][PROMPT]
    assert out["not_testable"] == []
    for control in M.CONTROLS:
        c = out["controls"][control]
        assert c["control_split_seeds"] == 6
        assert c["edit_consistency"]["low"] > 0 and c["keep_rate"]["low"] > 0
        v = c["verdicts"]
        assert v["P1"][0] == "held" and v["P2"][0] == "held", v
        # the lead grows with the split, and is nil where the control did not split
        assert c["rho_lead_vs_split"]["rho"] > 0.5 and v["P3"][0] == "held", (v, c)
    assert out["P4"][0] == "no difference" and out["uniform"]["same_run"] == 10


def test_edits_the_measure_cannot_see_leave_the_mechanism_untested():
    # every method's edits mostly "other" or "unedited": not testable; one method that the
    # measure sees is enough to test
    def runs(methods_unseen):
        records = []
        for seed in range(4):
            for method in ("proedit", *M.CONTROLS):
                outcomes = ["other", "unedited", "other", 0] if method in methods_unseen \
                    else [0, 0, 0, 0]
                records.append(_record(method, seed, _log((0, 0.5, 10, outcomes)), 20.0, 0.0))
        return M.study(records, views=VIEWS, recon_psnr=30.0)["instructions"][PROMPT]

    out = runs({"proedit", *M.CONTROLS})
    assert len(out["not_testable"]) == 1 and "every method" in out["not_testable"][0]
    assert out["unseen_share"]["proedit"] == pytest.approx(0.75)
    assert runs({"proedit"})["not_testable"] == []


def test_controls_that_never_split_leave_the_mechanism_untested():
    out = _study(split_seeds=3)["instructions"][PROMPT]
    for control in M.CONTROLS:
        v = out["controls"][control]["verdicts"]
        assert {p: x[0] for p, x in v.items()} == {"P1": "not testable", "P2": "not testable",
                                                  "P3": "not testable"}
        assert "fewer than 5" in v["P1"][1]


def test_a_script_run_on_a_folder_writes_the_summary(tmp_path, capsys):
    from importlib import util
    from pathlib import Path

    spec = util.spec_from_file_location(
        "mechanism_study", Path(__file__).resolve().parents[1] / "scripts" / "mechanism_study.py")
    script = util.module_from_spec(spec)
    spec.loader.exec_module(script)
    run = tmp_path / "run"
    (run / "face" / "reconstruct").mkdir(parents=True)
    (run / "settings.json").write_text(json.dumps({"scenes": ["face"], "views": VIEWS}))
    (run / "face" / "reconstruct" / "metrics.json").write_text(json.dumps({"test_psnr": 20.0}))
    records = [_record("proedit", s, _log((0, 0.25, 10, [0] * VIEWS)), 25.0, 0.0)
               for s in range(3)]
    (run / "runs.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    assert script.main([str(run)]) == 0
    summary = json.loads((run / "mechanism.json").read_text())
    out = summary["instructions"][PROMPT]
    # a reconstruction below 25 dB: nothing is testable, and the report says why
    assert "25.0" in out["not_testable"][0]
    assert "P1 vs nd_k: not testable" in capsys.readouterr().out
    assert script.main([str(tmp_path / "nothing")]) == 2
    assert capsys.readouterr().err.count("\n") == 1
