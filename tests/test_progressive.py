"""A progressive edit: plan, annealing, plateau, tiny end-to-end edits, exact resume, CLI."""

from __future__ import annotations

import dataclasses
import json
import time
import math
import threading

import jax
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from jaxedit import DataError
from jaxedit import camera as cl
from jaxedit import gaussians as gl
from jaxedit.edit import EditData, ProEditConfig, EditTrainConfig, anneal_timestep, plan_subtasks
from jaxedit.edit.state import EditState, LossTracker, apply_edits, track_loss
from jaxedit.edit.subtask import train_view
from jaxedit.edit.outputs import Renderer, reprojection_consistency
from jaxedit.pipelines import run_edit, select_snapshot
from jaxedit_lab.simulated import SimulatedEditor
from counting_editor import CountingEditor

PROMPT = "turn him into a bronze statue"


# ---------------------------------------------------------------------------
# Pure pieces
# ---------------------------------------------------------------------------
@settings(max_examples=30, deadline=None)
@given(lo=st.floats(0, 0.5), span=st.floats(0, 0.5), n=st.integers(1, 500))
def test_hifa_annealing_goes_from_tmax_to_tmin_monotonically(lo, span, n):
    hi = lo + span
    ts = [anneal_timestep(i, n, lo, hi) for i in range(0, n + 5)]
    assert ts[0] == pytest.approx(hi)
    assert ts[n] == pytest.approx(lo) and ts[-1] == pytest.approx(lo)  # clamped after N
    assert all(b <= a + 1e-12 for a, b in zip(ts, ts[1:]))
    i = n // 4
    assert ts[i] == pytest.approx(hi - (hi - lo) * math.sqrt(i / n))


def test_plan_of_each_mode():
    p = plan_subtasks("proedit", [0.0, 0.3, 0.6, 1.0], [0.1, 0.2, 0.15])
    assert [(s.name, s.kind, s.ratio) for s in p] == [
        ("r0", "refine", 0.0), ("r1", "edit", 0.3), ("r2", "edit", 0.6), ("r3", "edit", 1.0),
        ("rn", "consolidate", 1.0)]
    assert [s.index for s in p] == list(range(5))
    assert [s.difficulty for s in p] == [None, 0.1, 0.2, 0.15, None]
    assert p[2].dirname == "02_r0.600"
    nd = plan_subtasks("nd", [0.0, 1.0], [0.4])
    assert [(s.kind, s.ratio) for s in nd] == [("refine", 0.0), ("edit", 1.0), ("consolidate", 1.0)]
    assert [(s.kind, s.ratio) for s in plan_subtasks("in2n", [0.0, 1.0])] == [("edit", 1.0)]
    cont = plan_subtasks("proedit", [0.5, 0.75, 1.0], start_ratio=0.5, refine_first=False)
    assert [s.ratio for s in cont] == [0.75, 1.0, 1.0]
    with pytest.raises(DataError):
        plan_subtasks("proedit", [0.0, 0.5, 0.4, 1.0])
    with pytest.raises(DataError):
        ProEditConfig(mode="bogus")
    in2n = ProEditConfig.for_mode("in2n")
    assert in2n.timestep_range == (0.02, 0.98) and in2n.edit_every == 10
    assert not in2n.initial_sweep and not in2n.refine_first


def test_loss_tracker_plateau():
    t = LossTracker.init(3)
    for loss in [5, 4, 3, 2, 1]:
        t = track_loss(t, loss, min_delta=0.0)
    assert t.since_best == 0 and t.mean() == pytest.approx(2.0)
    t = track_loss(t, 2.0, min_delta=0.0)  # window (2, 1, 2): mean 5/3, a new minimum
    assert t.since_best == 0 and t.best == pytest.approx(5 / 3)
    for _ in range(3):
        t = track_loss(t, 2.0, min_delta=0.0)  # the mean rises to 2 and stays: no new minimum
    assert t.since_best == 3
    t = track_loss(t, -10.0, min_delta=0.0)
    assert t.since_best == 0


def test_the_loss_tracker_starts_afresh_once_the_training_images_are_final():
    # Every view edited and an edit made at t_min: from there on the plateau test measures
    # the loss against the final training images, not a best taken against older ones.
    t = LossTracker.init(2)
    for loss in [1.0, 1.0, 1.0]:
        t = track_loss(t, loss, min_delta=0.0)
    st = EditState.create(subtask=0, step=40, train=None, images=jax.numpy.zeros((2, 1, 1, 3)),
                          edited=np.zeros(2, bool), tracker=t)
    image = np.ones((1, 1, 3), np.float32)
    st = apply_edits(st, [0], [image], [True])     # annealed, not every view edited
    assert st.annealed_at == 40 and st.complete_at < 0 and int(st.tracker.count) == 3
    st = st.replace(step=45)
    st = apply_edits(st, [1], [image], [False])    # now both: a fresh tracker
    assert st.complete_at == 45 and int(st.tracker.count) == 0
    assert not np.isfinite(float(st.tracker.best)) and st.tracker.recent.shape == (2,)
    st = st.replace(tracker=track_loss(st.tracker, 3.0, min_delta=0.0), step=50)
    st = apply_edits(st, [0], [image], [True])     # later edits keep it
    assert int(st.tracker.count) == 1


