"""The ablation as statistics: per-seed records -> means, Student-t CIs, paired differences,
tables and the report page. (The end-to-end run is ``benchmarks/ablation.py --smoke`` in CI.)"""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import stats

from experiments import cli
from jaxedit_lab.ablation import METHODS, summarise, tables
from jaxedit_lab.ablation.report import write_ablation_report
from jaxedit import DataError
from jaxedit.metrics import mean_ci, mode_mixture, mode_scores, paired_differences

PROMPTS = ("make it look like autumn", "make his head bigger")


def records(seeds=4, modes=(1, 3)):
    """Synthetic runs: proedit is 1 dB better than nd on the first prompt, equal on the second."""
    rng = np.random.default_rng(0)
    out = []
    for k in modes:
        for p, prompt in enumerate(PROMPTS):
            for seed in range(seeds):
                noise = rng.normal(0, 0.3)  # shared by the methods of a seed: pairing removes it
                for m, method in enumerate(METHODS):
                    lead = 1.0 if (p == 0 and method == "proedit") else 0.0
                    out.append({"editor_modes": k, "scene": "face", "prompt": prompt,
                                "seed": seed, "method": method,
                                "psnr_best": 20.0 + lead + noise + 0.01 * rng.normal(),
                                "ssim_best": 0.8, "mode_mixing": 0.1 * m,
                                "multiview_consistency": 25.0, "psnr_vs_target": 19.0,
                                "total_steps": 100 + seed, "cpu_seconds": 1.0})
    return out


def test_mean_ci_and_paired_differences_are_student_t():
    x = np.array([1.0, 2.0, 4.0, 7.0])
    r = mean_ci(x)
    half = stats.t.ppf(0.975, 3) * x.std(ddof=1) / 2.0
    assert r["mean"] == pytest.approx(3.5) and r["ci"] == pytest.approx(half) and r["n"] == 4
    assert r["low"] == pytest.approx(3.5 - half) and r["high"] == pytest.approx(3.5 + half)
    assert mean_ci([2.0])["ci"] is None
    d = paired_differences([3.0, 4.0, 6.0], [1.0, 2.0, 4.5])
    assert d["mean"] == pytest.approx(np.mean([2.0, 2.0, 1.5]))
    with pytest.raises(DataError, match="paired"):
        paired_differences([1.0, 2.0], [1.0])
    with pytest.raises(DataError, match="finite"):
        mean_ci([1.0, float("nan")])


def test_mode_scores_favour_no_mode():
    rng = np.random.default_rng(1)
    t = rng.uniform(0, 1, (3, 2, 12, 12, 3))  # SSIM windows need >= 11 px
    for k in range(3):  # a render equal to any one mode scores the same and does not mix
        s = mode_scores(t[k], t)
        assert s["mode"] == k and s["psnr_best"] == pytest.approx(100.0, abs=1e-6)
        assert s["mode_mixing"] == pytest.approx(0.0, abs=1e-9)
    even = mode_scores(t.mean(0), t)
    assert even["mode_mixing"] == pytest.approx(1.0, abs=1e-6)
    w = mode_mixture(0.7 * t[0] + 0.3 * t[2], t)
    np.testing.assert_allclose(w, [0.7, 0.0, 0.3], atol=1e-6)
    # outside the simplex: the nearest blend on its boundary, weights still sum to 1
    w = mode_mixture(np.clip(1.4 * t[1] - 0.4 * t[0], 0, 1), t)
    assert w.min() >= 0 and w.sum() == pytest.approx(1.0) and w[1] == w.max()
    assert mode_scores(t[0], t[:1])["mode_mixing"] == 0.0
    with pytest.raises(DataError, match="mode_targets"):
        mode_mixture(t[0], t[:, :1])


