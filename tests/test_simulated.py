"""The simulated editor (a test instrument, not IP2P) and the memoised difficulty oracle."""

from pathlib import Path

import jax
import numpy as np
import pytest
import skimage.data
import skimage.transform

from jaxedit.edit.difficulty import DifficultyOracle, l1_distance, ms_ssim_distance
from jaxedit.editors.base import Editor, interpolate_embedding
from jaxedit.edit.schedule import decompose, decompose_root
from jaxedit.editors.keys import view_key
from jaxedit_lab.simulated import VOCABULARY, SimulatedEditor
from jaxedit.errors import DataError

S = 32
FULL = (1.0, 1.0)  # SDEdit at t = 1: nothing of the current render survives


def object_view(dx: float) -> np.ndarray:
    """A face-textured ellipse on white, shifted by dx pixels (a turntable-like family)."""
    face = skimage.transform.resize(skimage.data.astronaut()[20:220, 150:350], (S, S),
                                    anti_aliasing=True).astype(np.float32)
    yy, xx = np.mgrid[0:S, 0:S] + 0.5
    inside = ((yy - S / 2) / (0.36 * S)) ** 2 + ((xx - S / 2 - dx) / (0.3 * S)) ** 2 < 1
    textured = np.roll(face, int(round(dx)), axis=1)
    return np.where(inside[..., None], textured, 1.0).astype(np.float32)


@pytest.fixture(scope="module")
def editor():
    return SimulatedEditor()


@pytest.fixture(scope="module")
def img():
    return object_view(0.0)


def emb(editor, prompt, r):
    return interpolate_embedding(editor.encode(prompt), editor.encode(""), r)


KEY = jax.random.key(3)
AUTUMN, SHAPE = VOCABULARY[0].prompt, VOCABULARY[4].prompt


def test_protocol_vocabulary_and_embeddings(editor):
    assert isinstance(editor, Editor) and editor.name == "simulated"
    assert len(editor.instructions) >= 4
    assert {v.kind for v in VOCABULARY} >= {"colour", "shape"}
    null = editor.encode("")
    assert null.shape == (8,) and editor.decode(null) == (None, 0.0)
    for i, p in enumerate(editor.instructions):
        e = editor.encode(p)
        assert not np.allclose(e, null)
        assert editor.encode("  " + p.upper() + ". ") == pytest.approx(e)
        for r in (0.0, 0.3, 1.0):
            idx, rr = editor.decode(interpolate_embedding(e, null, r))
            assert rr == pytest.approx(r, abs=1e-6) and (idx == i or r == 0.0)
    with pytest.raises(DataError, match="make it look like autumn"):
        editor.encode("make it a dragon")
    mix = 0.5 * editor.encode(editor.instructions[0]) + 0.5 * editor.encode(editor.instructions[1])
    with pytest.raises(DataError, match="embedding"):
        editor.decode(mix)
    with pytest.raises(DataError, match="below 0"):
        editor.decode(emb(editor, AUTUMN, -0.5))
    # past 1: an extended edit (edit --extend) extrapolates
    assert editor.decode(emb(editor, AUTUMN, 1.5))[1] == pytest.approx(1.5, abs=1e-6)


def test_targets_end_points_continuity_nonlinearity(editor, img):
    for p in editor.instructions:
        t0, t1 = editor.target(img, 0.0, p), editor.target(img, 1.0, p)
        np.testing.assert_allclose(t0, img, atol=1e-5)
        assert np.mean(np.abs(t1 - img)) > 0.02, p
        assert t1.dtype == np.float32 and t1.min() >= 0 and t1.max() <= 1
        rs = np.linspace(0, 1, 11)
        ts = [editor.target(img, r, p) for r in rs]
        dist = [np.mean(np.abs(t - img)) for t in ts]
        # continuous: a tiny change of r is a tiny change of the target
        assert np.mean(np.abs(editor.target(img, 0.501, p) - ts[5])) < 0.01 * dist[-1] + 1e-4
        # non-linear in r: the distance to the original is not proportional to r
        ratio = np.asarray(dist[1:]) / (rs[1:] * dist[-1])
        assert ratio.max() - ratio.min() > 0.2, p
    s = [editor.strength(r, 0) for r in np.linspace(0, 1, 21)]
    assert s[0] == pytest.approx(0) and s[-1] == pytest.approx(1) and np.all(np.diff(s) > 0)


