"""Test-time pose refinement (jaxedit.poses) against an oracle: a scene rendered from known
cameras."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxedit import DataError, render, scenes
from jaxedit import gaussians as G
from jaxedit import train as T
from jaxedit.poses import (RefineConfig, apply_delta, correction_sizes, corrected_cameras,
                           init_corrections, refine_poses, scene_depth, so3_exp,
                           update_correction)

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


def _exact_scene(views: int, seed: int):
    """(true cameras [views], Gaussians of the face scene, their renders from those cameras,
    float64 [views, 6] corrections of 1 degree and 1% of the depth): an oracle whose images the
    Gaussians reproduce exactly from the true poses."""
    scene = scenes.get_scene("face")
    truth = scenes.rig_cameras(scene.rig, views, width=SIZE)
    rng = np.random.default_rng(seed)
    pts, rgb = scenes.sample_points(scene, truth, 3000, rng, position_noise=0.0, color_noise=0.0,
                                    outlier_fraction=0.0, min_views=1)
    g = G.from_points(pts, rgb, sh_degree=0, init_opacity=0.9)
    images = render(g, truth, background=jnp.ones(3)).rgb
    delta = rng.normal(size=(views, 6))
    delta[:, :3] *= np.radians(1.0) / np.linalg.norm(delta[:, :3], axis=1, keepdims=True)
    delta[:, 3:] *= 0.01 / np.linalg.norm(delta[:, 3:], axis=1, keepdims=True)
    return truth, g, images, delta


def test_refinement_recovers_perturbed_poses_and_keeps_exact_ones():
    """Face-scene Gaussians render the targets from known cameras; two cameras start 1 degree
    and 1% of the depth off, a third exactly right. All must end at the truth."""
    truth, g, images, delta = _exact_scene(3, seed=0)
    bg = jnp.ones(3)
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


# --------------------------------------------------------------------------------------
# Training-time camera optimisation (TrainConfig.camera_opt)
# --------------------------------------------------------------------------------------

def test_sparse_adam_moves_only_the_trained_view():
    corr = init_corrections(jnp.array([1.0, 2.0, 3.0]))
    grad = jnp.array([1.0, -1.0, 0.5, 0.0, 2.0, -3.0])
    step = update_correction(corr, jnp.int32(1), grad, jnp.float32(1e-2))
    delta = np.asarray(step.delta)
    np.testing.assert_array_equal(delta[[0, 2]], 0.0)
    # Adam's first step moves every coordinate with a gradient by the learning rate.
    np.testing.assert_allclose(delta[1], -1e-2 * np.sign(np.asarray(grad)), atol=1e-6)
    np.testing.assert_array_equal(np.asarray(step.adam.count), [0, 1, 0])
    # A zero learning rate (before camera_opt_from) leaves the row and its moments alone.
    frozen = update_correction(step, jnp.int32(1), grad, jnp.float32(0.0))
    for a, b in zip(jax.tree_util.tree_leaves(frozen), jax.tree_util.tree_leaves(step)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


# slow tier: a reconstruction with camera optimisation to a pose-error bar (the CLI's
# camera_opt run and test-time refinement stay in the default tier)
@pytest.mark.slow
def test_training_recovers_perturbed_training_poses():
    """The oracle of the training step's pose gradient: Gaussians that render the targets
    exactly from known cameras, held (near) fixed by tiny learning rates, and training
    cameras that start 1 degree and 1% of the depth off. Camera optimisation must bring
    every view back."""
    truth, g, images, delta = _exact_scene(6, seed=1)
    noisy = apply_delta(truth, jnp.asarray(delta, jnp.float32), scene_depth(g, truth))
    tiny = 1e-12
    config = T.TrainConfig(
        iterations=360, sh_degree=0, lambda_dssim=0.0, lr_means=tiny, lr_means_final=tiny,
        lr_sh_dc=tiny, lr_opacity=tiny, lr_scales=tiny, lr_quats=tiny,
        camera_opt=True, lr_camera=4e-3, lr_camera_final=4e-5, camera_opt_from=0,
        densify=T.DensifyConfig(warmup=10**6, reset_every=0))
    state = T.init_state(g, config, T.scene_extent(truth), cameras=noisy)
    state = T.fit(state, images, noisy, max_loss=None)
    fixed = corrected_cameras(noisy, state.cameras)
    before, after = _angle_deg(noisy, truth), _angle_deg(fixed, truth)
    centre = np.linalg.norm(np.asarray(fixed.center()) - np.asarray(truth.center()), axis=1)
    depth = np.asarray(state.cameras.depth)
    print(f"rotation error {before} -> {after} deg, centre error {centre / depth} of the depth")
    assert (after < 0.05).all()
    assert (centre < 1e-3 * depth).all()
    sizes = correction_sizes(state.cameras)
    assert sizes["rotation_deg"].shape == (6,) and (sizes["rotation_deg"] > 0.5).all()
    with pytest.raises(DataError, match="cameras"):
        T.fit(state, images[:5], noisy[:5])


def test_camera_opt_checkpoint_round_trip(tmp_path):
    g = G.from_points(np.zeros((4, 3)) + [[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]],
                      np.full((4, 3), 0.5), sh_degree=0)
    cams = scenes.rig_cameras(scenes.get_scene("ball").rig, 3, width=16)
    config = T.TrainConfig(iterations=10, sh_degree=0, camera_opt=True)
    state = T.init_state(g, config, 1.0, cameras=cams)
    corr = update_correction(state.cameras, jnp.int32(2), jnp.arange(6.0), jnp.float32(0.1))
    state = dataclasses.replace(state, cameras=corr)
    loaded = T.load_checkpoint(T.save_checkpoint(tmp_path / "c.npz", state))
    assert loaded.config == config and loaded.cameras.num_views == 3
    for a, b in zip(jax.tree_util.tree_leaves(loaded.cameras), jax.tree_util.tree_leaves(corr)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(DataError, match="training cameras"):
        T.init_state(g, config, 1.0)
    with pytest.raises(DataError, match="lr_camera"):
        T.TrainConfig(lr_camera=0.0)