def test_summary_and_paired_differences():
    runs = records()
    summary, differences = summarise(runs)
    pick = lambda rows, **kw: [r for r in rows if all(r[k] == v for k, v in kw.items())]  # noqa: E731
    for k in (1, 3):
        row, = pick(summary, editor_modes=k, prompt=PROMPTS[0], method="nd", metric="psnr_best")
        vals = [r["psnr_best"] for r in runs if r["editor_modes"] == k and r["method"] == "nd"
                and r["prompt"] == PROMPTS[0]]
        assert row["n"] == 4 and row["mean"] == pytest.approx(np.mean(vals))
        assert row["ci"] == pytest.approx(mean_ci(vals)["ci"])
        # pairing by seed removes the shared noise: proedit's 1 dB lead is resolved
        d, = pick(differences, editor_modes=k, prompt=PROMPTS[0], method="nd", metric="psnr_best")
        assert d["mean"] == pytest.approx(1.0, abs=0.05) and d["ci"] < 0.1
        d, = pick(differences, editor_modes=k, prompt=PROMPTS[1], method="in2n",
                  metric="psnr_best")
        assert abs(d["mean"]) < 0.05
        # "all" averages the instructions of each seed first: half the lead
        d, = pick(differences, editor_modes=k, prompt="all", method="nd_equal",
                  metric="psnr_best")
        assert d["mean"] == pytest.approx(0.5, abs=0.05) and d["n"] == 4
    assert not pick(differences, method="proedit")
    md = tables(summary, differences)
    assert "editor modes = 1: psnr_best" in md and "editor modes = 3: mode_mixing" in md
    assert "| face | make it look like autumn |" in md and "proedit − in2n" in md
    assert " *" in md  # the resolved lead is marked


def test_report_shows_the_statistics(tmp_path):
    runs = records(seeds=3)
    summary, differences = summarise(runs)
    (tmp_path / "ablation.json").write_text(json.dumps({
        "settings": {"scenes": ["face"], "seeds": 3}, "runs": runs, "summary": summary,
        "differences": differences}))
    text = write_ablation_report(tmp_path).read_text()
    assert "editor modes = 3: mode_mixing" in text and "not InstructPix2Pix" in text
    assert "proedit − nd_equal" in text and "data:image/png;base64," in text
    (tmp_path / "ablation.json").write_text(json.dumps({"proedit": {"psnr": 3}}))
    with pytest.raises(DataError, match="ablation.json"):
        write_ablation_report(tmp_path)
    (tmp_path / "ablation.json").write_text(json.dumps({"runs": [], "summary": [{"mean": 1}]}))
    with pytest.raises(DataError, match=r"summary\[0\]"):
        write_ablation_report(tmp_path)


