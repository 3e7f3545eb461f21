"""A dense start on the surfaces a sparse cloud marks (jaxedit.capture.dense, issue 74.3)."""

from __future__ import annotations

import jax
import numpy as np

from jaxedit import camera as camlib
from jaxedit.capture.dense import (back_project, front_layer, interpolate_depth, project,
                                   surface_points, view_candidates)

SIZE = 40


def _plane_views(n: int = 6):
    """(noise images float32 [n, S, S, 3], cameras [n] orbiting the origin, sparse points
    [625, 3] on the plane z = 0.2)."""
    cams = camlib.orbit(n, radius=3.0, elevation_deg=70.0, width=SIZE, height=SIZE,
                        fov_deg=40.0)
    rng = np.random.default_rng(0)
    # Wider than every view's footprint: each pixel lies inside the points' hull.
    grid = np.stack(np.meshgrid(np.linspace(-4, 4, 25), np.linspace(-4, 4, 25)), -1)
    xy = grid.reshape(-1, 2) + rng.uniform(-0.1, 0.1, size=(625, 2))
    sparse = np.concatenate([xy, np.full((625, 1), 0.2)], -1)
    images = rng.uniform(0.2, 0.8, size=(n, SIZE, SIZE, 3)).astype(np.float32)
    return images, cams, sparse


def test_projection_and_back_projection_are_inverse():
    _, cams, sparse = _plane_views()
    w2c = np.asarray(cams.world_to_camera[1], np.float64)
    intr = np.array([float(cams.fx[1]), float(cams.fy[1]), float(cams.cx[1]), float(cams.cy[1])])
    u, v, z = project(sparse, w2c, intr)
    np.testing.assert_allclose(back_project(u, v, z, w2c, intr), sparse, atol=1e-5)
    # The jaxedit Camera agrees on where the points land.
    uv = np.asarray(cams[1].project(np.asarray(sparse, np.float32))[0], np.float64)
    np.testing.assert_allclose(np.stack([u, v], -1), uv[..., :2], atol=1e-2)


def test_inverse_depth_interpolation_is_exact_on_a_plane():
    _, cams, sparse = _plane_views()
    w2c = np.asarray(cams.world_to_camera[0], np.float64)
    intr = np.array([float(cams.fx[0]), float(cams.fy[0]), float(cams.cx[0]), float(cams.cy[0])])
    u, v, z = project(sparse, w2c, intr)
    rng = np.random.default_rng(1)
    # Query positions inside the points' hull (convex combinations of three of them).
    tri = rng.integers(0, len(u), size=(200, 3))
    wts = rng.dirichlet(np.ones(3), size=200)
    qu, qv = (u[tri] * wts).sum(-1), (v[tri] * wts).sum(-1)
    world = back_project(qu, qv, interpolate_depth(u, v, z, qu, qv), w2c, intr)
    np.testing.assert_allclose(world[:, 2], 0.2, atol=1e-6)
    # Outside the hull: the nearest point's depth, finite and positive.
    far = interpolate_depth(u, v, z, np.array([-50.0]), np.array([-50.0]))
    assert np.isfinite(far).all() and (far > 0).all()
    # Two points span no triangle: the nearest one's depth everywhere.
    two = interpolate_depth(u[:2], v[:2], z[:2], u[:2] + 0.1, v[:2])
    np.testing.assert_allclose(two, z[:2])


def test_front_layer_drops_points_hidden_behind_nearer_ones():
    u = np.array([10.0, 10.5, 30.0, 10.2, -1.0, -30.0, 20.0])
    v = np.array([10.0, 10.5, 30.0, 11.0, 5.0, 5.0, 20.0])
    z = np.array([2.0, 4.0, 4.0, 2.05, 2.0, 2.0, -1.0])
    front = front_layer(u, v, z, 40, 40, cell=4, tolerance=0.05, margin=0.25)
    # Behind a nearer point of its cell: hidden; alone in its corner: seen; just off the
    # image: kept (it bounds the border); far off it or behind the camera: not.
    np.testing.assert_array_equal(front, [True, False, True, True, True, False, False])


def test_dense_points_lie_on_the_plane_with_their_pixels_colours_and_are_seeded():
    images, cams, sparse = _plane_views()
    key = jax.random.key(3)
    pts, colors = surface_points(sparse, images, cams, 300, key)
    assert pts.shape == colors.shape == (300, 3) and pts.dtype == np.float32
    # Back-projected at the interpolated depth: on the plane the sparse points lie on.
    np.testing.assert_allclose(pts[:, 2], 0.2, atol=1e-3)
    # The colour of each is its pixel's in some view that drew it.
    w2c = np.asarray(cams.world_to_camera, np.float64)
    matched = np.zeros(len(pts), bool)
    for k in range(len(images)):
        intr = np.array([float(cams.fx[k]), float(cams.fy[k]), float(cams.cx[k]),
                         float(cams.cy[k])])
        u, v, z = project(pts, w2c[k], intr)
        ok = (u >= 0) & (u < SIZE) & (v >= 0) & (v < SIZE) & (z > 0)
        cols = np.clip(np.floor(u), 0, SIZE - 1).astype(int)
        rows = np.clip(np.floor(v), 0, SIZE - 1).astype(int)
        matched |= ok & np.all(np.abs(images[k][rows, cols] - colors) < 1e-6, axis=-1)
    assert matched.all()
    again = surface_points(sparse, images, cams, 300, key)
    np.testing.assert_array_equal(pts, again[0])
    np.testing.assert_array_equal(colors, again[1])
    other = surface_points(sparse, images, cams, 300, jax.random.key(4))[0]
    assert not np.array_equal(pts, other)


def test_views_that_see_no_sparse_point_are_skipped():
    images, cams, sparse = _plane_views()
    # Points behind every camera's back: no view sees any, nothing is drawn.
    behind = sparse * 0 + np.asarray(cams.center()[0], np.float64) * 3.0
    empty = surface_points(behind, images, cams, 100, jax.random.key(0))
    assert empty[0].shape == (0, 3) and empty[1].shape == (0, 3)
    assert view_candidates(behind, images[0], cams, 0, 50, jax.random.key(0))[0].shape == (0, 3)
    # Background pixels are not drawn: an all-background view gives no candidates.
    white = np.ones_like(images[0])
    assert view_candidates(sparse, white, cams, 0, 50, jax.random.key(0),
                           background=(1.0, 1.0, 1.0))[0].shape == (0, 3)