def test_edit_end_points_and_timesteps(editor, img):
    # r = 0: the input comes back up to the noise floor
    for e in (editor.encode(""), emb(editor, AUTUMN, 0.0)):
        out = editor.edit(img, img, e, KEY, timestep_range=FULL)
        assert out.shape == img.shape and out.dtype == np.float32
        assert np.mean(np.abs(out - img)) < 0.01
    for p in (AUTUMN, SHAPE):
        t1 = editor.target(img, 1.0, p)
        # r = 1 from a render already at the target: the full target, up to the noise floor
        out = editor.edit(t1, img, emb(editor, p, 1.0), KEY, timestep_range=FULL)
        assert np.mean(np.abs(out - t1)) < 0.01
        # r = 1 from the original: a noisy jump that lands near the target
        outs = [editor.edit(img, img, emb(editor, p, 1.0), jax.random.key(k), timestep_range=FULL)
                for k in range(4)]
        mean = np.mean(outs, axis=0)
        assert np.mean(np.abs(mean - t1)) < 0.6 * np.mean(np.abs(img - t1)), p
    # t = 0 keeps the current render entirely; a higher t moves further towards the target
    e = emb(editor, AUTUMN, 1.0)
    assert np.allclose(editor.edit(img, img, e, KEY, timestep_range=(0.0, 0.0)), img, atol=1e-6)
    t1 = editor.target(img, 1.0, AUTUMN)
    gaps = [np.mean(np.abs(editor.edit(img, img, e, KEY, timestep_range=(t, t)) - t1))
            for t in (0.2, 0.5, 0.8)]
    assert gaps[0] > gaps[1] > gaps[2]


def test_determinism_and_view_keys(editor, img):
    e = emb(editor, SHAPE, 0.7)
    a = editor.edit(img, img, e, KEY)
    assert np.array_equal(a, editor.edit(img, img, e, KEY))
    assert not np.array_equal(a, editor.edit(img, img, e, jax.random.key(4)))
    run = jax.random.key(0)
    k = view_key(run, 2, 0.25, 7)
    same = view_key(run, 2, 0.25 + 1e-9, 7)  # ratios are quantised to 1e-6
    assert np.array_equal(jax.random.key_data(k), jax.random.key_data(same))
    others = [view_key(run, 3, 0.25, 7), view_key(run, 2, 0.26, 7), view_key(run, 2, 0.25, 8),
              view_key(jax.random.key(1), 2, 0.25, 7)]
    for o in others:
        assert not np.array_equal(jax.random.key_data(k), jax.random.key_data(o))
    with pytest.raises(DataError):
        view_key(run, -1, 0.5, 0)


def inconsistency(editor, image, original, e, keys=6):
    """Mean per-pixel standard deviation of the outputs over keys (views of a static image)."""
    outs = np.stack([editor.edit(image, original, e, jax.random.key(k), timestep_range=(0.7, 0.98))
                     for k in range(keys)])
    return float(np.mean(np.std(outs, axis=0)))


@pytest.mark.parametrize("prompt", [AUTUMN, SHAPE])
def test_inconsistency_grows_with_jump(editor, img, prompt):
    # from the original to r: bigger jumps, more inconsistent outputs
    jumps = [inconsistency(editor, img, img, emb(editor, prompt, r)) for r in (0.0, 0.4, 0.7, 1.0)]
    assert all(b > a for a, b in zip(jumps, jumps[1:])), jumps
    # the same target r = 1 from renders closer to it: smaller steps, more consistent outputs
    steps = [inconsistency(editor, editor.target(img, r0, prompt), img, emb(editor, prompt, 1.0))
             for r0 in (0.0, 0.5, 0.6, 1.0)]
    assert all(b < a for a, b in zip(steps, steps[1:])), steps
    # views of one object get targets consistent with each other: the edit follows the content
    v0, v1 = object_view(0.0), object_view(3.0)
    t0, t1 = editor.target(v0, 1.0, prompt), editor.target(v1, 1.0, prompt)
    inner = (slice(8, 24), slice(12, 20))
    np.testing.assert_allclose(np.roll(t0, 3, axis=1)[inner], t1[inner], atol=0.08)


def test_guidance_and_bad_inputs(editor, img):
    e = emb(editor, AUTUMN, 1.0)
    t1 = editor.target(img, 1.0, AUTUMN)
    def dev(g):
        out = editor.edit(img, img, e, KEY, guidance=g, timestep_range=FULL)
        return np.mean(np.abs(out - t1))

    assert dev((12.5, 1.5)) > dev((7.5, 1.5)) > dev((7.5, 3.0))
    with pytest.raises(DataError, match="image"):
        editor.edit(img[..., :2], img, e, KEY)
    with pytest.raises(DataError, match="differs"):
        editor.edit(img[:16], img, e, KEY)
    with pytest.raises(DataError, match="timestep_range"):
        editor.edit(img, img, e, KEY, timestep_range=(0.9, 0.1))
    with pytest.raises(DataError, match="NaN"):
        editor.edit(np.full_like(img, np.nan), img, e, KEY)
    with pytest.raises(DataError, match="noise"):
        SimulatedEditor(noise=-1.0)