def test_density_tally_counts_completed_maintenance_steps_only():
    from jaxedit.edit.state import DensityTally, tally_density

    completed = np.array([1, 0, 1, 1, 1], bool)  # step 1 was redone
    densify = {"refined": np.array([1, 1, 1, 1, 0], bool),
               "created": np.array([10, 99, 5, 2, 99], np.int32),
               "culled": np.array([3, 99, 1, 0, 99], np.int32),
               "budget": np.array([10, 99, 8, 50, 99], np.int32),
               "candidates": np.array([40, 99, 30, 1, 99], np.int32),
               "cap_limited": np.array([0, 0, 1, 0, 0], bool)}
    t = tally_density(DensityTally(refinements=1, created=4), densify, completed)
    # Steps 0, 2 and 3 refined: step 0 created its budget, step 2 was held by the cap
    # (wanted min(8, 30) = 8, made 5), step 3 by its candidates.
    assert t == DensityTally(refinements=4, created=21, culled=4, budget_limited=1,
                             cap_limited=1, shortfall=3)


def test_train_view_is_a_seeded_permutation_per_epoch():
    key = jax.random.key(3)
    views = [train_view(key, s, 5) for s in range(15)]
    for e in range(3):
        assert sorted(views[5 * e:5 * e + 5]) == list(range(5))
    assert views == [train_view(key, s, 5) for s in range(15)]


# ---------------------------------------------------------------------------
# A tiny scene: 8 train + 2 held-out views of a coloured ball, 32 x 32
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
    data = EditData.create(images[:8], cams[np.arange(8)], images[8:], cams[np.arange(8, 10)])
    return g, data, cams, images


FAST = EditTrainConfig(lr_sh_dc=0.05)  # a few dozen steps must visibly move colours
TINY = dict(warmup=6, patience=8, loss_window=4, max_steps=24, edit_every=3, checkpoint_every=5,
            subtasks=1, consolidate=False, asynchronous=False, turntable_frames=0)
#: The sync run: the difficulty-aware scheduler picks two edit subtasks (not ND).
SCHEDULED = {**TINY, "subtasks": None, "target_subtasks": 2, "difficulty_views": 3}


@pytest.fixture(scope="module")
def sync_run(tiny, tmp_path_factory):
    g, data, _, _ = tiny
    run_dir = tmp_path_factory.mktemp("sync")
    cfg = ProEditConfig.for_mode("proedit", **SCHEDULED)
    out = run_edit(SimulatedEditor(), PROMPT, data, g, config=cfg, settings=FAST, seed=7, run_dir=run_dir,
                   report=False, select=1)
    return run_dir, out


def test_reprojection_consistency_of_a_real_scene(tiny):
    g, data, cams, images = tiny
    renderer = Renderer()
    rgb, alpha, depth = renderer.views(g, cams[np.arange(4)])
    good = reprojection_consistency(rgb, alpha, depth, cams[np.arange(4)])
    rng = np.random.default_rng(0)
    noisy = np.clip(rgb + rng.normal(0, 0.2, rgb.shape), 0, 1).astype(np.float32)
    bad = reprojection_consistency(noisy, alpha, depth, cams[np.arange(4)])
    assert good > bad + 5.0  # independent per-view noise is inconsistent across views


