"""Properties of the densify/cull transformation (jaxedit.densify).

Shapes are fixed (capacity C = 48) across hypothesis examples so every strategy
compiles once; hypothesis draws the values (alive masks, opacities, scales,
gradients) through a seed.
"""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxedit import densify as D
from jaxedit import gaussians as G

C = 48
CAP = 40
EXTENT = 2.0
IMAGE = (64.0, 48.0)
CULL_ALPHA = 0.05

BUDGET_KW = dict(budget_min_new=3, budget_growth=0.1, budget_max_fraction=0.5)
BUDGET = D.creation_budget(min_new=3, growth=0.1, max_fraction=0.5)
COMMON = D.DensifyConfig(max_gaussians=CAP, refine_every=10, warmup=0, stop_at=1000,
                         reset_every=7, cull_alpha=CULL_ALPHA, dense_percent=0.05, cull_scale=0.5,
                         cull_screen=0.3)


def strategy_with(**changes) -> D.Strategy:
    """The strategy of COMMON with ``changes`` (DensifyConfig fields), on a scene of EXTENT."""
    s = D.strategy_for(dataclasses.replace(COMMON, **changes), iterations=2000)
    return D.Strategy(s.init, functools.partial(s.update, scene_extent=EXTENT))


BUDGETED = strategy_with(budget=True, **BUDGET_KW)
CLASSIC = strategy_with(budget=False, grad_threshold=2e-4)
NO_CREATE = strategy_with(budget=True, budget_min_new=0, budget_growth=0.0, budget_max_fraction=0.0)
UPD_BUDGETED = jax.jit(BUDGETED.update)
UPD_CLASSIC = jax.jit(CLASSIC.update)
UPD_NO_CREATE = jax.jit(NO_CREATE.update)
settings_ = settings(max_examples=25, deadline=None)


def random_case(seed, n_alive, capacity=C, last_culled=0):
    """Gaussians, ones-valued Adam state, stats and a RenderAux with mixed values."""
    rng = np.random.default_rng(seed)
    g = G.empty(capacity, sh_degree=1)
    alive = np.zeros(capacity, bool)
    alive[rng.choice(capacity, size=n_alive, replace=False)] = True
    opac = rng.choice([0.01, 0.03, 0.2, 0.6, 0.9], size=capacity)
    scale = EXTENT * rng.choice([0.01, 0.02, 0.2, 0.3, 0.8], size=(capacity, 1)) * rng.uniform(
        0.5, 1.0, size=(capacity, 3))
    g = dataclasses.replace(
        g,
        means=jnp.asarray(rng.normal(size=(capacity, 3)), jnp.float32),
        log_scales=jnp.asarray(np.log(scale), jnp.float32),
        quats=jnp.asarray(rng.normal(size=(capacity, 4)), jnp.float32),
        opacity_logits=jnp.asarray(np.log(opac / (1 - opac)), jnp.float32),
        sh=jnp.asarray(rng.normal(size=(capacity, 4, 3)), jnp.float32),
        alive=jnp.asarray(alive))
    params = dataclasses.replace(g, alive=None)
    opt_state = optax.adam(1e-3).init(params)
    opt_state = jax.tree_util.tree_map(lambda a: jnp.ones_like(a) if a.ndim else a, opt_state)
    stats = D.init_stats(capacity)._replace(last_culled=jnp.int32(last_culled))
    # Gradients of mixed magnitudes, some exactly tied, some Gaussians unseen.
    grad = rng.choice([0.0, 1e-6, 2e-6, 5e-6, 2e-5], size=(capacity, 1)) * rng.choice(
        [1.0, 1.0, 0.5], size=(capacity, 2))
    visible = alive & (rng.uniform(size=capacity) < 0.85)
    radii = rng.choice([1.0, 5.0, 30.0], size=capacity) * visible
    aux = D.RenderAux(grad_means2d=jnp.asarray(grad, jnp.float32), radii=jnp.asarray(radii),
                      visible=jnp.asarray(visible), image_size=jnp.asarray(IMAGE, jnp.float32))
    return g, opt_state, stats, aux