def test_surface_points_make_texture_3d(img):
    yy, xx = np.mgrid[0:S, 0:S] / S
    points = np.stack([xx, yy, 0.5 * xx * yy], -1).astype(np.float32)
    geo = SimulatedEditor(surfaces=(img[None], points[None]))
    marble = VOCABULARY[3].prompt
    a, b = geo.target(img, 1.0, marble), SimulatedEditor().target(img, 1.0, marble)
    assert np.mean(np.abs(a - b)) > 1e-3
    # an original not registered falls back to the colour-based texture
    other = object_view(2.0)
    assert np.allclose(geo.target(other, 1.0, marble), SimulatedEditor().target(other, 1.0, marble))


def test_distances():
    a = object_view(0.0)
    assert ms_ssim_distance(a, a) == pytest.approx(0.0, abs=1e-9)
    b = np.clip(a + 0.1, 0, 1)
    c = np.clip(a + 0.3, 0, 1)
    assert 0 < ms_ssim_distance(a, b) < ms_ssim_distance(a, c)
    assert l1_distance(a, c) > l1_distance(a, b) > 0
    with pytest.raises(DataError, match="differ"):
        ms_ssim_distance(a, a[:16])


def test_oracle_memoises_per_ratio_and_view(editor):
    views = np.stack([object_view(dx) for dx in (-3.0, 0.0, 3.0)])
    oracle = DifficultyOracle(editor, views, SHAPE, seed=0)
    assert oracle.views == (0, 1, 2)
    assert oracle(0.3, 0.3) == 0.0 and oracle.editor_calls == 0
    d = oracle(0.0, 0.5)
    assert d > 0 and oracle.editor_calls == 6 and oracle(0.5, 0.0) == d and oracle.editor_calls == 6
    assert oracle(0.0, 1.0) > d  # the full edit is harder than half of it
    s = decompose(oracle, threshold=0.5 * oracle(0.0, 1.0), max_depth=4)
    assert len(s.ratios) >= 3
    asked = {r for pair in oracle._pairs for r in pair}
    assert oracle.editor_calls == len(asked) * len(views)  # each ratio edited once per view
    calls = oracle.editor_calls
    again = decompose(oracle, threshold=s.threshold, max_depth=4)
    assert again == s and oracle.editor_calls == calls  # all memo hits
    root = decompose_root(oracle, threshold=s.threshold, resolution=1 / 32)
    assert all(x <= s.threshold for x in root.difficulties) or root.depth_limit_hit
    asked = {r for pair in oracle._pairs for r in pair}
    assert oracle.editor_calls == len(asked) * len(views)
    # the difficulty curve is what the driver plots
    curve = oracle.curve([0.0, 0.5, 1.0])
    assert curve[0] == (0.0, 0.0) and curve[2][1] > curve[1][1] > 0
    with pytest.raises(DataError, match="views"):
        DifficultyOracle(editor, views, SHAPE, views=[5])


def test_surface_views_stamp_texture_on_the_surface():
    from jaxedit import scenes

    scene = scenes.get_scene("face")
    cams, _, _ = scenes.scene_cameras(scene, views=2, test_views=0, size=S)
    images = scenes.render_scene(scene, cams, supersample=1)
    geo = SimulatedEditor(surfaces=scenes.surface_views(scene, cams, images))
    marble = VOCABULARY[3].prompt
    png = np.round(images[1] * 255) / 255  # as read back from an 8-bit file
    a = geo.target(png, 1.0, marble)
    assert np.mean(np.abs(a - SimulatedEditor().target(png, 1.0, marble))) > 1e-3
    assert np.allclose(a, geo.target(images[1], 1.0, marble), atol=0.02)


def test_oracle_common_noise_makes_difficulty_continuous(editor):
    views = np.stack([object_view(dx) for dx in (-3.0, 3.0)])
    common = DifficultyOracle(editor, views, AUTUMN)
    fresh = DifficultyOracle(editor, views, AUTUMN, common_noise=False)
    full = common(0.0, 1.0)
    near = [common(0.7, 0.7 + h) for h in (0.1, 0.01, 0.001)]
    assert near[0] > near[1] > near[2] and near[2] < 0.01 * full
    # per-ratio keys add the seed-to-seed variation: a floor that does not vanish as h -> 0
    assert fresh(0.7, 0.701) > 10 * near[2]


