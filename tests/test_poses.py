"""Test-time pose refinement (jaxedit.poses) against an oracle: a scene rendered from known
cameras."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from jaxedit import DataError, render, scenes
from jaxedit import gaussians as G
from jaxedit.poses import RefineConfig, apply_delta, refine_poses, scene_depth, so3_exp

SIZE = 40  # small: the oracle needs no detail, only texture to lock onto


def _angle_deg(a, b) -> np.ndarray:
    """Rotation angle between the world->camera rotations of two camera batches [B]."""
    ra = np.asarray(a.world_to_camera, np.float64)[:, :3, :3]
    rb = np.asarray(b.world_to_camera, np.float64)[:, :3, :3]
    rel = ra @ np.swapaxes(rb, -1, -2)
    # atan2 of the axis part over the trace part: arccos loses small angles in float32.
    sin = 0.5 * np.linalg.norm(np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0],
                                         rel[:, 1, 0] - rel[:, 0, 1]], -1), axis=-1)
    return np.degrees(np.arctan2(sin, (np.trace(rel, axis1=1, axis2=2) - 1) / 2))


def test_so3_exp_is_rodrigues():
    r = np.asarray(so3_exp(jnp.array([0.0, 0.0, np.pi / 2])))
    np.testing.assert_allclose(r, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-6)
    for omega in ([1e-9, 0, 0], [0.3, -0.2, 0.1]):
        r = np.asarray(so3_exp(jnp.array(omega)), np.float64)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-6)
    np.testing.assert_allclose(so3_exp(jnp.zeros(3)), np.eye(3), atol=0)


def test_refinement_recovers_perturbed_poses_and_keeps_exact_ones():
    """Face-scene Gaussians render the targets from known cameras; two cameras start 1 degree
    and 1% of the depth off, a third exactly right. All must end at the truth."""
    scene = scenes.get_scene("face")
    truth = scenes.rig_cameras(scene.rig, 3, width=SIZE)
    rng = np.random.default_rng(0)
    pts, rgb = scenes.sample_points(scene, truth, 3000, rng, position_noise=0.0, color_noise=0.0,
                                    outlier_fraction=0.0, min_views=1)
    g = G.from_points(pts, rgb, sh_degree=0, init_opacity=0.9)
    bg = jnp.ones(3)
    images = render(g, truth, background=bg).rgb
    delta = rng.normal(size=(3, 6))
    delta[:, :3] *= np.radians(1.0) / np.linalg.norm(delta[:, :3], axis=1, keepdims=True)
    delta[:, 3:] *= 0.01 / np.linalg.norm(delta[:, 3:], axis=1, keepdims=True)
    delta[2] = 0.0
    depth = np.asarray(scene_depth(g, truth))
    start = apply_delta(truth, jnp.asarray(delta, jnp.float32), depth)
    np.testing.assert_allclose(_angle_deg(start, truth), [1.0, 1.0, 0.0], atol=1e-3)

    refined, info = refine_poses(g, start, images, background=bg,
                                 config=RefineConfig(steps=120, lr=4e-3))
    angle = _angle_deg(refined, truth)
    centre = np.linalg.norm(np.asarray(refined.center()) - np.asarray(truth.center()), axis=1)
    print(f"rotation error after {angle} deg, centre error {centre / depth} of the depth")
    assert (angle < 0.05).all()
    assert (centre < 2e-3 * depth).all()
    assert info["loss"].shape == (120, 3)
    assert (info["loss"][-1, :2] < 0.1 * info["loss"][0, :2]).all()
    # Intrinsics are never touched.
    np.testing.assert_array_equal(np.asarray(refined.fx), np.asarray(truth.fx))


def test_refine_poses_rejects_images_of_another_shape():
    g = G.from_points(np.zeros((4, 3)) + [[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]],
                      np.full((4, 3), 0.5), sh_degree=0)
    cams = scenes.rig_cameras(scenes.get_scene("ball").rig, 2, width=16)
    with pytest.raises(DataError, match="expected shape"):
        refine_poses(g, cams, np.zeros((2, 8, 8, 3)))
    with pytest.raises(DataError, match="steps"):
        refine_poses(g, cams, np.zeros((2, 16, 16, 3)), config=RefineConfig(steps=0))
