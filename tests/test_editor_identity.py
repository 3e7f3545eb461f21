"""Issue 77: the editor's identity checked before an edit trains, detail-keeping targets for
views larger than the editor's size, and how far every snapshot moved from the input."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxedit import DataError
from jaxedit import camera as cl
from jaxedit import gaussians as gl
from jaxedit.edit import EditData, ProEditConfig, EditTrainConfig
from jaxedit.edit.difficulty import DifficultyOracle
from jaxedit.edit.identity import (IdentityFloor, LowIdentityError, identity_problem,
                                   measure_identity)
from jaxedit.edit.outputs import Renderer, distance_to_input
from jaxedit.editors.compose import (DeltaTargets, DetailTargets, compose_target,
                                     measuring_editor, with_targets)
from jaxedit.editors.base import interpolate_embedding
from jaxedit.editors.jax_ip2p import resize_images

PROMPT = "turn him into a bronze statue"


class Identity:
    """An editor that gives back the view it is shown (a perfect identity at every e(r))."""

    name = "identity"
    guidance = (7.5, 1.5)

    def encode(self, prompt):
        return np.zeros((4,), np.float32)

    def edit(self, image, original, embedding, key, **kwargs):
        return np.asarray(image, np.float32)


class Counting(Identity):
    """:class:`Identity` that records the SDEdit range of every editor call."""

    def __init__(self):
        self.calls = []

    def edit(self, image, original, embedding, key, **kwargs):
        self.calls.append(kwargs["timestep_range"])
        return super().edit(image, original, embedding, key)


def test_the_check_is_the_schedules_edits_at_r0():
    """One editor call per difficulty view, and d(0, r) edits only at r afterwards."""
    views = _views(5)
    editor = Counting()
    oracle = DifficultyOracle(editor, views, PROMPT, views=[0, 3, 4], seed=0)
    figures = measure_identity(oracle, views)
    t = oracle.timestep_range
    assert editor.calls == [t] * 3 and figures["editor_calls"] == 3
    assert figures["views"] == [0, 3, 4] and figures["timestep"] == t[1]
    oracle(0.0, 1.0)
    assert len(editor.calls) == 6  # the three views at r = 1 only
    again = measure_identity(oracle, views)  # the memo: no call
    assert len(editor.calls) == 6 and again["editor_calls"] == 0
    assert again["psnr"] == figures["psnr"]


def _views(n=3, size=32, seed=0):
    rng = np.random.default_rng(seed)
    base = rng.uniform(0.2, 0.8, (n, 1, 1, 3))
    ys, xs = np.mgrid[0:size, 0:size] / size
    texture = 0.15 * np.sin(12 * xs + 7 * ys)[None, ..., None]
    return np.clip(base + texture, 0, 1).astype(np.float32)


def test_distance_to_input_is_zero_for_the_input_and_grows_with_change():
    views = _views()
    same = distance_to_input(views, views)
    assert same["psnr_vs_input"] == 100.0 and same["ssim_vs_input"] == pytest.approx(1.0)
    assert same["lpips_vs_input"] == pytest.approx(0.0, abs=1e-6)
    rng = np.random.default_rng(1)
    small = np.clip(views + rng.normal(0, 0.02, views.shape), 0, 1).astype(np.float32)
    large = np.clip(views + rng.normal(0, 0.2, views.shape), 0, 1).astype(np.float32)
    a, b = distance_to_input(small, views), distance_to_input(large, views)
    assert 30 < a["psnr_vs_input"] < 40 and b["psnr_vs_input"] < a["psnr_vs_input"] - 10
    assert b["lpips_vs_input"] > a["lpips_vs_input"] and b["ssim_vs_input"] < a["ssim_vs_input"]


@pytest.mark.slow
def test_identity_of_a_perfect_and_of_a_random_editor():
    from ip2p_standins import standin_editor

    views = _views(4)
    floor = IdentityFloor()
    good = measure_identity(DifficultyOracle(Identity(), views, PROMPT, views=[0, 2]), views)
    assert good["psnr"] == 100.0 and good["views"] == [0, 2] and good["editor_calls"] == 2
    assert identity_problem(good, floor) is None
    poor = standin_editor(size=32, steps=2)  # random weights: a deliberately poor editor
    bad = measure_identity(DifficultyOracle(poor, views, PROMPT, views=[0, 1, 3]), views)
    assert bad["editor_calls"] == 3 and len(bad["psnr_per_view"]) == 3
    problem = identity_problem(bad, floor)
    assert problem is not None and f"floor {floor.min_psnr:g} dB" in problem


def test_compose_target_keeps_the_views_detail_and_adds_the_change():
    views = jnp.asarray(_views(2, size=64))
    small = resize_images(views, (16, 16))
    # no change at the editor's size: the target is the view itself, every bit of it
    assert np.array_equal(np.asarray(compose_target(views, small, small)), np.asarray(views))
    shifted = np.asarray(compose_target(views, small, small + 0.1))
    np.testing.assert_allclose(shifted, np.clip(np.asarray(views) + 0.1, 0, 1), atol=1e-6)


def test_detail_targets_only_change_views_larger_than_the_editor():
    from ip2p_standins import standin_editor

    inner = standin_editor(size=16, steps=2)
    wrapped = with_targets(inner, "detail")
    assert isinstance(wrapped, DetailTargets) and with_targets(inner, "stretch") is inner
    assert wrapped.name == inner.name and wrapped.batch == inner.batch
    e = inner.encode("")
    keys = jax.random.split(jax.random.key(0), 2)
    at_size = jnp.asarray(_views(2, size=16))
    # views at the editor's size: exactly the editor's edit
    assert np.array_equal(np.asarray(wrapped.edit_many(at_size, at_size, e, keys)),
                          np.asarray(inner.edit_many(at_size, at_size, e, keys)))
    big = jnp.asarray(_views(2, size=48))
    got = np.asarray(wrapped.edit_many(big, big, e, keys))
    small = resize_images(big, (16, 16))
    want = compose_target(big, small, inner.edit_many(small, small, e, keys))
    assert got.shape == (2, 48, 48, 3) and np.array_equal(got, np.asarray(want))
    one = np.asarray(wrapped.edit(big[0], big[0], e, keys[0]))
    np.testing.assert_allclose(one, got[0], atol=1e-6)
    with pytest.raises(DataError, match="targets"):
        with_targets(inner, "sharpest")
    # the paired edits in one call are the editor's two edits made apart
    delta = with_targets(inner, "delta")
    e_p = inner.encode(PROMPT)
    got = np.asarray(delta.edit_many(big, big, e_p, keys))
    want = compose_target(big, inner.edit_many(small, small, e, keys),
                          inner.edit_many(small, small, e_p, keys))
    np.testing.assert_allclose(got, np.asarray(want), atol=1e-5)
    assert np.abs(got - np.asarray(big)).max() > 1e-3  # the instruction changed something


class Shifting:
    """An editor of a 16 px model size whose edit darkens the view (an identity error), adds
    ``per_embedding`` times the embedding's mean and a noise drawn from the view's key."""

    name = "shifting"
    guidance = (7.5, 1.5)

    def __init__(self, per_embedding=0.002, batch=4):
        self.per_embedding, self.batch, self.calls = per_embedding, batch, []

    def model_hw(self, height, width):
        return (16, 16)

    def encode(self, prompt):
        return np.full((2, 3), float(len(prompt)), np.float32)

    def edit_many(self, images, originals, embeddings, keys, **kwargs):
        images = jnp.asarray(images, jnp.float32)
        b = images.shape[0]
        self.calls.append(b)
        emb = jnp.broadcast_to(jnp.asarray(embeddings, jnp.float32), (b, 2, 3))
        noise = jax.vmap(lambda k: jax.random.uniform(k, images.shape[1:], minval=-0.05,
                                                      maxval=0.05))(keys)
        shift = self.per_embedding * emb.mean((1, 2))[:, None, None, None]
        return 0.8 * images + 0.1 + shift + noise


def test_delta_targets_add_only_the_instructions_change_with_paired_keys():
    inner = Shifting()
    delta = with_targets(inner, "delta")
    assert isinstance(delta, DeltaTargets) and delta.batch == 4 and delta.name == "shifting"
    big = jnp.asarray(_views(3, size=48))
    keys = jax.random.split(jax.random.key(0), 3)
    e_p, e_null = inner.encode(PROMPT), inner.encode("")
    e_half = interpolate_embedding(e_p, e_null, 0.5)
    got = np.asarray(delta.edit_many(big, big, e_half, keys))
    # calls of both edits of half the editor's batch of views; the darkening and each key's
    # noise cancel
    assert inner.calls == [4, 2]
    shift = inner.per_embedding * float(e_half.mean())
    np.testing.assert_allclose(got, np.clip(np.asarray(big) + shift, 0, 1), atol=1e-5)
    # the detail composition keeps the editor's identity error and the noise
    detail = np.asarray(with_targets(inner, "detail").edit_many(big, big, e_half, keys))
    assert np.abs(detail - got).mean() > 0.02
    # per-view embeddings: each view's own change
    per_view = jnp.stack([e_null, e_half, e_p])
    got = np.asarray(delta.edit_many(big, big, per_view, keys))
    for i, e in enumerate(per_view):
        np.testing.assert_allclose(got[i], np.clip(np.asarray(big[i]) + inner.per_embedding
                                                   * float(e.mean()), 0, 1), atol=1e-5)
    one = np.asarray(delta.edit(big[1], big[1], e_half, keys[1]))
    np.testing.assert_allclose(one, np.clip(np.asarray(big[1]) + shift, 0, 1), atol=1e-5)


def test_delta_targets_are_the_view_where_the_instruction_changes_nothing():
    big = jnp.asarray(_views(2, size=48))
    keys = jax.random.split(jax.random.key(1), 2)
    # an editor whose e(r) edit equals its e(0) edit: every target is the view, bit for bit
    blind = Shifting(per_embedding=0.0)
    got = DeltaTargets(blind).edit_many(big, big, blind.encode(PROMPT), keys)
    assert np.array_equal(np.asarray(got), np.asarray(big)) and blind.calls == [4]
    # an editor of batch 1 (the CPU's) still gets a view's pair in one call
    single = Shifting(per_embedding=0.0, batch=1)
    DeltaTargets(single).edit_many(big, big, single.encode(PROMPT), keys)
    assert single.calls == [2, 2]
    # e(0): the change is zero by construction, no editor call
    inner = Shifting()
    at_zero = interpolate_embedding(inner.encode(PROMPT), inner.encode(""), 0.0)
    got = DeltaTargets(inner).edit_many(big, big, at_zero, keys)
    assert np.array_equal(np.asarray(got), np.asarray(big)) and inner.calls == []
    # views at the editor's size: the editor's own edit
    small = jnp.asarray(_views(2, size=16))
    want = inner.edit_many(small, small, inner.encode(PROMPT), keys)
    got = DeltaTargets(inner).edit_many(small, small, inner.encode(PROMPT), keys)
    assert np.array_equal(np.asarray(got), np.asarray(want))


def test_anchored_pairs_take_e0s_identity_error_on_the_photo():
    inner = Shifting()
    anchored = with_targets(inner, "anchored")
    assert isinstance(anchored, DeltaTargets) and anchored.reference == "photo"
    big = jnp.asarray(_views(2, size=48))
    photos = jnp.asarray(_views(2, size=48, seed=5))
    keys = jax.random.split(jax.random.key(3), 2)
    e_p = inner.encode(PROMPT)
    shift = inner.per_embedding * float(e_p.mean())
    # the render is its photo: only the instruction's change, the key's noise cancelled
    got = np.asarray(anchored.edit_many(big, big, e_p, keys))
    np.testing.assert_allclose(got, np.clip(np.asarray(big) + shift, 0, 1), atol=1e-5)
    assert inner.calls == [4]
    at_zero = np.asarray(anchored.edit_many(big, big, inner.encode(""), keys))
    np.testing.assert_allclose(at_zero, np.asarray(big), atol=1e-5)
    assert inner.calls == [4, 4]  # e(0) is edited: the render and the photo may differ
    # else the editor's darkening of the render less its darkening of the photo remains
    got = np.asarray(anchored.edit_many(big, photos, e_p, keys))
    small, ref = resize_images(big, (16, 16)), resize_images(photos, (16, 16))
    want = compose_target(big, small, small + shift - 0.2 * (small - ref))
    np.testing.assert_allclose(got, np.asarray(want), atol=1e-5)


def test_hybrid_targets_are_the_view_at_e0_and_detail_after():
    inner = Shifting()
    hybrid = with_targets(inner, "hybrid")
    assert isinstance(hybrid, DetailTargets) and hybrid.keep_null
    big = jnp.asarray(_views(2, size=48))
    keys = jax.random.split(jax.random.key(4), 2)
    got = hybrid.edit_many(big, big, inner.encode(""), keys)
    assert np.array_equal(np.asarray(got), np.asarray(big)) and inner.calls == []
    e_p = inner.encode(PROMPT)
    detail = with_targets(inner, "detail").edit_many(big, big, e_p, keys)
    assert np.array_equal(np.asarray(hybrid.edit_many(big, big, e_p, keys)), np.asarray(detail))
    assert inner.calls == [2, 2]


def test_delta_targets_batch_the_pairs_within_the_editors_batch():
    from jaxedit.editors.base import edit_views

    inner = Shifting(batch=4)
    big = jnp.asarray(_views(5, size=32))
    keys = jax.random.split(jax.random.key(2), 5)
    e = inner.encode(PROMPT)
    got = edit_views(DeltaTargets(inner), big, big, e, keys)
    # edit_views' chunks of the editor's batch, each in pairs of 2 views
    assert inner.calls == [4, 4, 2]
    whole = DeltaTargets(Shifting(batch=16)).edit_many(big, big, e, keys)
    np.testing.assert_allclose(np.stack(got), np.asarray(whole), atol=1e-6)


def test_the_identity_check_and_the_oracle_measure_the_editor_not_the_pairing():
    inner = Shifting()
    delta = with_targets(inner, "delta")
    measuring = measuring_editor(delta)
    assert isinstance(measuring, DetailTargets) and not isinstance(measuring, DeltaTargets)
    assert measuring.editor is inner
    detail = with_targets(inner, "detail")
    assert measuring_editor(detail) is detail and measuring_editor(inner) is inner
    for name in ("anchored", "hybrid"):
        m = measuring_editor(with_targets(inner, name))
        assert type(m) is DetailTargets and not m.keep_null and m.editor is inner
    views = _views(3, size=48)
    figures = measure_identity(DifficultyOracle(measuring, views, PROMPT, views=[0, 2]), views)
    # the darkening: far from the 100 dB the pairing would report at e(0)
    assert figures["psnr"] < 40 and figures["editor_calls"] == 2


# ---------------------------------------------------------------------------
# Whole runs on a tiny scene: 8 train + 2 held-out views of a coloured ball, 32 x 32
# ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    g = gl.from_points(d * 0.5, np.clip(0.5 + 0.4 * d[:, [2, 0, 1]], 0, 1), sh_degree=1,
                       init_opacity=0.8)
    g = dataclasses.replace(g, log_scales=g.log_scales + 0.3)
    cams = cl.orbit(10, radius=2.5, width=32, height=32, elevation_deg=15)
    renderer = Renderer()
    images = np.stack([renderer.rgb(g, cams[i]) for i in range(10)])
    return g, EditData.create(images[:8], cams[np.arange(8)], images[8:], cams[np.arange(8, 10)])


TINY = dict(warmup=6, patience=8, loss_window=4, max_steps=24, edit_every=3, checkpoint_every=5,
            subtasks=1, consolidate=False, asynchronous=False, turntable_frames=0,
            difficulty_views=3)


def test_a_random_editor_is_stopped_before_training_with_only_the_record(tiny, tmp_path):
    from ip2p_standins import standin_editor

    from jaxedit.pipelines import run_edit

    g, data = tiny
    run_dir = tmp_path / "run"
    with pytest.raises(LowIdentityError) as err:
        run_edit(standin_editor(size=32, steps=2), PROMPT, data, g,
                 config=ProEditConfig.for_mode("proedit", **TINY), seed=0, run_dir=run_dir,
                 report=False)
    message = str(err.value)
    assert "\n" not in message and "--ip2p-weights" in message
    assert "--accept-low-identity" in message and "dB < floor" in message
    assert sorted(p.name for p in run_dir.iterdir()) == ["identity.json"]
    record = json.loads((run_dir / "identity.json").read_text())
    assert record["passed"] is False and record["editor_calls"] == 3
    assert record["views"] == json.loads(json.dumps(err.value.figures["views"]))


@pytest.fixture(scope="module")
def simulated_run(tiny, tmp_path_factory):
    from jaxedit_lab.simulated import SimulatedEditor

    from jaxedit.pipelines import run_edit

    g, data = tiny
    run_dir = tmp_path_factory.mktemp("identity")
    lines = []
    # a refinement floor no real r_0 clears, so that its warning must be logged
    out = run_edit(SimulatedEditor(), PROMPT, data, g,
                   config=ProEditConfig.for_mode("proedit", **TINY),
                   settings=EditTrainConfig(lr_sh_dc=0.05), seed=1, run_dir=run_dir,
                   log=lines.append, identity=IdentityFloor(refine_min_psnr=99.0))
    return run_dir, out, lines


@pytest.mark.slow
def test_the_simulated_editor_passes_and_every_snapshot_says_how_far_it_moved(simulated_run,
                                                                               tiny):
    run_dir, out, lines = simulated_run
    g, _ = tiny
    sched = json.loads((run_dir / "schedule.json").read_text())
    ident = sched["identity"]
    assert ident["passed"] and ident["editor_calls"] == len(ident["views"]) == 3
    assert ident["timestep"] == DifficultyOracle.__init__.__kwdefaults__["timestep_range"][1]
    assert ident["editor_calls"] == len(ident["views"])
    assert any(line.startswith("editor identity on this scene: PSNR") for line in lines)
    for s in sched["subtasks"]:
        m = s["metrics"]
        assert m["input_gaussians"] == int(g.num_alive())
        assert m["gaussians_vs_input"] == pytest.approx(m["num_gaussians"] / m["input_gaussians"])
        assert 0 < m["psnr_vs_input"] < 100 and 0 < m["lpips_vs_input"] < 1
        on_disk = json.loads((run_dir / s["snapshot"]).with_name("metrics.json").read_text())
        assert on_disk["psnr_vs_input"] == m["psnr_vs_input"]
    # the r = 1 edit moved the scene further than the refinement did
    r0, r1 = (s["metrics"] for s in sched["subtasks"])
    assert r1["psnr_vs_input"] < r0["psnr_vs_input"]
    assert any("subtask r0 (refinement, e(0)) moved the scene" in line for line in lines)
    assert not any("subtask r1 (refinement" in line for line in lines)
    html = (run_dir / "report.html").read_text()
    assert "Editor identity on this scene" in html and "PSNR vs input (dB)" in html
    assert f"{r0['psnr_vs_input']:.2f}" in html


def test_the_progress_line_shows_the_last_snapshot():
    from experiments.edit import moved_postfix

    m = {"psnr_vs_input": 31.24, "lpips_vs_input": 0.0412, "num_gaussians": 900,
         "input_gaussians": 1000}
    assert moved_postfix([{"name": "r0", "metrics": m}]) == {
        "last": "r0", "vs_input": "31.2dB", "lpips": "0.041", "gaussians": "900/1000"}
    assert moved_postfix([]) == {} and moved_postfix([{"name": "r0", "metrics": None}]) == {}


@pytest.mark.parametrize("existing", [False, True])
def test_cli_edit_stopped_by_the_check_keeps_only_its_record(tmp_path, capfd, existing):
    """`edit` with a poor editor (tiny random InstructPix2Pix weights): exit 2, one line, and
    the run folder holds the check's record and nothing else the command wrote."""
    pytest.importorskip("diffusers")
    from cli_expect import fails
    from test_cli_bad_inputs import _dataset
    from test_ip2p import build_tiny_ip2p

    from jaxedit.io import save_ply

    weights = build_tiny_ip2p(tmp_path / "tiny-ip2p")
    data = _dataset(tmp_path / "data")
    scene = tmp_path / "scene.ply"
    rng = np.random.default_rng(1)
    save_ply(scene, gl.from_points(rng.normal(scale=0.3, size=(30, 3)),
                                   rng.uniform(size=(30, 3)), sh_degree=0))
    out = tmp_path / "new" / "run"
    before = []
    if existing:  # a folder the user made: what was there stays, with the record beside it
        out.mkdir(parents=True)
        (out / "notes.txt").write_text("mine\n")
        before = ["notes.txt"]
    line = fails(capfd, ["edit", "--editor", "ip2p", "--ip2p-weights", weights,
                         "--ip2p-size", "16", "--ip2p-steps", "1", "--data", data, "--scene",
                         scene, "--prompt", "make it red", "--mode", "nd", "--sync",
                         "--test-views", "1", "--turntable-frames", "0", "--quiet",
                         "--out", out], "--accept-low-identity")
    assert "dB < floor" in line and "--ip2p-weights" in line
    assert sorted(p.name for p in out.iterdir()) == sorted(before + ["identity.json"])
    assert sorted(p.name for p in (tmp_path / "new").iterdir()) == ["run"]
    record = json.loads((out / "identity.json").read_text())
    assert record["passed"] is False and record["editor_calls"] == len(record["views"])
    assert record["stopped"].startswith("editor identity")