def np_expectations(g, stats, aux, step, budget, grad_threshold=2e-4):
    """A NumPy restatement of the rules (the oracle)."""
    alive = np.asarray(g.alive)
    opac = 1 / (1 + np.exp(-np.asarray(g.opacity_logits, np.float64)))
    max_scale = np.exp(np.asarray(g.log_scales, np.float64)).max(-1)
    vis = np.asarray(aux.visible)
    ndc = np.asarray(aux.grad_means2d, np.float64) * np.asarray(IMAGE) / 2
    norm = np.sqrt((ndc ** 2).sum(-1)) * vis
    radius = np.asarray(aux.radii, np.float64) / max(IMAGE) * vis
    fails = (opac < CULL_ALPHA) | (max_scale > 0.5 * EXTENT) | (radius > 0.3)
    culled = alive & fails
    alive1 = alive & ~culled
    cand = alive1 & vis & (norm > (grad_threshold if budget is None else 0.0))
    n_alive0 = alive.sum()
    t = cand.sum() if budget is None else int(budget(jnp.int32(int(stats.last_culled)),
                                                       jnp.int32(int(n_alive0))))
    k = min(t, cand.sum(), len(alive) - alive1.sum(), max(CAP - alive1.sum(), 0))
    return dict(culled=culled, alive1=alive1, cand=cand, score=norm, t=t, k=k,
                small=max_scale <= 0.05 * EXTENT)


def adam_nodes(opt_state):
    return opt_state[0].mu, opt_state[0].nu


@settings_
@given(seed=st.integers(0, 2**31 - 1), n_alive=st.integers(0, C), last=st.integers(0, 30))
def test_budgeted_update_obeys_cap_budget_and_culls_exactly(seed, n_alive, last):
    g, opt_state, stats, aux = random_case(seed, n_alive, last_culled=last)
    g2, o2, s2, info = UPD_BUDGETED(g, opt_state, stats, aux, 10, jax.random.key(seed))
    exp = np_expectations(g, stats, aux, 10, BUDGET)
    alive2 = np.asarray(g2.alive)
    assert alive2.sum() <= CAP
    assert int(info.alive) == alive2.sum()
    assert int(info.created) <= int(info.budget) == exp["t"]
    assert int(info.created) == exp["k"]
    assert int(info.culled) == exp["culled"].sum()
    assert int(info.split) + int(info.duplicated) == int(info.created)
    assert alive2.sum() == exp["alive1"].sum() + exp["k"]
    # Survivors stay alive; culled slots are dead unless re-used by a new Gaussian.
    assert np.all(alive2[exp["alive1"]])
    reused = exp["culled"] & alive2
    assert reused.sum() <= exp["k"]
    # Statistics restart and n is remembered for the next budget.
    assert int(s2.last_culled) == exp["culled"].sum()
    assert float(jnp.sum(s2.grad_sum)) == 0.0 and int(jnp.sum(s2.count)) == 0


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n_alive=st.integers(1, C), last=st.integers(0, 30))
def test_a_local_edits_budget_counts_the_gaussians_it_may_change(seed, n_alive, last):
    # t(n, N) of a local edit: N is the editable Gaussians alive, not the frozen ones too
    g, opt_state, stats, aux = random_case(seed, n_alive, last_culled=last)
    frozen = np.asarray(g.alive) & (np.random.default_rng(seed).uniform(size=C) < 0.6)
    *_, info = UPD_BUDGETED(g, opt_state, stats, aux, 10, jax.random.key(seed),
                            jnp.asarray(frozen))
    editable = int(np.asarray(g.alive).sum() - frozen.sum())
    assert int(info.budget) == int(BUDGET(jnp.int32(last), jnp.int32(editable)))


