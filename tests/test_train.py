"""The trainer: a tiny reconstruction of the built-in face scene, exact resume, checkpoints.

One TrainConfig and one image size for the whole module, so the train step
compiles once per capacity / buffer size (they grow during the run, as designed).
"""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxedit import DataError
from jaxedit import gaussians as G
from jaxedit import scenes
from jaxedit import train as T
from jaxedit.pipelines.rundir import JsonlLog, RollingCheckpoints, resume

SIZE = 32
CONFIG = T.TrainConfig(
    iterations=300, sh_degree=1, sh_degree_interval=150, background="white",
    densify=T.DensifyConfig(warmup=40, refine_every=40, stop_at=200, reset_every=0,
                            max_gaussians=600, cull_alpha=0.01))
RESUME_AT = 130  # steps of the shared first leg (two maintenance steps: 80 and 120)


@pytest.fixture(scope="module")
def face():
    scene = scenes.get_scene("face")
    cams, train, test = scenes.scene_cameras(scene, views=10, test_views=2, size=SIZE)
    images = scenes.render_scene(scene, cams)
    points, colors = scenes.sample_points(scene, cams[train], 300, np.random.default_rng(0))
    extent = T.scene_extent(cams[train])
    # A tight capacity and intersection buffer, so that the run must grow both.
    init = G.from_points(points, colors, sh_degree=1, capacity=320)
    return dict(images=images, cams=cams, train=train, test=test, init=init, extent=extent)


def fresh_state(face):
    return T.init_state(face["init"], CONFIG, face["extent"], key=jax.random.key(7),
                        max_intersections=256)


@pytest.fixture(scope="module")
def first_leg(face, tmp_path_factory):
    """The uninterrupted run up to RESUME_AT steps, with its metrics log."""
    log = tmp_path_factory.mktemp("leg") / "log.jsonl"
    with JsonlLog(log) as record:
        state = T.fit(fresh_state(face), face["images"][face["train"]],
                      face["cams"][face["train"]], iterations=RESUME_AT, log=record,
                      log_every=10, room=None)
    return state, log


def leaves(tree):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(tree)]


def test_killed_run_resumes_bit_identically(face, first_leg, tmp_path):
    full, _ = first_leg
    ckpt = tmp_path / "ckpt"

    class Killed(Exception):
        pass

    def kill(state, metrics):
        if int(state.step) >= 110:  # the first chunk end at or after step 110 (here 120)
            raise Killed

    with pytest.raises(Killed):
        T.fit(fresh_state(face), face["images"][face["train"]], face["cams"][face["train"]],
              iterations=RESUME_AT, checkpoint=RollingCheckpoints(ckpt), checkpoint_every=60,
              callback=kill, room=None)
    assert [p.name for p in sorted(ckpt.glob("ckpt_*.npz"))] == ["ckpt_00000060.npz"]
    resumed = resume(ckpt)
    assert int(resumed.step) == 60
    resumed = T.fit(resumed, face["images"][face["train"]], face["cams"][face["train"]],
                    iterations=RESUME_AT, checkpoint=RollingCheckpoints(ckpt),
                    room=4.0)  # no plan after step 0
    assert int(resumed.step) == RESUME_AT
    assert resumed.capacity == full.capacity and resumed.max_intersections == full.max_intersections
    for a, b in zip(leaves(full), leaves(resumed)):
        np.testing.assert_array_equal(a, b)
    # The final checkpoint holds the final state.
    again = resume(ckpt)
    for a, b in zip(leaves(full), leaves(again)):
        np.testing.assert_array_equal(a, b)


def test_run_grew_buffer_and_capacity_and_logged_densification(face, first_leg):
    state, log = first_leg
    assert state.max_intersections > 256          # overflow -> redo with a larger buffer
    assert state.capacity > 320                    # density control asked for more slots
    records = [json.loads(line) for line in log.read_text().splitlines()]
    refined = [r for r in records if r["densify"]["refined"]]
    assert [r["step"] for r in refined] == [80, 120]
    assert sum(r["densify"]["created"] for r in refined) > 0
    assert all(r["num_gaussians"] <= CONFIG.densify.max_gaussians for r in records)
    assert not any(r["redo"] for r in records)
    assert records[-1]["step"] == RESUME_AT


