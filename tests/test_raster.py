"""The tile splatter against its dense oracle, and the splatter's invariances.

Every compositing backend (the XLA path and the Pallas kernel, the latter in the
Pallas interpreter on the CPU) is held to the same oracle tests. Shapes are fixed
per test (hypothesis draws seeds and values, never shapes) and the jitted
renderers are shared at module level, so each compiles once per backend.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from jaxedit import camera as cam_lib
from jaxedit.errors import DataError
from jaxedit.gaussians import Gaussians, grow, quat_to_rotmat
from jaxedit.raster import render, render_reference
from jaxedit.raster.render import next_capacity

W, H = 40, 36  # not a multiple of any tile size: partial tiles are exercised
N = 48
CAP = 8192
SETTINGS = settings(max_examples=6, deadline=None, derandomize=True)
PARAMS = ("means", "log_scales", "quats", "opacity_logits", "sh")


def make_scene(seed, n=N, sh_degree=1, spread=0.6, scale=(0.03, 0.25), dtype=np.float32):
    """Random Gaussians around the origin (fixed shapes, values from ``seed``)."""
    rng = np.random.default_rng(seed)
    k = (sh_degree + 1) ** 2
    sh = rng.normal(0.0, 0.25, (n, k, 3))
    sh[:, 0] = rng.normal(0.0, 1.0, (n, 3))
    return Gaussians(
        means=jnp.asarray(rng.normal(0.0, spread, (n, 3)), dtype),
        log_scales=jnp.asarray(np.log(rng.uniform(*scale, (n, 3))), dtype),
        quats=jnp.asarray(rng.normal(size=(n, 4)), dtype),
        opacity_logits=jnp.asarray(rng.normal(0.0, 1.5, n), dtype),
        sh=jnp.asarray(sh, dtype),
        alive=jnp.ones(n, bool),
    )


def make_camera(eye=(0.3, -3.0, 0.8), width=W, height=H, focal=None):
    return cam_lib.make_camera(cam_lib.look_at(eye, (0.0, 0.0, 0.0)), width=width, height=height,
                               focal=float(focal or width))


CAM = make_camera()
BG = jnp.array([0.1, 0.2, 0.3], jnp.float32)


BACKENDS = ("xla", "pallas")


def _fwd(backend):
    @functools.partial(jax.jit, static_argnames=("capacity",))
    def fwd(g, cam, capacity=CAP):
        # render() inside a caller's jit: the caller's buffer, the caller's overflow check.
        return render(g, cam, background=BG, max_intersections=capacity, backend=backend)

    return fwd


TILES_FWD = {b: _fwd(b) for b in BACKENDS}
tiles_fwd = TILES_FWD["xla"]


@jax.jit
def ref_fwd(g, cam):
    return render_reference(g, cam, background=BG)


def scalar_loss(out, weights):
    w_rgb, w_alpha, w_depth = weights
    return (jnp.sum(out.rgb * w_rgb) + jnp.sum(out.alpha * w_alpha)
            + 0.1 * jnp.sum(out.depth * out.alpha * w_depth))


def loss_weights(seed, height=H, width=W):
    rng = np.random.default_rng(seed + 1000)
    return (jnp.asarray(rng.normal(size=(height, width, 3)), jnp.float32),
            jnp.asarray(rng.normal(size=(height, width)), jnp.float32),
            jnp.asarray(rng.normal(size=(height, width)), jnp.float32))


def _grad(renderer):
    """jit(grad) of the scalar loss w.r.t. the Gaussians and the 2D-mean offsets."""
    def loss(g, delta, cam, weights):
        return scalar_loss(renderer(g, cam, delta), weights)

    return jax.jit(jax.grad(loss, argnums=(0, 1), allow_int=True))


TILES_GRAD = {b: _grad(lambda g, cam, d, b=b: render(g, cam, background=BG, means2d_delta=d,
                                                     max_intersections=CAP, backend=b))
              for b in BACKENDS}
tiles_grad = TILES_GRAD["xla"]
ref_grad = _grad(lambda g, cam, d: render_reference(g, cam, background=BG, means2d_delta=d))
ZEROS2D = jnp.zeros((N, 2), jnp.float32)


def assert_images_close(a, b, atol=1e-5):
    np.testing.assert_allclose(np.asarray(a.rgb), np.asarray(b.rgb), rtol=0, atol=atol)
    np.testing.assert_allclose(np.asarray(a.alpha), np.asarray(b.alpha), rtol=0, atol=atol)
    # Expected depth is a ratio (sum w z / alpha): compare it relative to its size.
    np.testing.assert_allclose(np.asarray(a.depth), np.asarray(b.depth), rtol=1e-5, atol=atol)


def assert_grads_close(ga, gb, rtol=1e-3, atol=1e-6):
    """Per parameter: |a - b| <= rtol * max|b| + atol (float32 sums of many terms)."""
    for name in PARAMS:
        a, b = np.asarray(getattr(ga, name)), np.asarray(getattr(gb, name))
        assert np.all(np.isfinite(a)), name
        scale = float(np.max(np.abs(b)))
        err = float(np.max(np.abs(a - b)))
        assert err <= rtol * scale + atol, f"{name}: max error {err} vs scale {scale}"


# --------------------------------------------------------------------------- known pixel
@pytest.mark.parametrize("backend", BACKENDS)
def test_one_gaussian_lands_on_the_expected_pixel(backend):
    # Camera at the origin looking down +z; principal point at the centre of pixel (12, 7).
    cam = cam_lib.Camera(world_to_camera=np.eye(4, dtype=np.float32), fx=20.0, fy=20.0,
                         cx=12.5, cy=7.5, width=W, height=H)
    x, y, z = 0.5, -0.25, 5.0  # -> u = 20 * 0.1 + 12.5 = 14.5, v = 20 * -0.05 + 7.5 = 6.5
    dc = np.array([0.4, -0.2, 0.0])
    # One live Gaussian plus dead slots (same shapes as the other tests: no recompile).
    g = make_scene(0)
    g = dataclasses.replace(
        g, means=g.means.at[0].set(jnp.array([x, y, z])),
        log_scales=g.log_scales.at[0].set(np.log(0.05)),
        quats=g.quats.at[0].set(jnp.array([2.0, 0.0, 0.0, 0.0])),  # unnormalised identity
        opacity_logits=g.opacity_logits.at[0].set(0.0),  # opacity 0.5
        sh=g.sh.at[0].set(0.0).at[0, 0].set(jnp.asarray(dc, jnp.float32)),
        alive=jnp.arange(N) == 0)
    for fn in (TILES_FWD[backend], ref_fwd):
        out = fn(g, cam)
        np.testing.assert_allclose(np.asarray(out.means2d[0]), [14.5, 6.5], atol=1e-5)
        alpha = np.asarray(out.alpha)
        assert np.unravel_index(np.argmax(alpha), alpha.shape) == (6, 14)  # (row, column)
        assert alpha[6, 14] == pytest.approx(0.5, abs=1e-6)  # dx = dy = 0: alpha = opacity
        colour = 0.5 + 0.28209479177387814 * dc
        np.testing.assert_allclose(np.asarray(out.rgb[6, 14]), 0.5 * colour + 0.5 * np.asarray(BG),
                                   atol=1e-6)
        assert float(out.depth[6, 14]) == pytest.approx(z, rel=1e-6)
        assert int(out.radii[0]) > 0 and bool(out.visible[0])
        assert not np.any(np.asarray(out.visible[1:]))
        # Symmetric neighbours get the same alpha (the 2D Gaussian is isotropic here).
        assert alpha[6, 13] == pytest.approx(alpha[6, 15], abs=1e-7)
        assert alpha[5, 14] == pytest.approx(alpha[7, 14], abs=1e-7)
        # Far from the Gaussian nothing is drawn: the background shows through.
        np.testing.assert_allclose(np.asarray(out.rgb[30, 35]), np.asarray(BG), atol=1e-7)


# --------------------------------------------------------------------------- oracle
@pytest.mark.parametrize("backend", BACKENDS)
@SETTINGS
@given(seed=st.integers(0, 2**31 - 1))
def test_tiles_match_oracle_values_and_gradients(backend, seed):
    g = make_scene(seed)
    a, b = TILES_FWD[backend](g, CAM), ref_fwd(g, CAM)
    assert not bool(a.overflow)
    assert_images_close(a, b)
    np.testing.assert_array_equal(np.asarray(a.radii), np.asarray(b.radii))
    np.testing.assert_allclose(np.asarray(a.means2d), np.asarray(b.means2d), atol=1e-5)
    weights = loss_weights(seed)
    (ga, da), (gb, db) = (TILES_GRAD[backend](g, ZEROS2D, CAM, weights),
                          ref_grad(g, ZEROS2D, CAM, weights))
    assert_grads_close(ga, gb)
    # The 2D-mean gradient (INRIA's densification statistic once scaled to NDC).
    da, db = np.asarray(da), np.asarray(db)
    assert np.all(da[~np.asarray(a.visible)] == 0) and np.any(da != 0)
    assert np.max(np.abs(da - db)) <= 1e-3 * np.max(np.abs(db)) + 1e-6


# --------------------------------------------------------------------------- invariances
@SETTINGS
@given(seed=st.integers(0, 2**31 - 1))
def test_permuting_gaussians_changes_nothing(seed):
    g = make_scene(seed)
    perm = np.random.default_rng(seed).permutation(N)
    gp = jax.tree_util.tree_map(lambda x: x[perm], g)
    a, b = tiles_fwd(g, CAM), tiles_fwd(gp, CAM)
    assert_images_close(a, b, atol=1e-6)
    weights = loss_weights(seed)
    ga, gpg = tiles_grad(g, ZEROS2D, CAM, weights)[0], tiles_grad(gp, ZEROS2D, CAM, weights)[0]
    for name in PARAMS:
        x, y = np.asarray(getattr(ga, name))[perm], np.asarray(getattr(gpg, name))
        np.testing.assert_allclose(y, x, rtol=0, atol=1e-5 * (1 + np.max(np.abs(x))))


def _quat_mul(q, r):
    w1, x1, y1, z1 = np.moveaxis(q, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(r, -1, 0)
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], -1)


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1))
def test_rigid_motion_of_scene_and_camera_changes_nothing(seed):
    rng = np.random.default_rng(seed)
    g = make_scene(seed, sh_degree=1)
    # View-dependent SH colours are defined in world axes: keep only DC for this test.
    g = dataclasses.replace(g, sh=g.sh.at[:, 1:].set(0.0))
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    rot = np.asarray(quat_to_rotmat(jnp.asarray(q, jnp.float32)), np.float64)
    shift = rng.normal(0.0, 2.0, 3)
    motion = np.eye(4)
    motion[:3, :3], motion[:3, 3] = rot, shift
    g2 = dataclasses.replace(
        g, means=jnp.asarray(np.asarray(g.means, np.float64) @ rot.T + shift, jnp.float32),
        quats=jnp.asarray(_quat_mul(q[None], np.asarray(g.quats, np.float64)), jnp.float32))
    cam2 = dataclasses.replace(CAM, world_to_camera=np.asarray(
        np.asarray(CAM.world_to_camera, np.float64) @ np.linalg.inv(motion), np.float32))
    a, b = tiles_fwd(g, CAM), tiles_fwd(g2, cam2)
    # The moved scene goes through different float32 roundings: compare loosely.
    np.testing.assert_allclose(np.asarray(b.rgb), np.asarray(a.rgb), atol=2e-3)
    np.testing.assert_allclose(np.asarray(b.alpha), np.asarray(a.alpha), atol=2e-3)
    np.testing.assert_allclose(np.asarray(b.means2d), np.asarray(a.means2d), atol=2e-3)
    assert_images_close(b, ref_fwd(g2, cam2))


@pytest.mark.parametrize("backend", BACKENDS)
def test_dead_and_behind_camera_gaussians_change_nothing_and_get_zero_gradient(backend):
    tiles_fwd, tiles_grad = TILES_FWD[backend], TILES_GRAD[backend]
    g = make_scene(3, n=N // 2)
    extra = make_scene(4, n=N // 2)
    # Half the extras are dead (in view!), half alive but behind the camera.
    eye = np.array([0.3, -3.0, 0.8])
    behind = np.asarray(extra.means) * 0.1 + eye + np.array([0.0, -1.0, 0.0]) * 2.0
    means = np.where(np.arange(N // 2)[:, None] < N // 4, np.asarray(extra.means), behind)
    extra = dataclasses.replace(extra, means=jnp.asarray(means, jnp.float32),
                                alive=jnp.asarray(np.arange(N // 2) >= N // 4))
    both = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), g, extra)
    only = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), g,
                                  dataclasses.replace(extra, alive=jnp.zeros(N // 2, bool)))
    a, b = tiles_fwd(both, CAM), tiles_fwd(only, CAM)
    assert_images_close(a, b, atol=1e-7)
    assert not np.any(np.asarray(a.visible[N // 2:]))
    assert np.all(np.asarray(a.radii[N // 2:]) == 0)
    weights = loss_weights(3)
    grads = tiles_grad(both, ZEROS2D, CAM, weights)[0]
    for name in PARAMS:
        x = np.asarray(getattr(grads, name))
        assert np.all(x[N // 2:] == 0), name
        assert np.any(x[: N // 2] != 0), name
    assert_images_close(a, ref_fwd(both, CAM))


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1))
def test_alpha_in_unit_interval_and_outputs_finite(seed):
    g = make_scene(seed, scale=(0.05, 0.6))  # big, overlapping: deep stacks
    out = tiles_fwd(g, CAM)
    alpha = np.asarray(out.alpha)
    assert np.all((alpha >= 0) & (alpha <= 1))
    for x in (out.rgb, out.depth, out.means2d):
        assert np.all(np.isfinite(np.asarray(x)))
    # Colour is a convex combination of non-negative colours and the background.
    assert np.all(np.asarray(out.rgb) >= 0)


# --------------------------------------------------------------------------- batching
@pytest.mark.parametrize("backend", BACKENDS)
def test_batched_cameras_equal_single_renders(backend):
    g = make_scene(11)
    cams = cam_lib.orbit(3, radius=3.0, width=W, height=H, focal=float(W))
    delta = jnp.zeros((3, N, 2), jnp.float32)
    out = render(g, cams, background=BG, means2d_delta=delta, backend=backend)
    assert out.rgb.shape == (3, H, W, 3) and out.means2d.shape == (3, N, 2)
    assert out.num_intersections.shape == (3,) and not np.any(np.asarray(out.overflow))
    for i in range(3):
        single = tiles_fwd(g, cams[i])
        assert_images_close(jax.tree_util.tree_map(lambda x: x[i], out), single, atol=1e-6)
        assert_images_close(single, ref_fwd(g, cams[i]))


# --------------------------------------------------------------------------- overflow
@pytest.mark.parametrize("backend", BACKENDS)
def test_too_small_buffer_still_yields_the_exact_image(backend):
    tiles_fwd = TILES_FWD[backend]
    g = make_scene(5)
    small = tiles_fwd(g, CAM, capacity=64)
    need = int(small.num_intersections)
    assert bool(small.overflow) and need > 64
    full = tiles_fwd(g, CAM)
    assert int(full.num_intersections) == need and not bool(full.overflow)
    assert np.max(np.abs(np.asarray(small.rgb) - np.asarray(full.rgb))) > 1e-3  # really dropped
    # render() starting from a buffer that is too small grows it and re-renders.
    out = render(g, CAM, background=BG, max_intersections=64, backend=backend)
    assert not bool(out.overflow)
    assert_images_close(out, ref_fwd(g, CAM))
    assert next_capacity(need) >= need


def test_renders_outside_a_trace_share_a_program_across_nearby_sizes():
    """render()'s own ladder is powers of two: scenes of 6000 and 8000 slots (one bucket of
    8192; two on the training ladder) render with one program, each frame the exact one."""
    from jaxedit.compilation import compile_stats
    from jaxedit.raster.render import render_capacity

    assert [render_capacity(n) for n in (1, 1024, 1025, 6144, 8192, 14336)] == \
        [1024, 1024, 2048, 8192, 8192, 16384]
    small, large = make_scene(5), make_scene(6)
    small = grow(small, 6000)  # dead slots: the same frame
    large = grow(large, 8000)
    render(small, CAM, background=BG)  # the 8192-slot program, compiled here if new
    before = compile_stats()
    out = render(large, CAM, background=BG)
    assert "render_tiles" not in compile_stats(since=before)["programs"]
    assert out.means2d.shape == (8000, 2)
    assert_images_close(out, ref_fwd(large, CAM))


def test_inside_jit_the_caller_owns_the_buffer():
    g = make_scene(5)
    small = tiles_fwd(g, CAM, capacity=64)  # render(max_intersections=64) under jit
    assert bool(small.overflow)
    assert int(tiles_fwd(g, CAM).num_intersections) == int(small.num_intersections)
    with pytest.raises(DataError, match="max_intersections"):
        jax.jit(lambda g: render(g, CAM).rgb)(g)


def test_bad_sh_degree_is_a_data_error():
    with pytest.raises(DataError, match="sh_degree"):
        render(make_scene(0, sh_degree=1), CAM, sh_degree=2)


# --------------------------------------------------------------------------- stress
# A camera at the origin looking down +z makes placing Gaussians in pixels easy.
CAM0 = cam_lib.Camera(world_to_camera=np.eye(4, dtype=np.float32), fx=30.0, fy=30.0,
                      cx=W / 2, cy=H / 2, width=W, height=H)


def at_pixels(u, v, z, cam=CAM0):
    """World points [n, 3] that project to pixel coordinates (u, v) at depth z."""
    u, v, z = np.broadcast_arrays(np.asarray(u, np.float64), np.asarray(v, np.float64),
                                  np.asarray(z, np.float64))
    return np.stack([(u - float(cam.cx)) * z / float(cam.fx),
                     (v - float(cam.cy)) * z / float(cam.fy), z], -1).astype(np.float32)


def check_against_oracle(g, cam=CAM0, seed=0, grads=True, backend="xla"):
    tiles_fwd, tiles_grad = TILES_FWD[backend], TILES_GRAD[backend]
    a, b = tiles_fwd(g, cam), ref_fwd(g, cam)
    assert not bool(a.overflow)
    for x in (a.rgb, a.alpha, a.depth, a.means2d):
        assert np.all(np.isfinite(np.asarray(x)))
    assert_images_close(a, b)
    weights = loss_weights(seed)
    (ga, da), (gb, db) = tiles_grad(g, ZEROS2D, cam, weights), ref_grad(g, ZEROS2D, cam, weights)
    for name in PARAMS:
        assert np.all(np.isfinite(np.asarray(getattr(ga, name)))), name
        assert np.all(np.isfinite(np.asarray(getattr(gb, name)))), name
    assert np.all(np.isfinite(np.asarray(da)))
    if grads:
        assert_grads_close(ga, gb)
    return a


@pytest.mark.parametrize("backend", BACKENDS)
@SETTINGS
@given(seed=st.integers(0, 2**31 - 1))
def test_stress_whole_scene_in_one_tile(backend, seed):
    # 48 Gaussians (more than a 32-pair chunk) inside pixels [8, 16)^2: one 8x8 tile,
    # opaque enough that pixels finish (T < 1e-4) part-way through the list.
    rng = np.random.default_rng(seed)
    g = make_scene(seed, scale=(0.02, 0.06))
    means = at_pixels(rng.uniform(9, 15, N), rng.uniform(9, 15, N), rng.uniform(1.0, 3.0, N))
    g = dataclasses.replace(g, means=jnp.asarray(means),
                            opacity_logits=jnp.asarray(rng.normal(3.0, 1.0, N), jnp.float32))
    out = check_against_oracle(g, seed=seed, backend=backend)
    assert float(jnp.max(out.alpha)) > 0.999  # some pixels hit the transmittance stop


@pytest.mark.parametrize("backend", BACKENDS)
@SETTINGS
@given(seed=st.integers(0, 2**31 - 1))
def test_stress_gaussians_straddling_tile_borders(backend, seed):
    rng = np.random.default_rng(seed)
    g = make_scene(seed, scale=(0.005, 0.05))
    # Centres exactly on 8- and 16-pixel tile borders and corners, and on the image edge.
    u = rng.choice([0.0, 8.0, 16.0, 24.0, 32.0, 40.0], N) + rng.choice([0.0, 1e-4, -1e-4], N)
    v = rng.choice([0.0, 8.0, 16.0, 24.0, 32.0, 36.0], N)
    g = dataclasses.replace(g, means=jnp.asarray(at_pixels(u, v, rng.uniform(1.0, 4.0, N))))
    check_against_oracle(g, seed=seed, backend=backend)


@pytest.mark.parametrize("backend", BACKENDS)
def test_stress_near_plane(backend):
    rng = np.random.default_rng(1)
    g = make_scene(1, scale=(0.001, 0.01))
    # Depths around near = 0.01: behind, on, just beyond it, and a little further.
    z = np.resize([-0.5, 0.0, 0.005, 0.01, 0.0100001, 0.0105, 0.02, 0.05, 0.2, 1.0], N)
    g = dataclasses.replace(g, means=jnp.asarray(at_pixels(rng.uniform(-20, 60, N),
                                                            rng.uniform(-20, 56, N), z)))
    out = check_against_oracle(g, backend=backend)
    assert not np.any(np.asarray(out.visible)[z <= 0.01])
    assert np.any(np.asarray(out.visible)[z > 0.01])


@pytest.mark.parametrize("backend", BACKENDS)
def test_stress_huge_and_tiny_scales_and_odd_quaternions(backend):
    rng = np.random.default_rng(2)
    g = make_scene(2)
    log_scales = np.asarray(g.log_scales).copy()
    log_scales[0::6] = 40.0  # huge (clipped to exp(20) inside)
    log_scales[1::6] = -40.0  # tiny: only the 0.3 px blur is left
    log_scales[2::6] = [5.0, -25.0, 0.0]  # needle
    quats = np.asarray(g.quats).copy()
    quats[0::4] = 0.0  # zero quaternion (identity rotation)
    quats[1::4] *= 1e4
    quats[2::4] *= 1e-4
    g = dataclasses.replace(g, log_scales=jnp.asarray(log_scales), quats=jnp.asarray(quats),
                            opacity_logits=jnp.asarray(rng.normal(-1.0, 1.0, N), jnp.float32))
    # A 1e5:1 needle's 2D covariance is ill-conditioned in float32 (for the oracle
    # too): gradients are compared in float64 in test_raster_grad_fd.py.
    check_against_oracle(g, cam=CAM, grads=False, backend=backend)


# --------------------------------------------------------------------------- backends
def test_auto_backend_is_pallas_on_gpu_and_xla_elsewhere():
    from jaxedit.raster.render import resolve_backend

    assert resolve_backend("auto", "gpu") == "pallas"
    assert resolve_backend("auto", "cpu") == "xla"
    assert resolve_backend("xla", "gpu") == "xla"
    with pytest.raises(DataError, match="backend"):
        resolve_backend("cuda")


def test_pallas_gradients_are_deterministic():
    # Per-pair gradient rows, one writer each, then a fixed-order reduction: no atomics.
    g = make_scene(7)
    weights = loss_weights(7)
    a = TILES_GRAD["pallas"](g, ZEROS2D, CAM, weights)
    b = TILES_GRAD["pallas"](g, ZEROS2D, CAM, weights)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_pallas_forward_and_backward_lower_for_cuda_from_any_machine():
    # The kernels are lowered to Triton (not run): what a CPU machine can check of the GPU path.
    from jaxedit.raster import pallas as PK
    from jaxedit.raster import render_tiles

    def loss(g, d, w):
        out = render_tiles(g, CAM, background=BG, means2d_delta=d, capacity=CAP, backend="pallas")
        return scalar_loss(out, w)

    fn = jax.jit(jax.value_and_grad(loss, argnums=(0, 1), allow_int=True))
    checks = [jax.export.DisabledSafetyCheck.custom_call("__gpu$xla.gpu.triton")]
    with PK.compiled_for_gpu():
        exported = jax.export.export(fn, platforms=("cuda",), disabled_checks=checks)(
            make_scene(0), ZEROS2D, loss_weights(0))
    # the forward, the backward and the per-Gaussian reduction of its rows
    assert exported.mlir_module().count("xla.gpu.triton") == 3