@settings_
@given(seed=st.integers(0, 2**31 - 1), n_alive=st.integers(0, C))
def test_cull_removes_exactly_the_failing_gaussians(seed, n_alive):
    g, opt_state, stats, aux = random_case(seed, n_alive)
    g2, o2, _, info = UPD_NO_CREATE(g, opt_state, stats, aux, 10, jax.random.key(0))
    exp = np_expectations(g, stats, aux, 10, D.creation_budget(min_new=0, growth=0.0,
                                                               max_fraction=0.0))
    assert int(info.created) == 0
    np.testing.assert_array_equal(np.asarray(g2.alive), exp["alive1"])
    # Freed slots have zeroed moments, survivors keep theirs.
    for node in adam_nodes(o2):
        m = np.asarray(node.means)
        assert np.all(m[exp["culled"]] == 0) and np.all(m[exp["alive1"]] == 1)


@settings_
@given(seed=st.integers(0, 2**31 - 1), n_alive=st.integers(0, C))
def test_classic_threshold_picks_highest_gradients_and_zeroes_new_moments(seed, n_alive):
    g, opt_state, stats, aux = random_case(seed, n_alive)
    g2, o2, _, info = UPD_CLASSIC(g, opt_state, stats, aux, 10, jax.random.key(seed))
    exp = np_expectations(g, stats, aux, 10, None)
    assert int(info.candidates) == exp["cand"].sum()
    assert int(info.created) == exp["k"]
    # Which Gaussians were refined: the k best by score, ties broken by lower slot index.
    order = sorted(np.flatnonzero(exp["cand"]), key=lambda i: (-np.float32(exp["score"][i]), i))
    chosen = np.zeros(C, bool)
    chosen[order[:exp["k"]]] = True
    assert int(info.split) == (chosen & ~exp["small"]).sum()
    assert int(info.duplicated) == (chosen & exp["small"]).sum()
    alive0, alive2 = np.asarray(g.alive), np.asarray(g2.alive)
    new_slots = alive2 & ~exp["alive1"]
    assert new_slots.sum() == exp["k"]
    # New slots take the lowest free indices.
    free = np.flatnonzero(~exp["alive1"])
    np.testing.assert_array_equal(np.flatnonzero(new_slots), free[:exp["k"]])
    split_parents = chosen & ~exp["small"]
    for node in adam_nodes(o2):
        for field in ("means", "log_scales", "quats", "opacity_logits", "sh"):
            a = np.asarray(getattr(node, field)).reshape(C, -1)
            assert np.all(a[new_slots] == 0) and np.all(a[split_parents] == 0)
            keep = exp["alive1"] & ~split_parents
            assert np.all(a[keep] == 1)
    # Duplicates are exact copies; split children have scales / 1.6.
    src_of_new = np.array(order[:exp["k"]], int)
    for slot, src in zip(np.flatnonzero(new_slots), src_of_new):
        if exp["small"][src]:
            np.testing.assert_array_equal(np.asarray(g2.means[slot]), np.asarray(g.means[src]))
            np.testing.assert_array_equal(np.asarray(g2.sh[slot]), np.asarray(g.sh[src]))
        else:
            np.testing.assert_allclose(np.asarray(g2.log_scales[slot]),
                                       np.asarray(g.log_scales[src]) - np.log(1.6), rtol=1e-6)
            np.testing.assert_allclose(np.asarray(g2.log_scales[src]),
                                       np.asarray(g.log_scales[src]) - np.log(1.6), rtol=1e-6)
    assert alive0.sum() - int(info.culled) + int(info.created) == alive2.sum()


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n_alive=st.integers(1, C))
def test_jit_matches_eager_and_fixed_key_is_deterministic(seed, n_alive):
    g, opt_state, stats, aux = random_case(seed, n_alive)
    key = jax.random.key(seed)
    a = UPD_BUDGETED(g, opt_state, stats, aux, 10, key)
    b = BUDGETED.update(g, opt_state, stats, aux, 10, key)
    c = UPD_BUDGETED(g, opt_state, stats, aux, 10, key)
    for x, y, z in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b),
                       jax.tree_util.tree_leaves(c)):
        x, y, z = np.asarray(x), np.asarray(y), np.asarray(z)
        np.testing.assert_array_equal(x, z)
        if x.dtype.kind == "f":
            np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6)
        else:
            np.testing.assert_array_equal(x, y)