def test_reconstruction_loss_falls_and_test_psnr_is_reasonable(face, first_leg):
    state, log = first_leg
    history = []
    state = T.fit(state, face["images"][face["train"]], face["cams"][face["train"]],
                  callback=lambda s, m: history.extend(m["loss"].tolist()))
    assert int(state.step) == CONFIG.iterations
    first = [json.loads(line)["loss"] for line in log.read_text().splitlines()][:3]
    assert np.mean(history[-20:]) < 0.6 * np.mean(first)
    result = T.evaluate(state.gaussians, face["images"][face["test"]], face["cams"][face["test"]])
    # Measured 20.7 dB / SSIM 0.82 after 300 steps at 32 x 32 (10 training views).
    assert result["psnr"] > 18.5, result["psnr"]
    assert 0.5 < result["ssim"] <= 1.0
    assert result["renders"].shape == (2, SIZE, SIZE, 3)


def test_should_stop_ends_early_and_data_order_is_a_function_of_key_and_step(face):
    images = face["images"][face["train"]]
    views = [int(T.view_and_key(jax.random.key_data(jax.random.key(3)), s, 10)[0])
             for s in range(20)]
    assert sorted(views[:10]) == list(range(10)) and sorted(views[10:]) == list(range(10))
    assert views[:10] != views[10:]
    again = [int(T.view_and_key(jax.random.key_data(jax.random.key(3)), s, 10)[0])
             for s in range(20)]
    assert views == again
    batch, _ = T.select_batch(images, face["cams"][face["train"]],
                              jax.random.key_data(jax.random.key(3)), 4)
    np.testing.assert_array_equal(np.asarray(batch.image), images[views[4]])
    # Checked before every chunk: at the module's chunk length (the program first_leg
    # compiled; chunk=1 would compile one more for the same property) it ends at 2 chunks.
    asked = []
    state = T.fit(fresh_state(face), images, face["cams"][face["train"]],
                  should_stop=lambda step, losses: asked.append(step) or step >= 2 * T.CHUNK,
                  room=None)
    assert int(state.step) == 2 * T.CHUNK
    assert asked[-1] == 2 * T.CHUNK and T.CHUNK in asked  # asked between chunks


def test_train_step_asks_for_a_redo_instead_of_returning_a_truncated_frame(face):
    state = fresh_state(face)
    batch, key = T.select_batch(face["images"][face["train"]], face["cams"][face["train"]],
                                state.key, 0)
    new, metrics = T.train_step(state, batch, key)
    assert bool(metrics["overflow"]) and bool(metrics["redo"])
    for a, b in zip(leaves(state), leaves(new)):
        np.testing.assert_array_equal(a, b)
    done, metrics = T.step_with_retry(state, batch, key)
    assert not bool(metrics["redo"]) and int(done.step) == 1
    assert done.max_intersections >= int(metrics["num_intersections"])


def test_config_and_checkpoint_errors(tmp_path, face):
    cfg = T.TrainConfig.from_dict(json.loads(json.dumps(CONFIG.to_dict())))
    assert cfg == CONFIG
    with pytest.raises(DataError, match="unknown train config"):
        T.TrainConfig.from_dict({"iterations": 5, "learning_rate": 1.0})
    with pytest.raises(DataError, match="background"):
        T.TrainConfig(background="green")
    with pytest.raises(DataError, match="sh_degree"):
        T.init_state(G.from_points(np.zeros((4, 3)) + np.arange(4)[:, None], np.zeros((4, 3)),
                                   sh_degree=0), CONFIG, 1.0)
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(DataError, match="cannot read checkpoint"):
        T.load_checkpoint(bad)
    with pytest.raises(DataError, match="no ckpt"):
        resume(tmp_path)
    with pytest.raises(DataError, match="no such"):
        resume(tmp_path / "missing.npz")
    with pytest.raises(DataError, match="images"):
        T.fit(fresh_state(face), np.zeros((3, SIZE, SIZE)), face["cams"][:3])