@pytest.mark.parametrize("refine_reset", [False, True])
def test_the_refinement_keeps_the_input_opacities_unless_asked(tiny, refine_reset):
    """r_0 starts from the input's opacities (its targets are edits of its own renders);
    every edit subtask, and r_0 with ``refine_reset``, starts from the paper's reset."""
    from jaxedit.edit.context import EditContext
    from jaxedit.edit.state import begin_subtask, init_state
    from jaxedit.edit.trainer import SubtaskTrainer

    g, data = tiny
    cfg = ProEditConfig.for_mode("proedit", **TINY, refine_reset=refine_reset)
    trainer = SubtaskTrainer(EditTrainConfig(scene_extent=3.0), num_input=int(g.num_alive()),
                             warmup=cfg.warmup)
    ctx = EditContext.create(Identity(), PROMPT, data, cfg, trainer, Renderer(),
                             jax.random.key(0))
    st = init_state(ctx, g)
    alive = np.asarray(st.train.gaussians.alive)
    before = np.asarray(jax.nn.sigmoid(st.train.gaussians.opacity_logits))[alive]
    reset = trainer.settings.densify.cull_alpha
    for kind, want_reset in (("refine", refine_reset), ("edit", True), ("consolidate", True)):
        begun = begin_subtask(ctx, st, kind)
        after = np.asarray(jax.nn.sigmoid(begun.train.gaussians.opacity_logits))[alive]
        if want_reset:
            np.testing.assert_allclose(after, reset, rtol=1e-5)
        else:
            assert np.array_equal(after, before) and not np.allclose(before, reset)
        assert int(begun.train.densify_origin) == int(st.train.step) and begun.step == 0