def test_split_children_follow_the_parent_and_depend_on_the_key():
    g, opt_state, stats, aux = random_case(3, 30)
    big = jnp.full((C, 3), np.log(0.2 * EXTENT), jnp.float32)
    g = dataclasses.replace(g, log_scales=big, opacity_logits=jnp.full((C,), 2.0))
    aux = aux._replace(grad_means2d=jnp.full((C, 2), 1e-3), visible=g.alive,
                       radii=jnp.ones((C,)))
    a = UPD_CLASSIC(g, opt_state, stats, aux, 10, jax.random.key(1))
    b = UPD_CLASSIC(g, opt_state, stats, aux, 10, jax.random.key(2))
    assert int(a[3].split) > 0 and int(a[3].duplicated) == 0
    assert not np.array_equal(np.asarray(a[0].means), np.asarray(b[0].means))
    moved = np.asarray(a[0].means - g.means)[np.asarray(g.alive)]
    # Offsets are draws of the parent's Gaussian (sigma = 0.4): not zero, rarely beyond 5 sigma.
    dist = np.linalg.norm(moved, axis=-1)
    assert (dist > 0).sum() == int(a[3].split) == CAP - 30  # the cap leaves room for 10
    assert np.all(dist < 5 * 0.4 * np.sqrt(3))


def test_nothing_happens_outside_maintenance_steps_but_stats_accumulate():
    g, opt_state, stats, aux = random_case(5, 30)
    g2, o2, s2, info = UPD_BUDGETED(g, opt_state, stats, aux, 9, jax.random.key(0))
    assert not bool(info.refined) and int(info.created) == 0 and int(info.culled) == 0
    np.testing.assert_array_equal(np.asarray(g2.alive), np.asarray(g.alive))
    vis = np.asarray(aux.visible)
    np.testing.assert_array_equal(np.asarray(s2.count), vis.astype(np.int32))
    ndc = np.asarray(aux.grad_means2d) * np.asarray(IMAGE) / 2
    np.testing.assert_allclose(np.asarray(s2.grad_sum), np.linalg.norm(ndc, axis=-1) * vis,
                               rtol=1e-6)
    late = strategy_with(budget=True, stop_at=5, **BUDGET_KW)
    info = jax.jit(late.update)(g, opt_state, stats, aux, 10, jax.random.key(0))[3]
    assert not bool(info.refined)


@pytest.mark.parametrize("warmup,from_warmup,want", [
    (3, True, [3, 13, 23]),  # the clock starts at the warm-up: exactly W steps without
    (3, False, [10, 20, 30]),  # INRIA's clock: a warm-up below refine_every changes nothing
    (0, True, [10, 20, 30]),
    (15, False, [20, 30]),
    (15, True, [15, 25])])
def test_maintenance_steps_follow_the_warmup_clock(warmup, from_warmup, want):
    g, opt_state, stats, _ = random_case(2, 20)
    strategy = strategy_with(budget=True, warmup=warmup, refine_from_warmup=from_warmup,
                             reset_every=0, stop_at=1000, **BUDGET_KW)
    due = jax.jit(jax.vmap(lambda s: strategy.update(g, opt_state, stats, None, s,
                                                     jax.random.key(0))[3].refined))
    steps = np.arange(1, 31)
    assert list(steps[np.asarray(due(jnp.asarray(steps)))]) == want


def test_ties_are_broken_by_slot_index():
    g, opt_state, stats, aux = random_case(11, 20)
    g = dataclasses.replace(g, opacity_logits=jnp.full((C,), 2.0),
                            log_scales=jnp.full((C, 3), np.log(0.01 * EXTENT), jnp.float32))
    aux = aux._replace(grad_means2d=jnp.full((C, 2), 1e-3), visible=g.alive,
                       radii=jnp.ones((C,)))
    strategy = strategy_with(budget=True, budget_min_new=4, budget_growth=0.0,
                             budget_max_fraction=0.0)
    g2, _, _, info = jax.jit(strategy.update)(g, opt_state, stats, aux, 10, jax.random.key(0))
    assert int(info.created) == 4 and int(info.duplicated) == 4
    first4 = np.flatnonzero(np.asarray(g.alive))[:4]
    new = np.flatnonzero(np.asarray(g2.alive) & ~np.asarray(g.alive))
    np.testing.assert_array_equal(np.asarray(g2.means)[new], np.asarray(g.means)[first4])