def test_sh_schedule_and_learning_rate_decay():
    cfg = dataclasses.replace(CONFIG, sh_degree=3, sh_degree_interval=1000)
    assert [int(T.active_sh_degree(s, cfg)) for s in (0, 999, 1000, 2500, 9000)] == [0, 0, 1, 2, 3]
    mask = np.asarray(T.sh_mask(1, 16))[:, 0]
    np.testing.assert_array_equal(mask, [1, 1, 1, 1] + [0] * 12)
    lr0 = float(T.means_lr(cfg, 2.0, 0))
    lr_end = float(T.means_lr(cfg, 2.0, cfg.iterations))
    assert lr0 == pytest.approx(1.6e-4 * 2.0) and lr_end == pytest.approx(1.6e-6 * 2.0)
    assert T.scene_extent(scenes.rig_cameras(scenes.get_scene("face").rig, 8)) > 1.0
    assert isinstance(T.background_color(dataclasses.replace(cfg, background="random"),
                                         jax.random.key(0)), jnp.ndarray)


def test_buffer_is_sized_from_the_views_not_guessed(face):
    cams = face["cams"][face["train"]]
    needed = T.measure_intersections(face["init"], cams)
    per_view = [T.measure_intersections(face["init"], cams[i]) for i in range(3)]
    assert needed >= max(per_view) > 0
    state = T.init_state(face["init"], CONFIG, face["extent"])
    assert state.max_intersections == 0
    sized = T.size_buffer(state, cams)
    assert 1.5 * needed <= sized.max_intersections
    from jaxedit.raster.render import next_capacity
    assert sized.max_intersections == next_capacity(int(1.5 * needed))
    # A run about to densify gets the buffer room it gets capacity; one past stop_at does not.
    assert T.planned_headroom(state, 2.0) == 2.0 * T.HEADROOM
    assert T.planned_headroom(state, None) == T.HEADROOM
    done = dataclasses.replace(state, step=jnp.int32(CONFIG.densify.stop_at))
    assert T.planned_headroom(done, 2.0) == T.HEADROOM


def test_planned_room_trains_the_same_scene_without_stopping_for_capacity(face, first_leg,
                                                                          tmp_path):
    grown, _ = first_leg  # room=None: the capacity grew on demand (a redo and a recompile)
    state = fresh_state(face)
    assert T.planned_capacity(state, 4.0) == CONFIG.densify.max_gaussians  # 4 x 300 > 600
    assert T.planned_capacity(state, None) == T.planned_capacity(state, 1.0) == state.capacity
    done = dataclasses.replace(state, step=jnp.int32(CONFIG.densify.stop_at))
    assert T.planned_capacity(done, 4.0) == state.capacity  # nothing left to densify
    log = tmp_path / "log.jsonl"
    with JsonlLog(log) as record:
        planned = T.fit(state, face["images"][face["train"]], face["cams"][face["train"]],
                        iterations=RESUME_AT, room=4.0, log=record, log_every=10)
    # From the first step on, density control had its room: no growth stopped the loop.
    assert {json.loads(line)["capacity"] for line in log.read_text().splitlines()} == {600}
    unplanned = {json.loads(line)["capacity"] for line in first_leg[1].read_text().splitlines()}
    assert unplanned == {320, 600}
    # The dead slots change nothing but the last bits of the floats.
    a, b = G.compact(grown.gaussians), G.compact(planned.gaussians)
    assert a.capacity == b.capacity
    for x, y in zip(leaves(a), leaves(b)):
        np.testing.assert_allclose(x, y, rtol=1e-4, atol=1e-4)


def test_a_checkpoint_of_the_static_extent_layout_loads_the_same_state(face, first_leg, tmp_path):
    # Before the extent was traced it travelled in the meta record only: such a file lacks its
    # leaf, and loading it gives the state a current file gives (the extent from the meta).
    state, _ = first_leg
    assert not isinstance(state.scene_extent, float)  # a leaf: scenes share programs
    current = T.save_checkpoint(tmp_path / "current.npz", state)
    with np.load(current) as z:
        arrays = {k: z[k] for k in z.files if k != ".scene_extent"}
    assert len(arrays) == len(np.load(current).files) - 1
    np.savez(tmp_path / "earlier.npz", **arrays)
    earlier = T.load_checkpoint(tmp_path / "earlier.npz")
    assert float(earlier.scene_extent) == pytest.approx(face["extent"], rel=1e-6)
    for a, b in zip(leaves(T.load_checkpoint(current)), leaves(earlier)):
        np.testing.assert_array_equal(a, b)