def test_sync_edit_writes_the_run_directory(sync_run):
    run_dir, out = sync_run
    sched = json.loads((run_dir / "schedule.json").read_text())
    for key in ("prompt", "editor", "mode", "threshold", "difficulty_curve", "subtasks"):
        assert key in sched
    assert sched["prompt"] == PROMPT and sched["editor"] == "simulated" and sched["mode"] == "proedit"
    # no guidance given: the editor's own, recorded as used (the simulated editor's is IP2P's)
    assert sched["config"]["guidance"] is None and sched["guidance"] == [7.5, 1.5]
    # How the difficulty was measured: distance, reduction, the seeded view subset.
    diff = sched["difficulty"]
    assert diff["distance"] == sched["distance"] and diff["reduction"].startswith("mean")
    assert diff["num_views"] == len(diff["views"]) == 3 and diff["of_training_views"] == 8
    assert "target_subtasks" in sched and isinstance(sched["depth_limit_hit"], bool)
    curve = sched["difficulty_curve"]
    assert curve[0] == [0.0, 0.0] and curve[-1][0] == 1.0 and curve[-1][1] > 0
    subs = sched["subtasks"]
    # a progressive run: the refine subtask, then the scheduler's two steps 0 < r1 < r2 = 1
    assert [s["name"] for s in subs] == ["r0", "r1", "r2"]
    assert subs[0]["ratio"] == 0.0 < subs[1]["ratio"] < subs[2]["ratio"] == 1.0
    assert sched["target_subtasks"] == 2 and sched["schedule_method"] == "bisection"
    if not sched["depth_limit_hit"]:
        assert all(0 < s["difficulty"] <= sched["threshold"] for s in subs[1:])
    from jaxedit_lab.ablation.methods import edits_per_subtask

    for s in subs:
        for key in ("index", "name", "ratio", "difficulty", "steps", "seconds", "converged",
                    "snapshot"):
            assert key in s
        assert (run_dir / s["snapshot"]).exists()
        snap = (run_dir / s["snapshot"]).parent
        assert (snap / "renders" / "view_000.png").exists()
        assert (snap / "depth" / "view_000.png").exists()
        assert json.loads((snap / "metrics.json").read_text())["ratio"] == s["ratio"]
        # a plateau ends a subtask only after every view's edit and an edit at t_min trained
        # `patience` steps; otherwise the step guard ends it exactly at max_steps
        if s["guard"] is None:
            assert s["converged"] is True and s["steps"] < TINY["max_steps"]
            assert s["steps"] >= max(s["edits_complete_at"], s["annealed_at"]) + TINY["patience"]
        else:
            assert s["guard"] == "steps" and s["converged"] is False
            assert s["steps"] == TINY["max_steps"]
        assert s["edits_complete_at"] == TINY["warmup"]  # the initial sweep edits every view
    # the deterministic edit schedule: the initial sweep of all 8 views in every subtask, then
    # one view every edit_every steps after W
    per_subtask = [edits_per_subtask(s["steps"], warmup=TINY["warmup"], every=TINY["edit_every"],
                                     views=8, initial_sweep=True) for s in subs]
    assert all(n >= 8 for n in per_subtask)
    assert (run_dir / "original" / "renders" / "view_000.png").exists()
    metrics = json.loads((run_dir / "metrics.json").read_text())
    for key in ("psnr_vs_target", "ssim_vs_target", "multiview_consistency", "num_gaussians",
                "wall_time_s"):
        assert np.isfinite(metrics[key])
    assert metrics["utilisation"]["edits"] == sum(per_subtask)
    # the edit moved the scene towards the target: the renders beat the unedited scene
    assert metrics["psnr_vs_target"] > json.loads(
        (run_dir / "original" / "metrics.json").read_text())["psnr_vs_target"]
    assert (run_dir / "selected.ply").read_bytes() == (run_dir / subs[1]["snapshot"]).read_bytes()
    assert json.loads((run_dir / "selected.json").read_text())["index"] == 1


def test_select_by_ratio_and_bad_selection(sync_run):
    run_dir, _ = sync_run
    select_snapshot(run_dir, 0.1)
    assert json.loads((run_dir / "selected.json").read_text())["name"] == "r0"
    select_snapshot(run_dir, "-1")
    assert json.loads((run_dir / "selected.json").read_text())["name"] == "r2"
    with pytest.raises(DataError, match="select"):
        select_snapshot(run_dir, 9)
    with pytest.raises(DataError, match="select"):
        select_snapshot(run_dir, 1.5)


class Crash(RuntimeError):
    pass


def test_resume_after_a_crash_mid_subtask_is_bit_exact(tiny, sync_run, tmp_path):
    g, data, _, _ = tiny
    _, reference = sync_run
    cfg = ProEditConfig.for_mode("proedit", **SCHEDULED)

    def crash(spec, step, loss):
        if spec.index == 1 and step == 13:  # last checkpoint at step 10 of subtask 1
            raise Crash

    with pytest.raises(Crash):
        run_edit(SimulatedEditor(), PROMPT, data, g, config=cfg, settings=FAST, seed=7, run_dir=tmp_path,
                 report=False, callback=crash)
    sched = json.loads((tmp_path / "schedule.json").read_text())
    assert sched["subtasks"][0]["snapshot"] and sched["subtasks"][1]["snapshot"] is None
    out = run_edit(SimulatedEditor(), PROMPT, data, g, config=cfg, settings=FAST, seed=7, run_dir=tmp_path,
                   report=False, resume=True)
    a, b = reference["gaussians"], out["gaussians"]
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert [s["steps"] for s in out["schedule"]["subtasks"]] == \
        [s["steps"] for s in reference["schedule"]["subtasks"]]


class BatchingEditor:
    """The simulated editor with ``edit_many`` (a loop over its ``edit``) and a batch size:
    stands for an editor that edits several views per call, and records the calls' sizes."""

    def __init__(self, batch: int):
        self.inner, self.batch, self.calls = SimulatedEditor(), batch, []

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def edit_many(self, images, originals, embedding, keys, **kw):
        self.calls.append(len(images))
        return [self.inner.edit(i, o, embedding, k, **kw) for i, o, k in zip(images, originals, keys)]


def test_batched_editing_gives_the_same_run(tiny, sync_run):
    """A subtask's initial sweep and the difficulty's views go to the editor in batches, with
    the keys and timesteps of the one-at-a-time edits: the same schedule and the same bits."""
    g, data, _, _ = tiny
    _, reference = sync_run
    editor = BatchingEditor(batch=3)
    cfg = ProEditConfig.for_mode("proedit", **SCHEDULED)
    out = run_edit(editor, PROMPT, data, g, config=cfg, settings=FAST, seed=7, run_dir=None)
    for x, y in zip(jax.tree_util.tree_leaves(reference["gaussians"]),
                    jax.tree_util.tree_leaves(out["gaussians"])):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert out["schedule"]["difficulty_curve"] == reference["schedule"]["difficulty_curve"]
    # 8 views swept in 3 + 3 + 2 per subtask; 3 difficulty views in one call per ratio
    assert set(editor.calls) == {2, 3} and editor.calls.count(2) == len(out["schedule"]["subtasks"])


