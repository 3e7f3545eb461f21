"""Camera conventions: OpenCV projection, OpenGL<->OpenCV conversion, trajectories."""

import jax
import numpy as np
import pytest

from jaxedit import Camera
from jaxedit import camera as C


def test_look_at_projects_target_to_principal_point():
    cam = C.make_camera(C.look_at([3.0, 1.0, 2.0], [0.2, -0.1, 0.3]), width=64, height=48, focal=50.0)
    px, z = cam.project(np.array([[0.2, -0.1, 0.3]], np.float32))
    np.testing.assert_allclose(np.asarray(px[0]), [32.0, 24.0], atol=1e-4)
    assert float(z[0]) > 0


def test_image_axes_point_right_and_down():
    # Camera on -y axis looking at the origin with +z up: world +x is image right,
    # world +z is image up (so smaller v).
    cam = C.make_camera(C.look_at([0.0, -5.0, 0.0], [0.0, 0.0, 0.0]), width=100, height=100, focal=100.0)
    px, _ = cam.project(np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], np.float32))
    assert px[0, 0] > 50 and abs(px[0, 1] - 50) < 1e-4
    assert px[1, 1] < 50 and abs(px[1, 0] - 50) < 1e-4


def test_opengl_conversion_known_pose():
    # An OpenGL camera at (0, 0, 5) looking down -z (identity rotation) sees the origin at the
    # image centre, and a point at +x/+y (OpenGL up) to the right and ABOVE the centre.
    c2w = np.eye(4)
    c2w[:3, 3] = [0.0, 0.0, 5.0]
    w2c = C.opengl_c2w_to_opencv_w2c(c2w)
    cam = Camera(world_to_camera=w2c, fx=100.0, fy=100.0, cx=50.0, cy=40.0, width=100, height=80)
    px, z = cam.project(np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]], np.float32))
    np.testing.assert_allclose(np.asarray(px), [[50.0, 40.0], [70.0, 20.0]], atol=1e-4)
    np.testing.assert_allclose(np.asarray(z), [5.0, 5.0], atol=1e-6)
    np.testing.assert_allclose(C.opencv_w2c_to_opengl_c2w(w2c), c2w, atol=1e-12)


@pytest.mark.parametrize("make", [
    lambda: C.orbit(6, radius=3.0, elevation_deg=25.0, width=32, height=32),
    lambda: C.hemisphere(9, radius=2.5, width=32, height=32),
])
def test_trajectories_look_at_target(make):
    cams = make()
    assert cams.batch_shape == (len(cams),)
    centers = np.asarray(cams.center())
    assert np.all(centers[:, 2] > 0)  # upper hemisphere, +z up
    for i in range(len(cams)):
        px, z = cams[i].project(np.zeros((1, 3), np.float32))
        np.testing.assert_allclose(np.asarray(px[0]), [16.0, 16.0], atol=1e-3)
        r = np.asarray(cams[i].rotation)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-5)


def test_camera_is_a_pytree_with_static_size():
    cams = C.orbit(3, radius=2.0, width=20, height=10)
    leaves, treedef = jax.tree_util.tree_flatten(cams)
    assert len(leaves) == 5
    again = jax.tree_util.tree_unflatten(treedef, leaves)
    assert (again.width, again.height) == (20, 10)
    centers = jax.jit(jax.vmap(lambda c: c.center()))(cams)
    np.testing.assert_allclose(np.asarray(centers), np.asarray(cams.center()), atol=1e-5)


def test_scaled_camera_keeps_projection_consistent():
    cam = C.make_camera(C.look_at([2.0, 2.0, 1.0], [0, 0, 0]), width=64, height=64, fov_deg=50)
    half = cam.scaled(0.5)
    p = np.array([[0.1, 0.2, -0.1]], np.float32)
    np.testing.assert_allclose(np.asarray(half.project(p)[0]), np.asarray(cam.project(p)[0]) * 0.5,
                               atol=1e-4)