# ---- divergent modes (module docstring, section 4) -----------------------------------------

GOLDEN = Path(__file__).parent / "data" / "simulated_modes1_golden.npz"


def test_modes1_is_bit_for_bit_the_editor_before_modes():
    # Outputs recorded with the editor before divergent modes existed (commit 8da66cf): the
    # single-outcome editor must keep reproducing them, so earlier figures stay reproducible.
    g = np.load(GOLDEN)
    ed = SimulatedEditor(modes=1)
    for i, ins in enumerate(VOCABULARY):
        e = emb(ed, ins.prompt, 0.6)
        a = ed.edit(g["render"], g["original"], e, jax.random.key(7 + i))
        b = ed.edit(g["render"], g["original"], e, jax.random.key(11), timestep_range=(0.6, 0.6),
                    guidance=(9.0, 1.2))
        assert np.array_equal(a, g[f"edit_{i}"]), ins.kind
        assert np.array_equal(b, g[f"edit_fixed_t_{i}"]), ins.kind
        assert np.array_equal(ed.target(g["original"], 0.8, i), g[f"target_{i}"]), ins.kind
        assert ed.edit_with_mode(g["render"], g["original"], e, jax.random.key(1))[1] == 0


@pytest.fixture(scope="module")
def modal():
    return SimulatedEditor(modes=3)


def test_modes_are_distinct_consistent_targets(modal, img):
    for i, ins in enumerate(VOCABULARY):
        t = modal.mode_targets(img, 1.0, i)
        assert t.shape == (3, *img.shape)
        np.testing.assert_array_equal(t[0], SimulatedEditor().target(img, 1.0, i))
        for a in range(3):
            np.testing.assert_allclose(modal.target(img, 0.0, i, a), img, atol=1e-5)
            for b in range(a):
                assert np.mean(np.abs(t[a] - t[b])) > 0.01, (ins.kind, a, b)
        # each mode follows the content like mode 0: shifted views get shifted targets
        v0, v1 = object_view(0.0), object_view(3.0)
        inner = (slice(8, 24), slice(12, 20))
        for k in range(3):
            np.testing.assert_allclose(np.roll(modal.target(v0, 1.0, i, k), 3, axis=1)[inner],
                                       modal.target(v1, 1.0, i, k)[inner], atol=0.08)
    with pytest.raises(DataError, match="mode"):
        modal.target(img, 1.0, 0, mode=3)
    with pytest.raises(DataError, match="mode"):
        SimulatedEditor().target(img, 1.0, 0, mode=1)
    for bad in (0, 4, 2.5, True):
        with pytest.raises(DataError, match="modes"):
            SimulatedEditor(modes=bad)


@pytest.mark.parametrize("index", range(len(VOCABULARY)))
def test_mode_draw_keeps_a_mode_the_render_shows_and_mixes_from_the_original(modal, img, index):
    calls = 20
    for r in (1.0, 0.6):
        e = emb(modal, VOCABULARY[index].prompt, r)
        targets = modal.mode_targets(img, r, index)
        for k in range(3):
            drawn = [modal.edit_with_mode(targets[k], img, e, jax.random.key(j))
                     for j in range(calls)]
            assert sum(m == k for _, m in drawn) >= 0.95 * calls, (r, k)
            # the output is the edit towards the drawn mode: nearest to that mode's target
            out = drawn[0][0]
            assert np.argmin([np.mean(np.abs(out - t)) for t in targets]) == k
    # from the original scene at r = 1 (far from every mode) every mode occurs
    e = emb(modal, VOCABULARY[index].prompt, 1.0)
    seen = {modal.edit_with_mode(img, img, e, jax.random.key(j))[1] for j in range(40)}
    assert seen == {0, 1, 2}


def _pair_distance(images):
    k = len(images)
    return np.mean([np.mean(np.abs(images[a] - images[b])) for a in range(k) for b in range(a)])