@pytest.mark.parametrize("argv, needle", [
    (["--scenes", "moon"], "--scenes"),
    (["--variants", "1,7"], "--variants"),
    (["--variants", "3:x"], "--variants"),
    (["--max-steps", "20", "--refine-every", "10"], "--max-steps: must be at least 3 x refine_every"),
    (["--methods", "nd,in2n"], "include proedit"),
    (["--prompts", "make it a dragon"], "unknown instruction"),
    (["--seeds", "0"], "--seeds"),
    (["--seeds", "4", "--seed-range", "2:5"], "--seed-range: 2:5 is not a non-empty range"),
    (["--seed-range", "3"], "--seed-range: expected A:B"),
    (["--ip2p-weights", "."], "--ip2p-weights: used only with the ip2p editor"),
    (["--editor", "ip2p", "--ip2p-weights", "/no/such/folder"], "--ip2p-weights"),
])
def test_bad_flags_fail_in_one_line(tmp_path, capsys, argv, needle):
    assert cli.main(["ablation", "--out", str(tmp_path / "run"), *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err


def test_an_interrupted_run_summarises_what_finished():
    runs = records(seeds=3, modes=(3,))
    # the second instruction stopped after seed 1's nd: seed 2 of it is left out, paired
    runs = [r for r in runs if not (r["prompt"] == PROMPTS[1] and (
        r["seed"] == 2 or (r["seed"] == 1 and r["method"] in ("nd_equal", "nd_k", "uniform", "in2n"))))]
    summary, differences = summarise(runs)
    rows = [r for r in summary if r["metric"] == "psnr_best" and r["method"] == "proedit"]
    assert {r["prompt"]: r["n"] for r in rows} == {PROMPTS[0]: 3, PROMPTS[1]: 1}
    assert all(r["prompt"] != "all" for r in summary)  # one complete instruction: no "all"
    d = [r for r in differences if r["prompt"] == PROMPTS[1] and r["method"] == "nd"]
    assert d and all(r["n"] == 1 and r["ci"] is None for r in d)


# ---- the run's bookkeeping (pure) and the mechanism's planted effect -------------------------

def test_edit_counts_follow_the_deterministic_source():
    from jaxedit_lab.ablation.methods import (edits_per_subtask, match_edit_every,
                                                    sweep_agreement)

    # exchanges at steps W, W + E, ... below the subtask's length; the first edits every view
    assert edits_per_subtask(30, warmup=4, every=3, views=6, initial_sweep=True) == 6 + 8
    assert edits_per_subtask(4, warmup=4, every=3, views=6, initial_sweep=True) == 0
    assert edits_per_subtask(30, warmup=0, every=10, views=6, initial_sweep=False) == 3
    lengths = [30, 120, 30]
    every = match_edit_every(70, lengths, warmup=4, views=6, most=3)
    got = sum(edits_per_subtask(s, warmup=4, every=every, views=6, initial_sweep=True)
              for s in lengths)
    assert all(abs(got - 70) <= abs(sum(edits_per_subtask(s, warmup=4, every=e, views=6,
                                                           initial_sweep=True)
                                        for s in lengths) - 70) for e in (1, 2, 3))
    # complete sweeps only; the fraction of views in the sweep's most common mode
    assert sweep_agreement([0, 0, 1, 2, 2, 1, 1], [4, 3], 2) == [[1.0, 0.5], [0.5]]
    with pytest.raises(ValueError):
        sweep_agreement([0, 1], [3], 2)


def _stays(editor, original, ratio, seeds, views):
    """Per seed, the fraction of views whose edit at ``ratio`` stays in mode 0, from a render
    committed to mode 0 at r = 0.45 (the first sweep of the next subtask, t = t_max)."""
    import jax

    from jaxedit.editors.base import interpolate_embedding
    from jaxedit.editors.keys import view_key

    prompt = "give him a marble texture"
    render = editor.target(original, 0.45, prompt, 0)
    e = interpolate_embedding(editor.encode(prompt), editor.encode(""), ratio)
    return [np.mean([editor.edit_with_mode(render, original, e, view_key(
        jax.random.key(seed), v, 0.0, 0), timestep_range=(0.85, 0.85))[1] == 0
        for v in range(views)]) for seed in range(seeds)]


def test_paired_intervals_detect_the_planted_step_size_effect_and_not_its_absence():
    # Planted: holding a mode falls with the step (mode_step_gain 1, the default; P(stay) 0.76
    # vs 0.59 here), so a committed scene keeps its mode in more views when the next subtask is
    # a small step (0.45 -> 0.575) than when it jumps to r = 1. Same keys for both (paired by seed and view). Gain 0: the draw
    # does not depend on the step, the same keys draw the same modes, the difference is 0.
    from jaxedit_lab.simulated import SimulatedEditor

    yy, xx = np.mgrid[0:24, 0:24] + 0.5
    inside = ((yy - 12) / 9) ** 2 + ((xx - 12) / 7) ** 2 < 1
    shade = np.stack([0.5 + 0.4 * np.sin(xx / 3), 0.4 + 0.3 * np.cos(yy / 4),
                      0.3 + 0.2 * np.sin((xx + yy) / 5)], -1)
    original = np.where(inside[..., None], shade, 1.0).astype(np.float32)
    planted = SimulatedEditor(modes=3)
    d = paired_differences(_stays(planted, original, 0.575, 16, 8),
                           _stays(planted, original, 1.0, 16, 8))
    assert d["low"] > 0, d
    off = SimulatedEditor(modes=3, mode_step_gain=0.0)
    d = paired_differences(_stays(off, original, 0.575, 16, 8), _stays(off, original, 1.0, 16, 8))
    assert d["low"] <= 0 <= d["high"] and d["mean"] == 0.0, d


# ---- the runner end to end: equal budgets, JSONL and resume, a planted effect ---------------

class PlantedEditor:
    """Three outcomes (the view tinted red, green or blue at strength r). Planted: an edit
    whose ratio is more than 0.5 above the strength the render shows draws its outcome from
    its key (each view its own), a smaller step keeps the outcome the render shows with
    certainty (outcome 0 while it shows none). Not planted: every edit is outcome 0."""

    label = "planted"
    COLOURS = np.array([[0.9, 0.1, 0.1], [0.1, 0.8, 0.1], [0.1, 0.2, 0.9]], np.float32)

    def __init__(self, planted: bool):
        self.planted = planted

    def encode(self, prompt):
        return np.array([0.0 if prompt == "" else 1.0], np.float32)

    def kind(self, prompt):
        return "texture"

    @staticmethod
    def _object(o):
        """1 on the object, 0 on the white backdrop (which the Gaussians cannot paint)."""
        return (o.min(-1, keepdims=True) < 0.95).astype(np.float32)

    def mode_targets(self, original, ratio, prompt):
        o = np.asarray(original, np.float32)
        return np.stack([o + ratio * self._object(o) * (c - o) for c in self.COLOURS])

    def edit(self, image, original, embedding, key, **kwargs):
        import jax

        r = float(np.asarray(embedding)[0])
        image, o = np.asarray(image, np.float32), np.asarray(original, np.float32)
        k = 0
        if self.planted:
            fits = []
            for c in self.COLOURS:
                d = self._object(o) * (c - o)
                s = float(np.clip(np.sum((image - o) * d) / np.sum(d * d), 0, 1))
                fits.append((float(np.sum((image - o - s * d) ** 2)), s))
            k = int(np.argmin([f[0] for f in fits]))
            shown = fits[k][1]
            if shown < 0.15:
                k, shown = 0, 0.0
            if r - shown > 0.5:
                k = int(jax.random.randint(key, (), 0, len(self.COLOURS)))
        return o + r * self._object(o) * (self.COLOURS[k] - o)


def _tiny(**kw):
    from jaxedit_lab.ablation import AblationConfig

    base = dict(scenes=("ball",), prompts=("make it look like autumn",), seeds=4,
                methods=("proedit", "nd", "nd_equal", "nd_replay"), size=12, views=6,
                test_views=3, recon_iters=30, refine_every=4, max_steps=16, warmup=2,
                patience=3, edit_every=2)
    return AblationConfig(**(base | kw))


# slow tier: a whole study through the runner (its paired intervals are proven in the default
# tier by test_paired_intervals_detect_the_planted_step_size_effect_and_not_its_absence)
@pytest.mark.slow
def test_planted_step_effect_is_found_through_the_runner_and_exactly_0_without(tmp_path):
    # Planted: ND's one large step draws each view's outcome, ProEdit's small steps hold one:
    # ND's scene mixes more (paired by seed). Not planted: every view is outcome 0 in every
    # method, so the outcome agreement differences are exactly 0. The unplanted run also
    # checks the equal budgets and the reference levels.
    from jaxedit_lab.ablation import run_ablation

    res = run_ablation(tmp_path / "planted", _tiny(seeds=5, methods=("proedit", "nd"),
                                                   references=False),
                       editor=PlantedEditor(True), report=False, log=lambda m: None)
    d, = [r for r in res["differences"] if r["metric"] == "mode_mixing" and r["method"] == "nd"]
    assert d["high"] < 0, d
    res = run_ablation(tmp_path / "off", _tiny(seeds=2), editor=PlantedEditor(False),
                       report=False, log=lambda m: None)
    for d in res["differences"]:
        if d["metric"] == "outcome_agreement" and d["method"] != "unedited":
            assert d["mean"] == 0.0 and d["ci"] == 0.0, d
    runs = [r for r in res["runs"] if not r.get("reference")]
    for seed in range(2):  # equal budgets, exactly
        mine = {r["method"]: r for r in runs if r["seed"] == seed}
        for m in ("nd_equal", "nd_replay"):
            assert mine[m]["total_steps"] == mine["proedit"]["total_steps"]
            assert mine[m]["editor_calls"] == mine["proedit"]["editor_calls"]
        assert mine["nd_replay"]["calls_by_band"] == mine["proedit"]["calls_by_band"]
        assert mine["nd_replay"]["hottest_calls"] == mine["proedit"]["hottest_calls"]
        assert mine["nd_replay"]["resets"] == 3 < mine["proedit"]["resets"]
        assert mine["proedit"]["plateau_share"] is not None
        assert mine["nd_equal"]["plateau_share"] is None  # a fixed budget
    assert {r["method"] for r in res["runs"] if r.get("reference")} == {"unedited", "ceiling"}
    # resumed: nothing runs again, the same records
    again = run_ablation(tmp_path / "off", _tiny(seeds=2), editor=PlantedEditor(False),
                         report=False, log=lambda m: None)
    assert len(again["runs"]) == len(res["runs"])
    # a study merged from two folders may hold a run twice: it counts once
    jsonl = tmp_path / "off" / "runs.jsonl"
    lines = jsonl.read_text().splitlines()
    jsonl.write_text("\n".join(lines + lines[:3]) + "\n")
    merged = run_ablation(tmp_path / "off", _tiny(seeds=2), editor=PlantedEditor(False),
                          report=False, log=lambda m: None)
    assert merged["runs"] == again["runs"] and len(jsonl.read_text().splitlines()) == len(lines)
    # a part of the study (seed 1 alone, in a folder of its own) makes seed 1's records of
    # the whole study, and leaves the references to the part holding seed 0
    part = run_ablation(tmp_path / "part", _tiny(seeds=2), editor=PlantedEditor(False),
                        report=False, log=lambda m: None, seeds=range(1, 2))

    def timeless(records):
        return [{k: v for k, v in r.items() if k not in ("seconds", "cpu_seconds")}
                for r in records]

    assert timeless(part["runs"]) == timeless([r for r in res["runs"] if r["seed"] == 1])
    with pytest.raises(DataError, match="seeds"):
        run_ablation(tmp_path / "part", _tiny(seeds=2), editor=PlantedEditor(False),
                     report=False, log=lambda m: None, seeds=range(1, 3))


def test_uniform_reuses_proedit_only_when_its_ratios_are_uniform():
    # The study on the bundled editor found ProEdit's scheduler picking 0.25, 0.5, 0.75:
    # its seed-0 ProEdit and uniform runs were then the same bit for bit (computed both
    # ways, benchmarks/results/cpu/mechanism_ip2p/runs.jsonl), so later seeds reuse it.
    from jaxedit_lab.ablation import _same_plan_as_uniform, _uniform_from

    lead = {"method": "proedit", "ratios": [0.0, 0.25, 0.5, 0.75, 1.0, 1.0], "psnr_best": 17.5,
            "total_steps": 1388, "seconds": 160.0, "cpu_seconds": 150.0, "schedule_calls": 51}
    assert _same_plan_as_uniform(lead)
    for ratios in ([0.0, 0.3, 0.5, 0.75, 1.0, 1.0], [0.0, 0.25, 0.5, 0.75, 1.0],
                   [0.0, 0.5, 1.0, 1.0, 1.0]):
        assert not _same_plan_as_uniform(dict(lead, ratios=ratios)), ratios
    assert not _same_plan_as_uniform(None)
    reused = _uniform_from(lead)
    assert reused["method"] == "uniform" and reused["same_run_as"] == "proedit"
    assert reused["psnr_best"] == 17.5 and reused["total_steps"] == 1388
    assert reused["seconds"] == 0.0 and reused["cpu_seconds"] is None
    assert reused["schedule_calls"] is None and lead["method"] == "proedit"


class _RecordingPlanted(PlantedEditor):
    """The planted editor, remembering each call's photo and which outcome (by exact equality
    with o + r * object * (colour_k - o)) and strength it produced."""

    def __init__(self, planted):
        super().__init__(planted)
        self.calls = []

    def edit(self, image, original, embedding, key, **kwargs):
        out = super().edit(image, original, embedding, key, **kwargs)
        o, r = np.asarray(original, np.float32), float(np.asarray(embedding)[0])
        ks = [k for k, c in enumerate(self.COLOURS)
              if np.array_equal(out, o + r * self._object(o) * (c - o))]
        self.calls.append((o.tobytes(), ks[0], r))
        return out


def test_every_training_edit_is_logged_with_its_view_step_and_outcome(tmp_path):
    # issue 47: each record names its scene, prompt, method and seed and logs every training
    # edit's outcome. The planted editor's edit is exactly r of the way to outcome k, so its
    # class is known: k above r = 0.5, "unedited" below (the outcome measure's rule; at 0.5
    # itself rounding decides). nd_equal's explicit exchanges and nd_k's periodic ones.
    from jaxedit_lab.outcome_class import UNEDITED
    from jaxedit_lab.ablation import run_ablation

    editor = _RecordingPlanted(True)
    config = _tiny(seeds=1, methods=("proedit", "nd_k", "nd_equal"), references=False)
    res = run_ablation(tmp_path / "log", config, editor=editor, recon_seed=3, report=False,
                       log=lambda m: None)
    runs = {r["method"]: r for r in res["runs"]}
    assert set(runs) == {"proedit", "nd_k", "nd_equal"}
    photos = {}  # logged view -> the photo the editor was given
    at = 0
    for method in ("proedit", "nd_equal", "nd_k"):  # the order the runner makes them
        r = runs[method]
        assert (r["scene"], r["prompt"], r["method"], r["seed"], r["recon_seed"]) == \
            ("ball", config.prompts[0], method, 0, 3)
        log = r["edit_outcomes"]
        assert len(log) == r["editor_calls"] > 0
        # this run's calls: its schedule's (difficulty) first, then its training edits
        made = r["schedule_calls"] + r["editor_calls"]
        mine = editor.calls[at:at + made][r["schedule_calls"]:]
        at += made
        per_subtask = np.bincount([e["subtask"] for e in log], minlength=r["subtasks"])
        assert per_subtask.tolist() == r["edits_per_subtask"]
        for e, (photo, k, strength) in zip(log, mine):
            assert photos.setdefault(e["view"], photo) == photo  # one view, one photo
            assert e["ratio"] == pytest.approx(strength)
            if abs(strength - 0.5) > 1e-6:
                assert e["outcome"] == (k if strength > 0.5 else UNEDITED), (method, e)
            assert 0 <= e["step"] < r["subtask_steps"][e["subtask"]]
        steps = [(e["subtask"], e["step"]) for e in log]
        assert steps == sorted(steps)  # in the order the subtasks made them
        assert sum(r["edit_outcome_counts"].values()) == len(log)
    assert at == len(editor.calls)  # every call accounted for
    assert len(photos) == len(set(photos.values())) == config.views  # a view, its own photo


def test_the_edit_observer_finds_the_view_and_cannot_class_an_outcome_it_cannot_see():
    from jaxedit_lab.outcome_class import UNEDITED
    from jaxedit_lab.ablation import _edit_observer

    rng = np.random.default_rng(2)
    photos = rng.uniform(0.2, 0.8, (3, 8, 8, 3)).astype(np.float32)
    targets = np.stack([photos + 0.1, photos - 0.1])  # [K=2, N=3, ...]
    targets[1, 2] = photos[2]  # outcome 1 leaves view 2 as it is
    observe = _edit_observer(photos, targets)
    assert observe(photos[1] + 1e-4, targets[1, 1]) == (1, 1)  # a copy of view 1's photo
    assert observe(photos[0], photos[0]) == (0, UNEDITED)
    assert observe(photos[2], targets[0, 2]) == (2, "undefined")


def test_the_ip2p_weights_the_study_runs_are_the_ones_it_records(tmp_path):
    import shutil

    from jaxedit.editors import bundled_editor
    from jaxedit_lab.ablation import AblationConfig, _ip2p_folder, _weights_id

    bundled = AblationConfig(editor="ip2p")
    assert _ip2p_folder(bundled) == bundled_editor()
    other = tmp_path / "v1"
    shutil.copytree(bundled_editor(), other)
    (other / "unet" / "diffusion_pytorch_model.safetensors").write_bytes(b"other weights")
    pinned = AblationConfig(editor="ip2p", ip2p_weights=other)
    assert _ip2p_folder(pinned) == other
    assert len(_weights_id("ip2p", pinned)) == 16
    assert _weights_id("ip2p", pinned) != _weights_id("ip2p", bundled)
    assert _weights_id("simulated", AblationConfig()) is None
