"""Local edits (issue 35): relevance lifting, regions and masks, frozen Gaussians."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from pathlib import Path

from jaxedit import camera as cam_lib
from jaxedit.gaussians import Gaussians
from jaxedit.raster import accumulate_weights, accumulate_weights_reference, render

W, H, N = 40, 36, 48


def make_scene(seed, n=N):
    rng = np.random.default_rng(seed)
    return Gaussians(means=jnp.asarray(rng.normal(0.0, 0.6, (n, 3)), jnp.float32),
                     log_scales=jnp.asarray(np.log(rng.uniform(0.03, 0.25, (n, 3))), jnp.float32),
                     quats=jnp.asarray(rng.normal(size=(n, 4)), jnp.float32),
                     opacity_logits=jnp.asarray(rng.normal(0.0, 1.5, n), jnp.float32),
                     sh=jnp.asarray(rng.normal(0.0, 1.0, (n, 1, 3)), jnp.float32),
                     alive=jnp.asarray(rng.uniform(size=n) > 0.1))


def make_cameras():
    eyes = ((0.3, -3.0, 0.8), (2.5, -1.5, 0.2))
    return cam_lib.stack([cam_lib.make_camera(cam_lib.look_at(e, (0.0, 0.0, 0.0)), width=W,
                                              height=H, focal=float(W)) for e in eyes])


def test_per_gaussian_weights_match_the_dense_oracle():
    g = make_scene(0)
    cams = make_cameras()
    mask = jax.random.uniform(jax.random.key(1), (2, H, W, 1))
    values = jnp.concatenate([mask, jnp.ones_like(mask)], -1)  # [B, H, W, 2]
    tiles = np.asarray(accumulate_weights(g, cams, values))
    dense = np.asarray(accumulate_weights_reference(g, cams, values))
    assert tiles.shape == (N, 2)
    assert dense[:, 1].max() > 1.0  # drawn Gaussians
    np.testing.assert_allclose(tiles, dense, rtol=1e-4, atol=1e-5)
    assert np.all(tiles[~np.asarray(g.alive)] == 0)
    # The weights of one view sum, over Gaussians, to the frame's alpha: sum_i w_i = 1 - T.
    one = accumulate_weights(g, cams[0], jnp.ones((H, W, 1)))
    alpha = render(g, cams[0]).alpha
    np.testing.assert_allclose(float(one.sum()), float(alpha.sum()), rtol=1e-4)


# ---------------------------------------------------------------------------
# Relevance, regions, masks (item 1 and 3)
# ---------------------------------------------------------------------------
from jaxedit.edit import local as L  # noqa: E402
from jaxedit.editors.base import relevance_mask  # noqa: E402
from jaxedit.errors import DataError  # noqa: E402


def test_relevance_mask_keeps_the_changed_blob_and_nothing_for_no_change():
    d = np.zeros((2, 20, 24), np.float32)
    d[0, 5:10, 6:12] = 3.0
    m = np.asarray(relevance_mask(d))
    assert m.shape == (2, 20, 24) and set(np.unique(m)) <= {0.0, 1.0}
    assert m[0, 7, 9] == 1 and m[0, 0, 0] == 0 and m[0, 18, 20] == 0
    assert not m[1].any()


def test_lifted_relevance_is_the_weighted_mean_of_the_mask():
    g = make_scene(0)
    cams = make_cameras()
    alive = np.asarray(g.alive)
    ones = np.asarray(L.lift_relevance(g, cams, jnp.ones((2, H, W))))
    drawn = np.asarray(accumulate_weights(g, cams, jnp.ones((2, H, W, 1))))[:, 0] > 1e-8
    np.testing.assert_allclose(ones[drawn], 1.0, rtol=1e-5)
    assert np.all(ones[~drawn] == 0) and np.all(ones[~alive] == 0)
    half = np.zeros((2, H, W), np.float32)
    half[:, :, : W // 2] = 1.0
    rel = np.asarray(L.lift_relevance(g, cams, half))
    assert np.all((rel >= 0) & (rel <= 1 + 1e-6)) and 0 < rel[drawn].mean() < 1


def test_regions_parse_and_contain():
    box = L.parse_region("box:-1,-1,-1,0,0,0")
    ball = L.parse_region("sphere: 1, 1, 1, 0.5")
    means = jnp.asarray([[-0.5, -0.5, -0.5], [1.2, 1.0, 1.0], [0.5, 0.5, 0.5]])
    assert list(np.asarray(L.in_regions([box], means))) == [True, False, False]
    assert list(np.asarray(L.in_regions([box, ball], means))) == [True, True, False]
    assert np.asarray(L.in_regions([], means)).all()
    for bad in ("cube:1,2,3", "box:1,2,3", "box:0,0,0,1,1,x", "box:1,0,0,0,1,1",
                "sphere:0,0,0,0", "sphere:0,0,0,nan", "box"):
        with pytest.raises(DataError):
            L.parse_region(bad)


def test_editable_refuses_an_empty_region_and_freezes_the_rest():
    g = make_scene(0)
    with pytest.raises(DataError, match="contains no Gaussian"):
        L.editable(g, regions=[L.parse_region("sphere:50,50,50,1")])
    ed = L.editable(g, regions=[L.parse_region("box:-10,-10,-10,0,10,10")])
    frozen = np.asarray(L.frozen_of(g, ed))
    x = np.asarray(g.means)[:, 0]
    alive = np.asarray(g.alive)
    assert np.array_equal(np.asarray(ed), alive & (x <= 0))
    assert np.array_equal(frozen, alive & (x > 0))
    with pytest.raises(DataError, match="relevance"):
        L.editable(g, relevance=jnp.zeros(N))


def test_the_training_masks_take_the_edit_whole_where_the_editable_gaussians_own_the_pixel():
    g = make_scene(0)
    cams = make_cameras()
    plan = L.plan_local(L.LocalSpec("off", regions=(L.parse_region("box:-10,-10,-10,0,10,10"),)),
                        g, cams, np.zeros((2, H, W, 3), np.float32))
    weights = L.render_editable(g, cams, plan.editable)
    owned = weights >= L.OWNED
    assert owned.any() and (~owned & (weights > 0.05)).any()  # both kinds of pixel are here
    assert np.all(plan.masks[owned] == 1.0)  # the edit whole, no share of the photo
    assert np.all(plan.masks[~owned] == 0.0)  # the photo where frozen Gaussians hold most


def test_masks_by_frame_name_and_their_bad_inputs(tmp_path):
    from jaxedit.io.images import write_image

    names = ["images/frame_00001.png", "images/frame_00002.png"]
    d = tmp_path / "masks"
    d.mkdir()
    m = np.zeros((6, 8, 3), np.float32)
    m[2:4, 3:6] = 1.0
    write_image(d / "frame_00001.png", m)
    with pytest.raises(DataError, match="no mask for frame 'frame_00002'"):
        L.load_masks(d, names, (6, 8))
    write_image(d / "frame_00002.png", np.zeros((6, 8, 3), np.float32))
    masks = L.load_masks(d, names, (6, 8))
    assert masks.shape == (2, 6, 8) and masks[0, 2, 3] == 1 and masks[1].sum() == 0
    with pytest.raises(DataError, match="mask is 8x6 px, its view 10x6"):
        L.load_masks(d, names, (6, 10))
    # masks named as the frames' photos, drawn at twice the view's size (a downscaled run)
    photos = tmp_path / "photo_masks"
    photos.mkdir()
    write_image(photos / "IMG_0007.png", np.repeat(np.repeat(m, 2, 0), 2, 1))
    write_image(photos / "IMG_0008.jpg", np.zeros((12, 16, 3), np.float32))
    originals = ["IMG_0007.JPG", "IMG_0008.JPG"]
    np.testing.assert_array_equal(L.load_masks(photos, names, (6, 8), originals), masks)
    with pytest.raises(DataError, match="frame 'frame_00002' or its photo 'IMG_0009'"):
        L.load_masks(photos, names, (6, 8), ["IMG_0007.JPG", "IMG_0009.JPG"])
    with pytest.raises(DataError, match="mask is 16x12 px, its view 7x6"):
        L.load_masks(photos, names, (6, 7), originals)
    with pytest.raises(DataError, match="empty"):
        L.load_masks(d, names[1:], (6, 8))
    with pytest.raises(DataError, match="not a folder"):
        L.load_masks(tmp_path / "nope", names, (6, 8))


def test_simulated_editor_relevance_follows_its_target():
    from jaxedit_lab.simulated import SimulatedEditor
    from jaxedit.editors.base import relevance

    ed = SimulatedEditor()
    rng = np.random.default_rng(0)
    original = rng.uniform(0, 1, (16, 20, 3)).astype(np.float32)
    key = jax.random.key(0)
    m = np.asarray(relevance(ed, original, original, ed.encode(ed.instructions[1]), key))
    assert m.shape == (16, 20) and set(np.unique(m)) <= {0.0, 1.0} and m.any()
    assert not np.asarray(relevance(ed, original, original, ed.encode(""), key)).any()
    with pytest.raises(DataError, match="no relevance"):
        relevance(object(), original, original, None, key)


def test_jax_ip2p_relevance_one_batched_unet_call():
    from ip2p_standins import standin_editor

    from jaxedit.editors.base import relevance

    ed = standin_editor(size=32, steps=2)
    rng = np.random.default_rng(0)
    image = rng.uniform(0, 1, (24, 20, 3)).astype(np.float32)
    e = ed.encode("turn the bear into a panda")
    a = np.asarray(relevance(ed, image, image, e, jax.random.key(3)))
    b = np.asarray(relevance(ed, image, image, e, jax.random.key(3)))
    assert a.shape == (24, 20) and np.array_equal(a, b) and a.any()
    assert set(np.unique(a)) <= {0.0, 1.0}
    assert not np.asarray(relevance(ed, image, image, ed.encode(""), jax.random.key(3))).any()


# ---------------------------------------------------------------------------
# The trainer honours the frozen Gaussians (item 4)
# ---------------------------------------------------------------------------
def _densifying_state(frozen):
    import dataclasses

    from jaxedit import densify, train

    g = make_scene(2)
    g = dataclasses.replace(g, sh=jnp.concatenate([g.sh, jnp.zeros((N, 3, 3))], 1),
                            alive=jnp.ones(N, bool))
    from jaxedit.gaussians import grow

    g = grow(g, 2 * N)
    dens = densify.DensifyConfig(max_gaussians=2 * N, budget=True, budget_min_new=4,
                                 refine_every=2, warmup=1, refine_from_warmup=True,
                                 reset_every=3, cull_alpha=0.3, grad_floor=0.0,
                                 stop_at=100)
    cfg = train.TrainConfig(iterations=100, sh_degree=1, background="white", densify=dens,
                            lr_sh_dc=0.05)
    state = train.init_state(g, cfg, 1.0, max_intersections=8192)
    if frozen is not None:
        state = dataclasses.replace(state, frozen=jnp.asarray(frozen))
    return state


def test_frozen_gaussians_stay_bit_identical_and_new_ones_come_from_the_editable():
    from jaxedit import train

    cams = make_cameras()
    target = jnp.full((H, W, 3), 0.2)
    x = np.asarray(make_scene(2).means)[:, 0]
    frozen = np.zeros(2 * N, bool)
    frozen[:N] = x > 0
    state = _densifying_state(frozen)
    g0 = state.gaussians
    created = culled = 0
    for s in range(6):
        state, m = train.step_with_retry(state, train.Batch(target, cams[s % 2]),
                                         jax.random.key(s))
        created += int(m["densify"]["created"])
        culled += int(m["densify"]["culled"])
        assert bool(m["densify"]["refined"]) or s % 2 == 1 or s == 0
    g1 = state.gaussians
    f = np.asarray(frozen)
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh", "alive"):
        a, b = np.asarray(getattr(g0, name))[f], np.asarray(getattr(g1, name))[f]
        assert np.array_equal(a, b), name  # bit-identical, still alive
    editable = ~f & np.asarray(g0.alive)
    assert not np.allclose(np.asarray(g0.sh)[editable], np.asarray(g1.sh)[editable])
    assert created > 0 and culled > 0  # density control ran, on the editable part only
    # (new Gaussians took freed or dead slots, never a frozen one: those are unchanged above)


def test_without_frozen_the_step_is_unchanged():
    from jaxedit import train

    cams = make_cameras()
    target = jnp.full((H, W, 3), 0.2)
    a = _densifying_state(None)
    b = _densifying_state(np.zeros(2 * N, bool))
    for s in range(3):
        a, _ = train.step_with_retry(a, train.Batch(target, cams[s % 2]), jax.random.key(s))
        b, _ = train.step_with_retry(b, train.Batch(target, cams[s % 2]), jax.random.key(s))
    for name in ("means", "sh", "opacity_logits", "alive"):
        assert np.array_equal(np.asarray(getattr(a.gaussians, name)),
                              np.asarray(getattr(b.gaussians, name))), name


def test_a_region_adds_its_loss_to_the_metrics_and_trains_the_same():
    from jaxedit import train
    from jaxedit.losses import photometric_loss

    cams = make_cameras()
    target = jnp.full((H, W, 3), 0.2)
    region = jnp.zeros((H, W)).at[:, : W // 2].set(1.0)
    a, ma = train.train_step(_densifying_state(None), train.Batch(target, cams[0]),
                             jax.random.key(0))
    b, mb = train.train_step(_densifying_state(None), train.Batch(target, cams[0], region=region),
                             jax.random.key(0))
    assert "region_loss" not in ma
    for name in ("means", "sh", "opacity_logits"):  # what is trained does not change
        assert np.array_equal(np.asarray(getattr(a.gaussians, name)),
                              np.asarray(getattr(b.gaussians, name))), name
    render_before = render(_densifying_state(None).gaussians, cams[0], background=jnp.ones(3))
    want = photometric_loss(render_before.rgb, target, 0.2, weight=region)
    assert float(mb["region_loss"]) == pytest.approx(float(want), rel=1e-4)
    assert float(mb["region_loss"]) != pytest.approx(float(mb["loss"]), rel=1e-3)


# ---------------------------------------------------------------------------
# Bad input on the command line: one line, exit 2 (item 6)
# ---------------------------------------------------------------------------
def test_edit_cli_refuses_bad_regions_and_masks(tmp_path, capfd):
    from test_cli_bad_inputs import _dataset, _fails

    from jaxedit import gaussians as G
    from jaxedit.io import load_nerfstudio, save_ply, write_image

    data = _dataset(tmp_path / "data")
    rng = np.random.default_rng(1)
    scene = tmp_path / "scene.ply"
    save_ply(scene, G.from_points(rng.normal(scale=0.3, size=(30, 3)),
                                  rng.uniform(size=(30, 3)), sh_degree=0))
    ds = load_nerfstudio(data)
    train = [Path(ds.filenames[i]).stem for i in np.asarray(ds.train_indices)]
    base = ["edit", "--data", data, "--scene", scene, "--prompt", "x", "--out", tmp_path / "o"]
    _fails(capfd, base + ["--region", "sphere:50,50,50,1"], "contains no Gaussian")
    _fails(capfd, base + ["--region", "cube:1,2,3"], "--region")
    masks = tmp_path / "masks"
    masks.mkdir()
    write_image(masks / f"{train[0]}.png", np.ones((16, 16, 3), np.float32))
    _fails(capfd, base + ["--masks", masks], f"no mask for frame {train[1]!r}")
    for name in train[1:]:
        write_image(masks / f"{name}.png", np.ones((8, 8, 3), np.float32))
    _fails(capfd, base + ["--masks", masks], "mask is 8x8 px, its view 16x16")
    for name in train:
        write_image(masks / f"{name}.png", np.zeros((16, 16, 3), np.float32))
    _fails(capfd, base + ["--masks", masks], "every mask is empty")


# ---------------------------------------------------------------------------
# The simulated editor's local instruction (the benchmark's ground truth)
# ---------------------------------------------------------------------------
LOCAL_PROMPT = "paint the orange parts blue"


def test_local_instruction_changes_the_orange_part_only():
    from jaxedit_lab.simulated import INSTRUCTIONS, LOCAL_VOCABULARY, VOCABULARY, SimulatedEditor
    from jaxedit_lab.simulated_targets import orange_weight

    assert INSTRUCTIONS[:len(VOCABULARY)] == VOCABULARY and LOCAL_VOCABULARY[0].kind == "local"
    ed = SimulatedEditor()
    img = np.zeros((12, 16, 3), np.float32)
    img[:] = (0.5, 0.5, 0.5)             # grey: untouched
    img[2:6, 3:8] = (0.87, 0.46, 0.32)   # orange: turns blue
    img[7:10, 9:14] = (0.2, 0.4, 0.8)    # blue (cool): untouched
    img[0, :] = (1.0, 1.0, 1.0)          # white: untouched
    w = np.asarray(orange_weight(jnp.asarray(img)))
    assert w[3, 4] == 1.0 and w[8, 10] == 0.0 and w[5, 12] == 0.0 and w[0, 0] == 0.0
    full = ed.target(img, 1.0, LOCAL_PROMPT)
    np.testing.assert_allclose(full[3, 4], (0.32, 0.46, 0.87), atol=1e-6)
    outside = w == 0
    assert np.array_equal(full[outside], img[outside])  # bit for bit the original
    half = ed.target(img, 0.5, LOCAL_PROMPT)
    assert np.array_equal(half[outside], img[outside]) and 0.32 < half[3, 4, 0] < 0.87
    rel = ed.relevance(img, img, ed.encode(LOCAL_PROMPT), jax.random.key(0))
    assert rel[3, 4] == 1 and rel[8, 11] == 0 and rel[0, 15] == 0
    assert ed.decode(ed.encode(LOCAL_PROMPT)) == (len(VOCABULARY), 1.0)
    modal = SimulatedEditor(modes=3).mode_targets(img, 1.0, LOCAL_PROMPT)
    assert len({tuple(np.round(t[3, 4], 3)) for t in modal}) == 3  # blue, violet, green
    assert all(np.array_equal(t[outside], img[outside]) for t in modal)


# ---------------------------------------------------------------------------
# A local edit end to end (library): frozen bits, resume after a crash
# ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ball():
    """8 train + 2 held-out views (32 px) of a ball of coloured Gaussians, some orange."""
    import dataclasses

    from jaxedit import gaussians as gl
    from jaxedit.edit import EditData
    from jaxedit.edit.outputs import Renderer

    rng = np.random.default_rng(0)
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    colours = np.where(d[:, :1] > 0.3, (0.9, 0.45, 0.2), (0.45, 0.5, 0.55))
    g = gl.from_points(d * 0.5, colours, sh_degree=1, init_opacity=0.8)
    g = dataclasses.replace(g, log_scales=g.log_scales + 0.3)
    cams = cam_lib.orbit(10, radius=2.5, width=32, height=32, elevation_deg=15)
    images = np.stack([Renderer().rgb(g, cams[i]) for i in range(10)])
    return g, EditData.create(images[:8], cams[np.arange(8)], images[8:], cams[np.arange(8, 10)])


LOCAL_RUN = dict(warmup=6, patience=8, loss_window=4, max_steps=24, edit_every=3,
                 checkpoint_every=5, subtasks=2, consolidate=False, asynchronous=False,
                 turntable_frames=0)


class Crash(RuntimeError):
    pass


def _local_edit(ball, run_dir, editor=None, **kw):
    from jaxedit.edit import ProEditConfig, EditTrainConfig
    from jaxedit_lab.simulated import SimulatedEditor
    from jaxedit.pipelines import run_edit

    g, data = ball
    return run_edit(editor or SimulatedEditor(), LOCAL_PROMPT, data, g,
                    config=ProEditConfig.for_mode("proedit", **LOCAL_RUN),
                    settings=EditTrainConfig(lr_sh_dc=0.05), seed=3, run_dir=run_dir,
                    report=False, local=L.LocalSpec("auto"), **kw)


def test_local_edit_keeps_the_frozen_bits_and_resumes_exactly(ball, tmp_path):
    import json

    from counting_editor import CountingEditor

    g, data = ball
    editor = CountingEditor()
    whole = _local_edit(ball, tmp_path / "whole", editor=editor)
    # the relevance (--local auto), the context and the difficulty share one encoding
    assert editor.encoded == {LOCAL_PROMPT: 1, "": 1}
    figures = json.loads((tmp_path / "whole" / "schedule.json").read_text())["local"]
    assert figures["mode"] == "auto" and figures["editable"] > 0 and figures["frozen"] > 0
    out = whole["gaussians"]
    # Slots keep their place through the edit: the input's Gaussians whose every field
    # kept its bits include (at least) every frozen one, still alive.
    kept = np.asarray(g.alive).copy()
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        a, b = np.asarray(getattr(g, name)), np.asarray(getattr(out, name))[:g.capacity]
        kept &= np.all((a == b).reshape(len(a), -1), -1)
    assert figures["frozen"] <= kept.sum() < int(g.num_alive())
    assert np.asarray(out.alive)[:g.capacity][kept].all()
    # the report shows the region over the held-out views and the figures
    from jaxedit.pipelines.report import write_report

    assert len(sorted((tmp_path / "whole" / "local").glob("view_*.png"))) == len(data.test_images)
    page = write_report(tmp_path / "whole")
    html = __import__("pathlib").Path(page).read_text()
    assert 'id="local"' in html and "Local edit" in html and "frozen" in html

    def crash(spec, step, loss):
        if spec.index == 1 and step == 13:  # last checkpoint at step 10 of subtask 1
            raise Crash

    with pytest.raises(Crash):
        _local_edit(ball, tmp_path / "killed", callback=crash)
    resumed = _local_edit(ball, tmp_path / "killed", resume=True)  # rebuilds frozen
    for a, b in zip(jax.tree_util.tree_leaves(whole["gaussians"]),
                    jax.tree_util.tree_leaves(resumed["gaussians"])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


# ---------------------------------------------------------------------------
# The viewer: the splats coloured by their saved relevance
# ---------------------------------------------------------------------------
def test_viewer_colours_the_gaussians_by_their_saved_relevance(tmp_path):
    import dataclasses

    from experiments import view
    from jaxedit.io import save_ply

    g = make_scene(5)
    alive = np.asarray(g.alive)
    rel = np.zeros(N, np.float32)
    rel[alive] = np.linspace(0.0, 1.0, int(alive.sum()))
    ed = alive & (rel >= L.GAUSSIAN_THRESHOLD)
    run = tmp_path / "run"
    L.save_gaussian_relevance(run / "local", g, ed, rel)
    saved = view.relevance_of_run(run)
    assert np.array_equal(saved["editable"], ed[alive]) and bool(saved["lifted"])
    np.testing.assert_array_equal(saved["relevance"], rel[alive])
    # an edited snapshot: one Gaussian moved, the rest (frozen ones among them) kept
    moved = dataclasses.replace(g, means=g.means.at[int(np.flatnonzero(alive)[-1])].add(0.1))
    colours = L.relevance_colours(saved, np.asarray(moved.means)[alive])
    np.testing.assert_allclose(colours[0], L.COLD, atol=1e-6)  # relevance 0: frozen
    np.testing.assert_allclose(colours[-1], L.CHANGED)  # moved by the edit
    mid = colours[:-1]
    assert np.all(np.diff(mid[:, 0]) >= 0) and np.all(np.diff(mid[:, 2]) <= 0)  # blue -> red
    # without the lifted relevance (a region alone) the flags stand in for it
    L.save_gaussian_relevance(tmp_path / "flags", g, ed)
    assert np.array_equal(L.load_gaussian_relevance(tmp_path / "flags")["relevance"],
                          ed[alive].astype(np.float32))
    assert L.load_gaussian_relevance(tmp_path) is None  # a global edit's run
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / L.GAUSSIANS_FILE).write_bytes(b"not an npz")
    with pytest.raises(DataError, match="unreadable"):
        L.load_gaussian_relevance(tmp_path / "bad")
    pytest.importorskip("viser", reason="the optional extra 'viewer' is not installed")
    save_ply(run / "original" / "scene.ply", g)
    viewer = view.open_run(run, port=0)
    try:
        drawn = []
        viewer.server.scene.add_gaussian_splats = lambda name, **a: drawn.append(a["rgbs"])
        toggle = viewer._colour_by_relevance
        assert toggle is not None and not toggle.value
        toggle.value = True  # what ticking the checkbox does
        np.testing.assert_allclose(drawn[-1], L.relevance_colours(saved, saved["means"]))
        toggle.value = False
        assert not np.allclose(drawn[-1], L.relevance_colours(saved, saved["means"]))
    finally:
        viewer.close()
    plain = tmp_path / "plain"
    save_ply(plain / "original" / "scene.ply", g)
    viewer = view.open_run(plain, port=0)
    try:
        assert viewer._colour_by_relevance is None  # a global edit: no checkbox
    finally:
        viewer.close()


# ---------------------------------------------------------------------------
# The CLI on a built-in scene: make-scene, reconstruct, edit --local / --region / --masks
# ---------------------------------------------------------------------------
@pytest.mark.slow
def test_cli_local_region_and_masks_on_a_built_in_scene(tmp_path):
    import json

    from experiments import cli
    from jaxedit.io import load_nerfstudio, load_ply, write_image

    data, recon = tmp_path / "data", tmp_path / "recon"
    assert cli.main(["make-scene", "tabletop", "--out", str(data), "--size", "24", "--views", "6",
                     "--test-views", "2", "--quiet"]) == 0
    assert cli.main(["reconstruct", "--data", str(data), "--out", str(recon), "--iters", "80",
                     "--quiet"]) == 0
    scene = load_ply(recon / "scene.ply")
    base = ["edit", "--data", str(data), "--scene", str(recon / "scene.ply"), "--prompt",
            LOCAL_PROMPT, "--mode", "nd", "--sync", "--max-steps", "12", "--warmup", "2",
            "--patience", "4", "--turntable-frames", "0", "--no-report", "--quiet"]

    def run(name, *flags):
        out = tmp_path / name
        assert cli.main([*base, "--out", str(out), *flags]) == 0
        figures = json.loads((out / "schedule.json").read_text())["local"]
        final = load_ply(sorted(out.glob("subtasks/*/scene.ply"))[-1])
        # every frozen Gaussian of the input is in the output bit for bit (PLYs hold the
        # alive ones only, so compare rows as sets)
        rows = lambda g: {np.concatenate([np.asarray(getattr(g, f)).reshape(g.capacity, -1)  # noqa: E731
                                          for f in ("means", "sh", "opacity_logits")], 1)[i]
                          .tobytes() for i in range(g.capacity)}
        assert len(rows(scene) & rows(final)) >= figures["frozen"] > 0
        return out, figures

    out, auto = run("auto", "--local", "auto")
    assert auto["mode"] == "auto" and 0 < auto["editable"] < int(scene.num_alive())
    flags = json.loads((out / "config.json").read_text())["flags"]
    assert flags["local"] == "auto" and flags["region"] == [] and flags["masks"] is None
    # a region (half the table, scene coordinates) and masks (the left half of every frame)
    means = np.asarray(scene.means)
    mid = float(np.median(means[:, 0]))
    lo, hi = means.min(0) - 1, means.max(0) + 1
    box = f"box:{lo[0]:.3f},{lo[1]:.3f},{lo[2]:.3f},{mid:.3f},{hi[1]:.3f},{hi[2]:.3f}"
    # masks named as each frame's photo (process-data's original_file_path), drawn at twice
    # the views' size: the run matches them by photo name and box-averages them down
    masks = tmp_path / "masks"
    masks.mkdir()
    meta_path = data / "transforms.json"
    meta = json.loads(meta_path.read_text())
    for k, frame in enumerate(meta["frames"]):
        frame["original_file_path"] = f"IMG_{k:04d}.JPG"
    meta_path.write_text(json.dumps(meta))
    ds = load_nerfstudio(data)
    m = np.zeros((48, 48, 3), np.float32)
    m[:, :24] = 1.0
    for k in range(len(ds.filenames)):
        write_image(masks / f"IMG_{k:04d}.png", m)
    config = tmp_path / "local.json"
    config.write_text(json.dumps({"region": [box], "masks": str(masks)}))
    out, both = run("region", "--config", str(config))
    assert both["mode"] == "off" and both["regions"] and both["user_masks"]
    assert both["editable"] < int(scene.num_alive())
    flags = json.loads((out / "config.json").read_text())["flags"]
    assert flags["region"] == [box] and flags["masks"] == str(masks) and flags["local"] == "off"