def test_mode_draw_follows_the_documented_equation(modal, img):
    # A NumPy oracle of section 4 for a cross-fade kind (material): T^k(s) = o + s (F_k - o).
    from jaxedit_lab.simulated import mode_probabilities

    r, t = 0.7, 0.6
    e = emb(modal, VOCABULARY[1].prompt, r)
    full = modal.mode_targets(img, 1.0, 1)
    path = lambda k, s: np.clip(img + s * (full[k] - img), 0, 1)  # noqa: E731
    render = np.clip(0.6 * path(0, 0.5) + 0.4 * path(2, 0.5), 0, 1).astype(np.float32)
    grid = np.linspace(0, 1, 21)
    dist = np.array([[np.mean(np.abs(render - path(k, s))) for s in grid] for k in range(3)])
    e_k, best = dist.min(axis=1), dist.argmin(axis=1)
    k_hat = int(np.argmin(e_k))
    z = (e_k - e_k.min()) / (_pair_distance([path(k, grid[best[k_hat]]) for k in range(3)])
                             + 0.004)
    s = modal.strength(r, 1)
    rho = np.mean(np.abs(render - path(k_hat, s))) / (
        _pair_distance([path(k, s) for k in range(3)]) + 0.004)
    tau = 0.15 * t * (1 + rho ** 2)
    want = np.exp(-z / tau) / np.exp(-z / tau).sum()
    got = modal.mode_probabilities(render, img, e, t)
    np.testing.assert_allclose(got, want, rtol=2e-3, atol=1e-5)
    np.testing.assert_allclose(mode_probabilities(z, rho, t, temperature=0.15, step_gain=1.0),
                               want, rtol=1e-6)
    assert got[0] > got[2] > got[1]  # closer to mode 0 than to 2; mode 1 is not in the blend
    # the temperature rises with the SDEdit timestep: a noisier edit holds the mode less
    assert modal.mode_probabilities(render, img, e, 0.9)[0] < got[0] \
        < modal.mode_probabilities(render, img, e, 0.3)[0]
    # the original shows no mode: a uniform draw whatever the step
    np.testing.assert_allclose(modal.mode_probabilities(img, img, e, t), 1 / 3, atol=1e-6)


def _stay(editor, img, index, r_from, r_to, t):
    """Mean over modes c of P(stay in c) from a render equal to T^c(r_from), editing at r_to."""
    targets = editor.mode_targets(img, r_from, index)
    e = emb(editor, VOCABULARY[index].prompt, r_to)
    return np.mean([editor.mode_probabilities(targets[c], img, e, t)[c] for c in range(3)])


@pytest.mark.parametrize("index,subtasks", [(3, 4), (4, 8)])  # texture ~4, shape ~8 (paper)
def test_committed_mode_stays_across_the_schedulers_steps(modal, img, index, subtasks):
    # The measurement: from a render set exactly to mode c's target at r_{i-1}, the
    # chance of staying in c at the scheduler's next r_i (it was 0.07-0.08 for shape).
    from jaxedit.edit.schedule import for_target_subtasks

    views = np.stack([object_view(dx) for dx in (-3.0, 0.0, 3.0)])
    oracle = DifficultyOracle(modal, views, VOCABULARY[index].prompt, seed=0, reduction="mean")
    ratios = for_target_subtasks(oracle, subtasks).ratios
    off = SimulatedEditor(modes=3, mode_step_gain=0.0)
    t_min, t_max = 0.45, 0.85  # the driver's annealed SDEdit range
    checked = 0
    for a, b in zip(ratios[1:], ratios[2:]):
        if modal.strength(a, index) < 0.3:  # the modes cannot be told apart yet
            continue
        checked += 1
        assert _stay(modal, img, index, a, b, t_min) > 0.95, (a, b)
        assert _stay(modal, img, index, a, b, t_max) > 0.8, (a, b)
        # with the knob on, holding falls with the step: the whole rest of the edit at once
        # holds less; with it off, the draw does not depend on the step at all
        if b < 1.0:
            assert _stay(modal, img, index, a, 1.0, t_max) < _stay(modal, img, index, a, b, t_max)
        assert _stay(off, img, index, a, 1.0, t_max) == pytest.approx(
            _stay(off, img, index, a, b, t_max), abs=1e-6)
    assert checked >= 2, ratios


def test_mode_draw_same_key_same_output(modal, img):
    e = emb(modal, SHAPE, 1.0)
    a = modal.edit_with_mode(img, img, e, KEY)
    b = modal.edit_with_mode(img, img, e, KEY)
    assert a[1] == b[1] and np.array_equal(a[0], b[0])
    assert np.array_equal(modal.edit(img, img, e, KEY), a[0])
    outs = [modal.edit_with_mode(img, img, e, jax.random.key(j)) for j in range(6)]
    assert len({o[0].tobytes() for o in outs}) == 6