def test_resume_from_snapshot_with_another_schedule(tiny, sync_run, tmp_path):
    g, data, _, _ = tiny
    run_dir, _ = sync_run
    cfg = ProEditConfig.for_mode("proedit", **{**TINY, "subtasks": 2, "max_steps": 8})
    out = run_edit(SimulatedEditor(), PROMPT, data, g, config=cfg, settings=FAST, seed=7, run_dir=tmp_path,
                   report=False, resume_from=run_dir / "subtasks" / "00_r0.000")
    subs = out["schedule"]["subtasks"]
    assert [(s["kind"], s["ratio"]) for s in subs] == [("edit", 0.5), ("edit", 1.0)]
    assert out["schedule"]["start_ratio"] == 0.0 and out["schedule"]["resumed_from"]
    with pytest.raises(DataError):
        run_edit(SimulatedEditor(), PROMPT, data, g, config=cfg, settings=FAST, run_dir=tmp_path / "x",
                 resume_from=tmp_path / "nope")


def test_threaded_edit_completes_and_records_utilisation(tiny):
    g, data, _, _ = tiny
    cfg = ProEditConfig.for_mode("nd", **{**TINY, "subtasks": None, "asynchronous": True,
                                          "refine_first": False})
    out = run_edit(SimulatedEditor(), PROMPT, data, g, config=cfg, settings=FAST, seed=1, run_dir=None)
    subs = out["schedule"]["subtasks"]
    assert [s["ratio"] for s in subs] == [1.0]
    u = out["metrics"]["utilisation"]
    assert u["edits"] >= 1 and u["consumed"] >= 1 and u["polls"] >= 1
    assert u["edits"] >= u["consumed"]
    assert out["metrics"]["asynchronous"] is True


def test_editor_failure_in_thread_surfaces(tiny):
    from jaxedit.edit.buffer import EditorThreadError

    g, data, _, _ = tiny

    class Broken(SimulatedEditor):
        def edit(self, *a, **k):  # fine for the scheduler (main thread), fails in the producer
            if threading.current_thread() is not threading.main_thread():
                raise ValueError("broken editor")
            return super().edit(*a, **k)

    cfg = ProEditConfig.for_mode("nd", **{**TINY, "subtasks": None, "asynchronous": True,
                                          "refine_first": False, "max_steps": 200})
    with pytest.raises(EditorThreadError) as info:
        run_edit(Broken(), PROMPT, data, g, config=cfg, settings=FAST, run_dir=None)
    assert isinstance(info.value.__cause__, ValueError)


def test_cli_edit_writes_contract_files(tiny, tmp_path):
    from experiments.cli import main
    from jaxedit.io import save_nerfstudio, save_ply

    g, _, cams, images = tiny
    save_nerfstudio(tmp_path / "data", images, cams)
    save_ply(tmp_path / "scene.ply", g)
    out = tmp_path / "run"
    rc = main(["edit", "--data", str(tmp_path / "data"), "--scene", str(tmp_path / "scene.ply"),
               "--prompt", PROMPT, "--editor", "simulated", "--out", str(out), "--sync",
               "--subtasks", "1", "--max-steps", "8", "--warmup", "6", "--patience", "3",
               "--turntable-frames", "0", "--quiet", "--no-report", "--select", "0"])
    assert rc == 0
    sched = json.loads((out / "schedule.json").read_text())
    assert {"prompt", "editor", "mode", "threshold", "difficulty_curve", "subtasks"} <= set(sched)
    assert all({"index", "name", "ratio", "difficulty", "steps", "seconds", "converged",
                "snapshot"} <= set(s) for s in sched["subtasks"])
    assert (out / "metrics.json").exists() and (out / "selected.ply").exists()
    assert json.loads((out / "config.json").read_text())["command"] == "edit"
    rc = main(["edit", "--data", str(tmp_path / "data"), "--scene", str(tmp_path / "nope.ply"),
               "--prompt", PROMPT, "--out", str(tmp_path / "bad"), "--quiet"])
    assert rc == 2
    rc = main(["edit", "--data", str(tmp_path / "data"), "--scene", str(tmp_path / "scene.ply"),
               "--prompt", "make it purple please", "--out", str(tmp_path / "bad2"), "--quiet"])
    assert rc == 2


def test_in2n_baseline_runs_its_fixed_budget_with_one_edit_every_10_steps(tiny):
    g, data, _, _ = tiny
    cfg = ProEditConfig.for_mode("in2n", max_steps=30, checkpoint_every=100)
    out = run_edit(SimulatedEditor(), PROMPT, data, g, config=cfg, settings=FAST.classic(), seed=0,
                   run_dir=None)
    (sub,) = out["schedule"]["subtasks"]
    # a fixed budget: it neither plateaus (converged None) nor is cut by a guard
    assert (sub["kind"], sub["ratio"], sub["steps"]) == ("edit", 1.0, 30)
    assert sub["converged"] is None and sub["guard"] is None
    assert out["metrics"]["all_converged"]
    assert out["metrics"]["utilisation"]["edits"] == 3  # steps 0, 10, 20: no sweep, no r0/rn
    assert out["schedule"]["difficulty_curve"] == []