def test_capacity_growth_redo_creates_what_the_small_capacity_could_not():
    cap = 200
    strategy = strategy_with(max_gaussians=cap, cull_scale=None, cull_screen=None)
    g, opt_state, stats, aux = random_case(2, 30, capacity=32)
    g = dataclasses.replace(g, opacity_logits=jnp.full((32,), 2.0))
    aux = aux._replace(grad_means2d=jnp.full((32, 2), 1e-3), visible=g.alive,
                       radii=jnp.ones((32,)))
    key = jax.random.key(4)
    upd = jax.jit(strategy.update)
    _, _, _, info = upd(g, opt_state, stats, aux, 10, key)
    assert bool(info.capacity_limited) and not bool(info.cap_limited)
    assert int(info.created) == 2 and int(info.slots_needed) == 60
    new_cap = D.grown_capacity(32, int(info.slots_needed), cap)
    assert new_cap == 64
    g_big, o_big, s_big = D.grow_state(g, opt_state, stats, new_cap)
    assert g_big.capacity == 64 and s_big.grad_sum.shape == (64,)
    assert adam_nodes(o_big)[0].means.shape == (64, 3)
    g2, _, _, info2 = upd(g_big, o_big, s_big, aux._replace(
        grad_means2d=jnp.pad(aux.grad_means2d, ((0, 32), (0, 0))),
        radii=jnp.pad(aux.radii, (0, 32)), visible=jnp.pad(aux.visible, (0, 32))), 10, key)
    assert not bool(info2.capacity_limited) and int(info2.created) == 30
    assert int(g2.num_alive()) == 60
    assert D.grown_capacity(64, 500, cap) == cap


def test_hard_cap_holds_when_capacity_exceeds_it():
    strategy = strategy_with(max_gaussians=35)
    g, opt_state, stats, aux = random_case(9, 30)
    g = dataclasses.replace(g, opacity_logits=jnp.full((C,), 2.0),
                            log_scales=jnp.full((C, 3), np.log(0.01 * EXTENT), jnp.float32))
    aux = aux._replace(grad_means2d=jnp.full((C, 2), 1e-3), visible=g.alive,
                       radii=jnp.ones((C,)))
    g2, _, _, info = jax.jit(strategy.update)(g, opt_state, stats, aux, 10, jax.random.key(0))
    assert int(g2.num_alive()) == 35 and int(info.created) == 5
    assert bool(info.cap_limited) and not bool(info.capacity_limited)


def test_opacity_reset_set_and_clamp():
    g, opt_state, _, _ = random_case(1, 20)
    g_set, o_set = D.opacity_reset(g, opt_state, 0.05)
    alive = np.asarray(g.alive)
    op = np.asarray(g_set.opacities())
    np.testing.assert_allclose(op[alive], 0.05, rtol=1e-5)
    assert np.all(op[~alive] == 0)
    g_clamp, _ = D.opacity_reset(g, None, 0.05, clamp=True)
    before = np.asarray(g.opacities())[alive]
    np.testing.assert_allclose(np.asarray(g_clamp.opacities())[alive], np.minimum(before, 0.05),
                               rtol=1e-5)
    for node in adam_nodes(o_set):
        assert np.all(np.asarray(node.opacity_logits) == 0)
        assert np.all(np.asarray(node.means) == 1)


@pytest.mark.parametrize("value", [0.005, 0.01, 0.1, 0.3])
def test_an_opacity_reset_to_the_cull_threshold_culls_nothing(value):
    # In float32 sigmoid(logit(0.005)) rounds one ulp below 0.005: the cull would remove
    # every Gaussian no view had updated since the reset.
    g, _, _, _ = random_case(2, 20)
    g_set, _ = D.opacity_reset(g, None, value)
    op = np.asarray(g_set.opacities())[np.asarray(g.alive)]
    assert np.all(op >= np.float32(value)) and np.allclose(op, value, rtol=1e-6)


