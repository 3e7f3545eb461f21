"""The outcome measure with an "unedited" class (jaxedit_lab.outcome_class, issue 51):
the unedited input scores "unedited", a pure outcome target its outcome, a 50/50 blend of two
outcomes "mixed", for every divergent instruction the bundled editor was trained on."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from jaxedit_lab import outcome_class as oc


@pytest.fixture(scope="module")
def divergent():
    """(input, targets [K, H, W, 3], prompt) of every divergent instruction on a few views."""
    from jaxedit_lab.train_editor.edit_data import build_dataset, outcome_targets

    data = build_dataset(32, 4, ("face",))
    out = []
    for i, ins in enumerate(data.instructions):
        if len(ins.outcomes) < 2:
            continue
        for v in range(len(data.inputs)):
            if ins.applies_to(data.scenes[data.scene[v]]):
                out.append((data.inputs[v].astype(np.float32) / 255,
                            outcome_targets(data, v, i), ins.prompt))
    assert {p for *_, p in out} == {"splash some colour on it", "add a neon accent"}
    return out


def test_input_target_and_blend_classes_for_every_divergent_instruction(divergent):
    for u, t, prompt in divergent:
        assert oc.classify(u, u, t)["label"] == oc.UNEDITED, prompt
        for k in range(len(t)):
            c = oc.classify(t[k], u, t)
            assert c["label"] == k and c["weights"][k] == pytest.approx(1.0, abs=1e-6), prompt
        for j, k in itertools.combinations(range(len(t)), 2):
            c = oc.classify(0.5 * t[j] + 0.5 * t[k], u, t)
            assert c["label"] == oc.MIXED and c["purity"] == pytest.approx(0.5, abs=1e-6), prompt
        # an even blend of all of them mixes too (the old measure's "average" case)
        assert oc.classify(t.mean(0), u, t)["label"] == oc.MIXED
        # a quarter of the way to an outcome is not yet an edit; three quarters is one
        assert oc.classify(0.75 * u + 0.25 * t[0], u, t)["label"] == oc.UNEDITED
        assert oc.classify(0.25 * u + 0.75 * t[0], u, t)["label"] == 0


def test_changes_no_outcome_explains_are_other_and_small_noise_is_not(divergent):
    rng = np.random.default_rng(0)
    for u, t, prompt in divergent:
        scale = np.sqrt(np.mean((t - u) ** 2))
        # a colour cast over the whole view, twice a typical outcome's change: other
        cast = np.clip(u + 2 * scale * np.array([1.0, -1.0, 1.0], np.float32), 0, 1)
        assert oc.classify(cast, u, t)["label"] == oc.OTHER, prompt
        # ... unless the gate is off: then it is wherever it leans
        assert oc.classify(cast, u, t, other_gate=False)["label"] != oc.OTHER
        # noise at a fifth of an outcome's change on the input: still unedited; on a target:
        # still that outcome
        noise = rng.normal(0, 0.2 * scale, u.shape).astype(np.float32)
        assert oc.classify(u + noise, u, t)["label"] == oc.UNEDITED, prompt
        assert oc.classify(t[1] + noise, u, t)["label"] == 1, prompt


def test_summary_counts_over_edited_draws_only():
    labels = [oc.UNEDITED, oc.UNEDITED, 0, 0, 1, 2, oc.MIXED, oc.OTHER]
    s = oc.summarise(labels, 3)
    assert s["draws"] == 8 and s["edited"] == 6
    assert s["unedited_fraction"] == pytest.approx(2 / 8)
    assert s["single_outcome_fraction"] == pytest.approx(4 / 6)
    assert s["outcome_frequencies"] == pytest.approx([2 / 6, 1 / 6, 1 / 6])
    assert s["mixed_fraction"] == pytest.approx(1 / 6) and s["other_fraction"] == pytest.approx(1 / 6)
    none = oc.summarise([oc.UNEDITED] * 3, 3)
    assert none["unedited_fraction"] == 1.0 and none["single_outcome_fraction"] is None


def test_view_bootstrap_intervals_follow_the_views_not_the_draws():
    # Every view with the same mix of draws: no spread between views, so the interval is
    # the point itself, whatever the number of draws.
    same = [0, 0, 1, oc.MIXED] * 10
    s = oc.summarise(same, 2, groups=np.repeat(np.arange(10), 4))
    assert s["intervals"]["outcome_frequencies"][0] == pytest.approx([0.5, 0.5])
    assert s["intervals"]["single_outcome_fraction"] == pytest.approx([0.75, 0.75])
    # Each view's 4 draws in one outcome, 12 of 30 views in outcome 0: the interval is that of
    # 30 views (binomial sd sqrt(.4 * .6 / 30) = 0.089), not of 120 draws (0.045).
    views = np.repeat(np.arange(30), 4)
    labels = [0 if v < 12 else 1 for v in views]
    s = oc.summarise(labels, 2, groups=views, seed=3)
    low, high = s["intervals"]["outcome_frequencies"][0]
    assert low < 0.4 < high
    assert (high - low) / (2 * 1.96) == pytest.approx(np.sqrt(0.4 * 0.6 / 30), rel=0.15)
    assert s["intervals"]["views"] == 30 and s["intervals"]["resamples"] == oc.BOOTSTRAP
    assert oc.summarise(labels, 2, groups=views, seed=3) == s  # seeded
    with pytest.raises(ValueError, match="groups"):
        oc.summarise(labels, 2, groups=views[:-1])


def test_view_spread_tells_a_choice_by_view_from_a_choice_by_draw():
    # Balanced pooled shares and one outcome in every draw both ways; only the spread differs.
    views = np.repeat(np.arange(30), 4)
    by_view = [int(v % 3) for v in views]
    s = oc.view_spread(by_view, views, 3)
    assert s == {"views": 30, "spread": 0.0, "expected": pytest.approx(1 - 3 / 3 ** 4)}
    assert oc.summarise(by_view, 3)["outcome_frequencies"] == pytest.approx([1 / 3] * 3)
    by_draw = list(np.random.default_rng(0).integers(0, 3, len(views)))
    s = oc.view_spread(by_draw, views, 3)
    assert s["spread"] == pytest.approx(s["expected"], abs=0.1) and s["spread"] > 0.8
    # Draws off every outcome do not count; a view left with one outcome draw is not judged.
    s = oc.view_spread([0, 1, oc.MIXED, oc.UNEDITED, 2, oc.OTHER], [0, 0, 0, 1, 1, 1], 3)
    assert s["views"] == 1 and s["spread"] == 1.0
    assert s["expected"] == pytest.approx(1 - 2 * 0.5 ** 2)
    assert oc.view_spread([oc.MIXED, 0], [0, 0], 3) == {"views": 0, "spread": None,
                                                         "expected": None}
    with pytest.raises(ValueError, match="groups"):
        oc.view_spread([0, 1], [0], 3)


def test_an_outcome_equal_to_the_input_is_refused():
    u = np.full((4, 4, 3), 0.5, np.float32)
    with pytest.raises(ValueError, match="equals the input"):
        oc.classify(u, u, np.stack([u, u + 0.1]))


def test_band_figures_place_a_change_inside_or_outside_the_outcome_s_band(divergent):
    """band_figures: a target itself changes only its band at gain 1 in its direction; the
    same change at twice the strength, gain 2; a target plus a cast over the whole view
    puts part of its change outside the band."""
    from jaxedit_lab.train_editor.quality import band_figures

    for u, t, prompt in divergent:
        k = len(t)
        exact = band_figures(t, np.stack([u] * k), np.stack([t] * k))
        assert exact["outside_band"] == pytest.approx(0.0, abs=1e-4), prompt  # rounding
        assert exact["gain_in_band"] == pytest.approx(1.0, abs=1e-4), prompt
        assert exact["cosine_in_band"] == pytest.approx(1.0, abs=1e-4), prompt
        twice = band_figures(u + 2 * (t - u), np.stack([u] * k), np.stack([t] * k))
        assert twice["gain_in_band"] == pytest.approx(2.0, abs=1e-4), prompt
        cast = band_figures(t + 0.1, np.stack([u] * k), np.stack([t] * k))
        assert 0.2 < cast["outside_band"] < 1, prompt


def test_outcome_figures_per_scene_and_by_view(divergent):
    """outcome_figures with views and scenes: each scene's draws summarised alone, and a
    choice by the view (every draw of a view the same outcome) seen as no spread."""
    from jaxedit_lab.train_editor.quality import outcome_figures

    u, t, prompt = divergent[0]
    assert len(t) == 3, prompt
    # Two views of one scene, one of another; each view always the same outcome.
    views = [0, 0, 1, 1, 2, 2]
    picks = [0, 0, 1, 1, 2, 2]
    images = np.stack([t[c] for c in picks])
    figures = outcome_figures(images, np.stack([u] * 6), np.stack([t] * 6), views=views,
                              scenes=["a", "a", "a", "a", "b", "b"])
    assert figures["outcome_frequencies"] == pytest.approx([1 / 3] * 3), prompt
    assert figures["view_spread"] == {"views": 3, "spread": 0.0,
                                      "expected": pytest.approx(1 - 3 / 9)}
    assert figures["per_scene"]["a"]["outcome_frequencies"] == pytest.approx([0.5, 0.5, 0])
    assert figures["per_scene"]["b"]["outcome_frequencies"] == pytest.approx([0, 0, 1])
    assert figures["per_scene"]["b"]["draws"] == 2