def test_cli_edit_uses_lpips_difficulty_and_checks_real_model_flags(tiny, tmp_path):
    from experiments.cli import main
    from jaxedit.io import save_nerfstudio, save_ply
    from jaxedit.lpips import _convs, _tap_channels, save_lpips_params

    g, _, cams, images = tiny
    save_nerfstudio(tmp_path / "data", images, cams)
    save_ply(tmp_path / "scene.ply", g)
    rng = np.random.default_rng(3)
    tensors = {}
    for c in _convs("alex"):  # a random AlexNet trunk with non-negative heads
        fan_in = c.cin * c.kernel * c.kernel
        tensors[f"trunk.{c.index}.weight"] = rng.normal(
            0, np.sqrt(2 / fan_in), (c.cout, c.cin, c.kernel, c.kernel)).astype(np.float32)
        tensors[f"trunk.{c.index}.bias"] = np.zeros(c.cout, np.float32)
    for k, ch in enumerate(_tap_channels("alex")):
        tensors[f"lin{k}.weight"] = rng.uniform(0, 1, (1, ch, 1, 1)).astype(np.float32)
    weights = save_lpips_params(tmp_path / "lpips_alex.npz", tensors, "alex")
    base = ["edit", "--data", str(tmp_path / "data"), "--scene", str(tmp_path / "scene.ply"),
            "--prompt", PROMPT, "--editor", "simulated", "--sync", "--subtasks", "1",
            # the contract test's run settings: one compiled edit chunk for both CLI runs
            "--max-steps", "8", "--warmup", "6", "--patience", "3", "--turntable-frames", "0",
            "--quiet", "--no-report"]
    out = tmp_path / "run"
    assert main(base + ["--out", str(out), "--lpips-weights", str(weights)]) == 0
    sched = json.loads((out / "schedule.json").read_text())
    assert sched["distance"] == "lpips-alex"
    edit_steps = [s for s in sched["subtasks"] if s["kind"] == "edit"]
    assert edit_steps and edit_steps[0]["difficulty"] > 0
    assert main(base + ["--out", str(tmp_path / "bad"), "--lpips-weights",
                        str(tmp_path / "missing.npz")]) == 2
    assert main(base + ["--out", str(tmp_path / "bad2"), "--clip-weights", str(tmp_path)]) == 2


def test_edit_cap_defaults_to_twice_the_input_and_is_never_below_it():
    from jaxedit.edit.trainer import (CAP_MIN_ROOM, SubtaskTrainer, default_max_gaussians,
                                      resolve_max_gaussians)

    # Reconstructions of 0.3-3M Gaussians keep room to create (the old fixed 200k cap had none).
    assert default_max_gaussians(1_000_000) == 2_000_000
    assert default_max_gaussians(500) == 500 + CAP_MIN_ROOM
    def cap(settings):
        return settings.densify.max_gaussians

    capped = EditTrainConfig().replace_densify
    assert cap(resolve_max_gaussians(EditTrainConfig(), 300_000)) == 600_000
    assert cap(resolve_max_gaussians(capped(max_gaussians=400_000), 300_000)) == 400_000
    with pytest.raises(DataError, match="max_gaussians"):
        resolve_max_gaussians(capped(max_gaussians=1000), 300_000)
    trainer = SubtaskTrainer(EditTrainConfig(), num_input=250_000)
    assert trainer.config.densify.max_gaussians == 500_000
    with pytest.raises(DataError, match="max_gaussians"):
        SubtaskTrainer(EditTrainConfig())


def test_difficulty_views_are_a_fixed_seeded_subset():
    from jaxedit.edit.difficulty import DIFFICULTY_VIEWS, difficulty_view_subset

    key = jax.random.key(0)
    assert difficulty_view_subset(10, None, key) == tuple(range(10))  # all views when few
    many = difficulty_view_subset(40, None, key)
    assert len(many) == DIFFICULTY_VIEWS and list(many) == sorted(set(many))
    assert difficulty_view_subset(40, None, key) == many  # seeded: the same subset again
    assert difficulty_view_subset(40, 5, jax.random.key(1)) != difficulty_view_subset(40, 5, key)
    with pytest.raises(DataError):
        difficulty_view_subset(0, None, key)


# ---------------------------------------------------------------------------
# A subtask's pure parts
# ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def chunk_start(tiny):
    """A context, the state at the start of an edit subtask (the tiny scene), the subtask
    and its limits."""
    from jaxedit.edit.context import EditContext
    from jaxedit.edit.state import begin_subtask, init_state
    from jaxedit.edit.plan import SubtaskSpec, subtask_limits
    from jaxedit.edit.trainer import SubtaskTrainer

    g, data, _, _ = tiny
    cfg = ProEditConfig.for_mode("proedit", **TINY)
    settings = dataclasses.replace(FAST, scene_extent=3.0)
    trainer = SubtaskTrainer(settings, num_input=int(g.num_alive()), warmup=cfg.warmup)
    ctx = EditContext.create(SimulatedEditor(), PROMPT, data, cfg, trainer, Renderer(),
                             jax.random.key(3))
    return (ctx, begin_subtask(ctx, init_state(ctx, g)), SubtaskSpec(1, "r1", 0.5, None, "edit"),
            subtask_limits(cfg, data.train_images.shape))