def test_periodic_reset_runs_inside_update():
    strategy = strategy_with(reset_every=20)
    g, opt_state, stats, aux = random_case(4, 25)
    g2, o2, _, info = jax.jit(strategy.update)(g, opt_state, stats, aux, 20, jax.random.key(0))
    assert bool(info.reset)
    assert float(jnp.max(g2.opacities())) <= 2 * CULL_ALPHA + 1e-6


def test_creation_budget_default_shape():
    t = D.creation_budget(min_new=10, growth=0.02, max_fraction=0.1)
    assert int(t(jnp.int32(0), jnp.int32(100))) == 10          # min_new floor
    assert int(t(jnp.int32(50), jnp.int32(10_000))) == 250      # n + 2% N
    assert int(t(jnp.int32(5000), jnp.int32(10_000))) == 1000   # capped at 10% N
    with pytest.raises(ValueError):
        D.creation_budget(min_new=0, growth=-1.0, max_fraction=0.1)


def test_named_operations_against_numpy():
    """cull_mask, select, split and place, each alone, against NumPy transcriptions."""
    g, _, stats, aux = random_case(3, n_alive=30)
    stats = D.accumulate(stats, aux)
    # cull: low opacity or too large, alive only (no screen rule before ``screen_from``).
    culled = np.asarray(D.cull_mask(g, stats, 5, cull_alpha=CULL_ALPHA, big_scale=0.5 * EXTENT,
                                    cull_screen=0.3, screen_from=7))
    opac = 1 / (1 + np.exp(-np.asarray(g.opacity_logits)))
    big = np.exp(np.asarray(g.log_scales)).max(-1) > 0.5 * EXTENT
    np.testing.assert_array_equal(culled, ((opac < CULL_ALPHA) | big) & np.asarray(g.alive))
    g1 = D.remove(g, jnp.asarray(culled))
    assert int(g1.num_alive()) == int(g.num_alive()) - int(culled.sum())
    # select: the best ``budget`` candidates by mean gradient, ties by slot.
    sel = D.select(stats, g1.alive, floor=0.0, budget=jnp.int32(4), max_gaussians=CAP)
    avg = np.asarray(stats.grad_sum) / np.maximum(np.asarray(stats.count), 1)
    cand = np.asarray(g1.alive) & (np.asarray(stats.count) > 0) & (avg > 0)
    best = sorted(np.flatnonzero(cand), key=lambda i: (-avg[i], i))
    k = min(4, len(best), CAP - int(g1.num_alive()), C - int(g1.num_alive()))
    assert int(sel.count) == k
    np.testing.assert_array_equal(np.flatnonzero(np.asarray(sel.selected)), sorted(best[:k]))
    # split: children = parent mean + R (eps * scale), scales / factor.
    key = jax.random.key(5)
    first, second = D.split(g1, sel.selected, key, 1.6)
    eps = np.asarray(jax.random.normal(key, (C, 2, 3)))
    rot = np.asarray(g1.rotations())
    scale = np.exp(np.asarray(g1.log_scales))
    kids = np.asarray(g1.means)[:, None] + np.einsum("cij,ckj->cki", rot, eps * scale[:, None])
    s = np.asarray(sel.selected)
    np.testing.assert_allclose(np.asarray(first.means)[s], kids[s, 0], atol=1e-5)
    np.testing.assert_allclose(np.asarray(second.means)[s], kids[s, 1], atol=1e-5)
    np.testing.assert_array_equal(np.asarray(first.means)[~s], np.asarray(g1.means)[~s])
    np.testing.assert_allclose(np.asarray(first.log_scales)[s],
                               np.asarray(g1.log_scales)[s] - np.log(1.6), rtol=1e-6)
    # place: the j-th ranked row goes to the j-th free slot, now alive.
    placed, written = D.place(first, second, sel.order, sel.count)
    free = np.flatnonzero(~np.asarray(first.alive))[:k]
    np.testing.assert_array_equal(np.flatnonzero(np.asarray(written)), free)
    order = np.asarray(sel.order)[:k]
    np.testing.assert_array_equal(np.asarray(placed.means)[free], np.asarray(second.means)[order])
    assert int(placed.num_alive()) == int(first.num_alive()) + k
