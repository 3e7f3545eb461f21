"""The edit state's two parts and its checkpoint, whose layout is derived from them."""

from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest

from jaxedit import camera as cl
from jaxedit import gaussians as gl
from jaxedit.edit.buffer import Utilisation
from jaxedit.edit.checkpoint import KIND, load_checkpoint, record_schema, save_checkpoint
from jaxedit.edit.state import (DensityTally, DeviceState, EditState, HostState, LossTracker,
                                track_loss)
from jaxedit.edit.trainer import SubtaskTrainer, EditTrainConfig
from jaxedit.io.checkpoint import FORMAT_VERSION, read_pytree

PLAN = [{"index": 0, "name": "r1", "ratio": 1.0, "difficulty": None, "kind": "edit"}]


@pytest.fixture(scope="module")
def state() -> tuple[EditState, object]:
    rng = np.random.default_rng(3)
    g = gl.from_points(rng.normal(size=(12, 3)), rng.uniform(size=(12, 3)), sh_degree=0)
    cams = cl.orbit(2, radius=4.0, width=8, height=8)
    train = SubtaskTrainer(EditTrainConfig(scene_extent=1.0), int(g.num_alive())).init(g, cams)
    tracker = LossTracker.init(3)
    for loss in (0.5, 0.25, 0.75, 0.125):
        tracker = track_loss(tracker, loss, min_delta=0.01)
    st = EditState.create(subtask=1, step=7, train=train,
                          images=rng.uniform(size=(2, 4, 4, 3)).astype(np.float32),
                          edited=np.array([True, False]), tracker=tracker,
                          records=({"index": 0, "steps": 5},), seconds=1.5,
                          utilisation=Utilisation(edits=3, editor_seconds=0.25),
                          complete_at=4, annealed_at=-1, density=DensityTally(refinements=2))
    return st, train


def _leaves(tree):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(tree)]


def _assert_same(a: EditState, b: EditState) -> None:
    for x, y in zip(_leaves(a.device), _leaves(b.device), strict=True):
        np.testing.assert_array_equal(x, y)
        assert x.dtype == y.dtype
    np.testing.assert_array_equal(a.edited, b.edited)
    assert dataclasses.replace(a.host, edited=None) == dataclasses.replace(b.host, edited=None)


def test_replace_routes_each_field_to_its_part(state):
    st, _ = state
    moved = st.replace(step=9, images=st.images * 0, density=DensityTally(created=1))
    assert (moved.step, moved.density.created, moved.subtask) == (9, 1, 1)
    assert moved.device.train is st.device.train and float(np.sum(moved.images)) == 0.0
    assert st.step == 7  # never mutated
    with pytest.raises(TypeError):
        st.replace(no_such_field=1)
    assert isinstance(st.device, DeviceState) and jax.tree_util.tree_leaves(st.device)


def test_the_checkpoint_record_holds_the_host_fields_by_name(state, tmp_path):
    st, train = state
    save_checkpoint(tmp_path / "c.npz", st, {"plan": PLAN, "header": {}})
    arrays, info = read_pytree(tmp_path / "c.npz", kind=KIND)
    host = {f.name for f in dataclasses.fields(HostState)}
    assert set(info) == set(record_schema()) == host - {"edited"} | {"max_intersections", "meta"}
    assert {"['tracker'].best", "['images']", "['edited']"} <= set(arrays)
    loaded, meta = load_checkpoint(tmp_path / "c.npz", train)
    _assert_same(st, loaded)
    assert meta == {"plan": PLAN, "header": {}}


def test_a_checkpoint_of_the_earlier_layout_reads_as_the_same_state(state, tmp_path):
    """Before the tracker was stored whole: its losses as ``tracker_recent``, the rest in
    the record's ``tracker`` list (and no ``complete_at``, ``annealed_at``, ``density``)."""
    st, train = state
    save_checkpoint(tmp_path / "new.npz", st, {"plan": PLAN, "header": {}})
    arrays, info = read_pytree(tmp_path / "new.npz", kind=KIND)
    t = st.tracker
    arrays = {k: v for k, v in arrays.items() if not k.startswith("['tracker']")}
    arrays["['tracker_recent']"] = np.asarray(t.recent)
    info = dict(info, tracker=[int(t.count), float(t.best), int(t.since_best)])
    for key in ("complete_at", "annealed_at", "density"):
        del info[key]
    record = dict(version=FORMAT_VERSION, kind=KIND, paths=list(arrays), keys=[], meta=info)
    with open(tmp_path / "old.npz", "wb") as f:
        np.savez(f, __meta__=np.asarray(json.dumps(record)), **arrays)
    loaded, _ = load_checkpoint(tmp_path / "old.npz", train)
    _assert_same(st.replace(complete_at=-1, density=DensityTally()), loaded)