def _bits(tree):
    return [np.asarray(x).tobytes() for x in jax.tree_util.tree_leaves(tree)]


@settings(max_examples=4, deadline=None)
@given(num_steps=st.integers(1, 16), stop_if_plateau=st.booleans(), skip=st.integers(0, 12))
def test_step_chunk_is_a_pure_function_of_its_inputs(chunk_start, num_steps, stop_if_plateau, skip):
    from jaxedit.edit.subtask import step_chunk

    ctx, start, spec, limits = chunk_start
    start = start.replace(step=skip)  # any point of the subtask
    before = _bits((start.train, start.tracker, start.images))
    a, ra = step_chunk(ctx, start, spec, limits, num_steps, stop_if_plateau=stop_if_plateau)
    b, rb = step_chunk(ctx, start, spec, limits, num_steps, stop_if_plateau=stop_if_plateau)
    assert _bits((a.train, a.tracker, a.images)) == _bits((b.train, b.tracker, b.images))
    assert a.step == b.step == skip + len(ra.losses) and ra.losses.tobytes() == rb.losses.tobytes()
    assert _bits((start.train, start.tracker, start.images)) == before  # the input is untouched
    assert start.step == skip


def test_a_chunk_of_edit_steps_makes_no_implicit_host_transfer(chunk_start):
    from jaxedit.edit.subtask import step_chunk

    ctx, start, spec, limits = chunk_start
    step_chunk(ctx, start, spec, limits, 8, stop_if_plateau=False)  # compiled outside the guard
    with jax.transfer_guard("disallow"):
        st, result = step_chunk(ctx, start, spec, limits, 8, stop_if_plateau=False)
    assert st.step == 8 and len(result.losses) == 8 and np.all(np.isfinite(result.losses))


def test_the_chunk_program_built_beside_the_schedule_is_the_one_the_subtask_runs(chunk_start):
    """run_edit builds the training chunks' program on a thread while the schedule edits
    (compile_chunk); the subtask's first chunk then compiles nothing (a min_delta no other
    test uses makes the program new here)."""
    from jaxedit.compilation import compile_stats
    from jaxedit.edit.subtask import compile_chunk, step_chunk

    ctx, start, spec, limits = chunk_start
    ctx = dataclasses.replace(ctx, config=dataclasses.replace(ctx.config, min_delta=2.5e-3))
    before = compile_stats()
    compile_chunk(ctx, start)
    built = compile_stats(since=before)["programs"]["_edit_chunk"]
    assert built["count"] + built["cache_hits"] == 1
    before = compile_stats()
    st, result = step_chunk(ctx, start, spec, limits, 4, stop_if_plateau=False)
    assert st.step == 4 and "_edit_chunk" not in compile_stats(since=before)["programs"]


def test_work_on_a_thread_ends_with_the_block_and_its_error_is_raised_there():
    """on_a_thread (the chunk compile beside the schedule, the demo's editor warm-up beside
    the reconstruction): joined when the block ends; its error raised there, unless the
    block failed too, whose own error then goes first."""
    from jaxedit.pipelines.edit_run import on_a_thread

    done, release = [], threading.Event()
    with on_a_thread(lambda: (release.wait(10), done.append(1))):
        assert done == []  # the work waits for the block's word
        release.set()
    assert done == [1]

    def fail():
        raise ValueError("the work failed")

    with pytest.raises(ValueError, match="the work failed"):
        with on_a_thread(fail):
            pass
    with pytest.raises(KeyError, match="the block"):
        with on_a_thread(fail):
            raise KeyError("the block")


class SlowEditor(SimulatedEditor):
    """The simulated editor, 40 ms per edit: far slower than the trainer's steps."""

    def edit(self, *args, **kwargs):
        time.sleep(0.04)
        return super().edit(*args, **kwargs)


def test_async_subtask_never_ends_on_edits_it_has_not_trained_on(tiny):
    g, data, _, _ = tiny
    # A 12-step guard fires long before 8 slow edits arrive: the subtask must wait for the
    # missing views and then train `patience` steps on the complete dataset.
    cfg = ProEditConfig.for_mode("nd", **{**TINY, "subtasks": None, "asynchronous": True,
                                          "refine_first": False, "max_steps": 12})
    out = run_edit(SlowEditor(), PROMPT, data, g, config=cfg, settings=FAST, seed=2, run_dir=None)
    for sub in out["schedule"]["subtasks"]:
        assert sub["edits_complete_at"] is not None
        assert sub["steps"] >= sub["edits_complete_at"] + cfg.patience
    assert out["metrics"]["utilisation"]["trainer_waits"] >= 1


def test_the_wall_clock_guard_ends_subtasks_and_says_so(tiny):
    g, data, _, _ = tiny
    # A guard of a millisecond fires after the first chunk of every subtask; the record
    # names it, and the step guard stays far away.
    cfg = ProEditConfig.for_mode("nd", **{**TINY, "subtasks": None, "refine_first": False,
                                          "max_steps": 200, "max_seconds": 1e-3})
    out = run_edit(SimulatedEditor(), PROMPT, data, g, config=cfg, settings=FAST, seed=2,
                   run_dir=None)
    subs = out["schedule"]["subtasks"]
    assert subs and all(s["guard"] == "seconds" and not s["converged"] for s in subs)
    assert all(s["steps"] < cfg.max_steps for s in subs)
    assert out["schedule"]["guard"]["max_seconds"] == 1e-3
    with pytest.raises(DataError, match="max_seconds"):
        ProEditConfig.for_mode("nd", max_seconds=0.0)


def test_subtask_guard_scales_with_views_and_resolution():
    from jaxedit.edit.plan import GUARD_MIN_STEPS, subtask_guard

    assert subtask_guard(4, 32, 32) == GUARD_MIN_STEPS  # small scenes keep the floor
    assert subtask_guard(32, 64, 64) == 640  # the demo: 20 epochs of its 32 views
    assert subtask_guard(64, 64, 64) == 2 * subtask_guard(32, 64, 64)
    assert subtask_guard(100, 512, 512) == 4000  # twice the passes at twice the side
    assert subtask_guard(100, 540, 960) > subtask_guard(100, 256, 256)


def test_the_subtask_limits_resolve_the_users_config_without_changing_it():
    from jaxedit.edit.plan import SubtaskLimits, step_guard, subtask_guard, subtask_limits

    shape = (8, 32, 32, 3)
    scaled = ProEditConfig.for_mode("proedit", max_steps=None)
    assert step_guard(scaled, shape) == subtask_guard(8, 32, 32)
    assert subtask_limits(scaled, shape) == SubtaskLimits(subtask_guard(8, 32, 32), True)
    assert scaled.max_steps is None  # still the user's: "scaled with the scene"
    given = ProEditConfig.for_mode("proedit", max_steps=77)
    assert subtask_limits(given, shape) == SubtaskLimits(77, True)
    assert subtask_limits(ProEditConfig.for_mode("in2n", max_steps=40), shape) == \
        SubtaskLimits(40, False)


def test_the_run_keeps_the_users_config_and_records_the_scaled_guard(tiny):
    from jaxedit.edit import progressive
    from jaxedit.edit.context import EditContext
    from jaxedit.edit.plan import subtask_guard

    g, data, _, _ = tiny
    cfg = ProEditConfig.for_mode("in2n", max_steps=None, turntable_frames=0)
    trainer = progressive.make_trainer(cfg, FAST, data, g)
    ctx = EditContext.create(SimulatedEditor(), PROMPT, data, cfg, trainer, Renderer(),
                             jax.random.key(0))
    assert ctx.config is cfg
    _, header = progressive.plan_edit(ctx, g, seed=0)
    assert header["config"]["max_steps"] is None
    assert header["guard"]["max_steps"] == subtask_guard(8, 32, 32)
    assert header["guard"]["max_steps_scaled"] is True
    ctx = dataclasses.replace(ctx, config=dataclasses.replace(cfg, max_steps=50))
    assert progressive.plan_edit(ctx, g, seed=0)[1]["guard"] == {
        "max_steps": 50, "max_steps_scaled": False, "max_seconds": None}


def test_the_density_warmup_is_the_plans_unless_set(tiny):
    from jaxedit.edit import progressive

    g, data, _, _ = tiny
    cfg = ProEditConfig.for_mode("proedit", warmup=7)
    assert FAST.densify.warmup is None
    assert progressive.make_trainer(cfg, FAST, data, g).config.densify.warmup == 7
    own = FAST.replace_densify(warmup=5)
    assert progressive.make_trainer(cfg, own, data, g).config.densify.warmup == 5


def test_a_run_encodes_its_prompt_once(tiny):
    # the context, the difficulty oracle (and a local edit's relevance) share one encoding
    g, data, _, _ = tiny
    # TINY's warm-up (the density control's, static in the trainer's config): the program
    # the sync run compiled
    cfg = ProEditConfig.for_mode("proedit", **{**TINY, "max_steps": 8, "patience": 2,
                                               "difficulty_views": 2})
    editor = CountingEditor()
    run_edit(editor, PROMPT, data, g, config=cfg, settings=FAST, seed=1, run_dir=None)
    assert editor.encoded == {PROMPT: 1, "": 1}


class RecordingEditor(SimulatedEditor):
    """The simulated editor, recording the SDEdit timestep range of every call."""

    def __init__(self):
        super().__init__()
        self.timesteps = []

    def edit(self, *args, timestep_range=(0.02, 0.98), **kwargs):
        self.timesteps.append(tuple(float(t) for t in timestep_range))
        return super().edit(*args, timestep_range=timestep_range, **kwargs)


def test_the_anneal_reaches_t_min_in_subtasks_that_end_on_their_plateau(tiny):
    g, data, _, _ = tiny
    # A guard far above where the plateau would end on its own: the subtask still anneals
    # down to t_min and trains ``patience`` steps on an edit made there.
    cfg = ProEditConfig.for_mode("proedit", **{**TINY, "subtasks": 2, "refine_first": False,
                                               "max_steps": 300})
    editor = RecordingEditor()
    out = run_edit(editor, PROMPT, data, g, config=cfg, settings=FAST, seed=5, run_dir=None)
    subs = out["schedule"]["subtasks"]
    assert len(subs) == 2 and all(s["converged"] and s["guard"] is None for s in subs)
    t_min, t_max = cfg.timestep_range
    # The subtasks' edits (the difficulty's edits use t = 0.98): one non-increasing run of
    # timesteps per subtask, restarting at t_max.
    ts = [t0 for t0, t1 in editor.timesteps if t0 == t1 and t0 <= t_max]
    starts = [0] + [i for i in range(1, len(ts)) if ts[i] > ts[i - 1]] + [len(ts)]
    runs = [ts[a:b] for a, b in zip(starts, starts[1:])]
    assert len(runs) == 2
    for run, sub in zip(runs, subs):
        assert run[0] == pytest.approx(t_max) and run[-1] == pytest.approx(t_min)
        # the plateau is judged on the final images only: a full window, then patience
        ready = max(sub["annealed_at"], sub["edits_complete_at"])
        assert ready + cfg.loss_window + cfg.patience - 1 <= sub["steps"] < cfg.max_steps
    room = cfg.max_steps - cfg.warmup - cfg.patience - cfg.edit_every
    assert all(s["anneal_horizon"] == cfg.warmup + room // 2 for s in subs)


# slow tier: an edit at 200k Gaussians (the budget and the cap are proven at small sizes)
@pytest.mark.slow
def test_an_input_above_200k_gaussians_grows_up_to_its_cap_and_never_past_it():
    # Real reconstructions hold 0.3-3M Gaussians; the old fixed 200k cap left such a scene
    # no room at all. Tiny images keep the 200k-Gaussian steps cheap.
    rng = np.random.default_rng(1)
    n = 200_200
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    g = gl.from_points(d * rng.uniform(0.2, 0.5, (n, 1)), rng.uniform(0, 1, (n, 3)),
                       sh_degree=0, init_opacity=0.5)
    cams = cl.orbit(6, radius=2.5, width=16, height=16, elevation_deg=15)
    renderer = Renderer()
    images = np.stack([renderer.rgb(g, cams[i]) for i in range(6)])
    data = EditData.create(images[:4], cams[np.arange(4)], images[4:], cams[np.arange(4, 6)])
    cap = n + 500
    # Opacities frozen: the cull removes nothing, so only the cap can bound the growth.
    settings = dataclasses.replace(FAST, lr_opacity=0.0).replace_densify(max_gaussians=cap,
                                                                         refine_every=4)
    cfg = ProEditConfig.for_mode("nd", warmup=2, patience=4, loss_window=4, max_steps=14,
                                 edit_every=3, refine_first=False, consolidate=False,
                                 difficulty_views=1, curve_points=2, asynchronous=False)
    alive, logs = [], []
    out = run_edit(SimulatedEditor(), PROMPT, data, g, config=cfg, settings=settings, seed=0,
                   run_dir=None, log=logs.append,
                   progress=lambda spec, step, loss, st: alive.append(
                       int(st.train.gaussians.num_alive())))
    sub = out["schedule"]["subtasks"][0]
    density = sub["density"]
    assert density["refinements"] >= 2 and density["created"] > 0
    assert max(alive) <= cap and int(out["gaussians"].num_alive()) == cap  # up to it, not past
    # t(n) wanted ~2% of 200k per maintenance step; the cap left room for 500: said loudly.
    assert density["cap_limited"] >= 1 and density["shortfall"] > 0
    assert any(f"the Gaussian cap ({cap}) limited creation" in m for m in logs)
    assert out["schedule"]["max_gaussians"] == cap


def test_target_subtasks_gives_4_and_8_subtasks_on_the_demo_scene(tmp_path):
    """The demo's edit (the person scene at 64 px, its first instruction, 8 seeded difficulty
    views, the bundled LPIPS-AlexNet) split for 4 and for 8 subtasks."""
    from jaxedit import scenes
    from jaxedit.edit import schedule as sched
    from jaxedit.edit.difficulty import DifficultyOracle, lpips_weights_to_use
    from jaxedit.edit.difficulty import difficulty_view_subset
    from jaxedit.io import load_nerfstudio

    path = scenes.make_scene("person", tmp_path / "person", downscale=4, views=32, test_views=4)
    ds = load_nerfstudio(path)
    originals = np.asarray(ds.images, np.float32)[np.asarray(ds.train_indices)]
    from jaxedit.lpips import lpips_distance

    distance = lpips_distance(lpips_weights_to_use("auto"))
    editor = SimulatedEditor()
    views = difficulty_view_subset(len(originals), 8, jax.random.key(0))
    oracle = DifficultyOracle(editor, originals, editor.instructions[0], views=views,
                              distance=distance, seed=0, reduction="mean")
    for target in (4, 8):
        s = sched.for_target_subtasks(oracle, target, max_depth=4)
        assert abs(s.num_subtasks - target) <= 1, (target, s.num_subtasks, s.threshold)
        assert not s.depth_limit_hit
