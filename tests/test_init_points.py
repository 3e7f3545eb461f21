"""Starting points for datasets without a point cloud (jaxedit.capture.points)."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from jaxedit import scenes
from jaxedit.capture.points import background_fraction, random_points, view_box


def _inside(points, lo, hi) -> np.ndarray:
    return np.all((points >= lo) & (points <= hi), axis=-1)


def _overlap(lo, hi, s_lo, s_hi) -> float:
    """Fraction of the box [s_lo, s_hi] inside the box [lo, hi]."""
    inter = np.clip(np.minimum(hi, s_hi) - np.maximum(lo, s_lo), 0, None)
    return float(np.prod(inter) / np.prod(s_hi - s_lo))


def test_view_box_holds_the_scene_that_the_camera_centres_box_misses():
    for name in ("face", "tabletop", "ball"):
        scene = scenes.get_scene(name)
        cams = scenes.rig_cameras(scene.rig, 24, width=32)
        lo, hi = view_box(cams)
        s_lo, s_hi = scene.bounds()
        # Most of the scene (what every view frames: the face's shoulders leave the frame) ...
        assert _overlap(lo, hi, s_lo, s_hi) > 0.7, (name, lo, hi, s_lo, s_hi)
        # ... in a box that is not the whole world.
        assert np.prod(hi - lo) < 30 * np.prod(s_hi - s_lo), (name, hi - lo, s_hi - s_lo)
        if name == "tabletop":  # cameras circling above the table: their box misses it
            centres = np.asarray(cams.center(), np.float64)
            assert _overlap(centres.min(0), centres.max(0), s_lo, s_hi) < 0.3


def test_photo_consistent_points_land_on_the_object_and_take_its_colours():
    scene = scenes.get_scene("tabletop")
    cams = scenes.rig_cameras(scene.rig, 16, width=48)
    images = scenes.render_scene(scene, cams, supersample=1)
    key = jax.random.key(0)
    plain, plain_colors = random_points(images, cams, 2000, key, oversample=1)
    chosen, colors = random_points(images, cams, 2000, key)
    lo, hi = scene.bounds()
    assert _inside(chosen, lo, hi).mean() > 1.5 * _inside(plain, lo, hi).mean()
    assert chosen.shape == colors.shape == (2000, 3) and chosen.dtype == np.float32
    assert colors.min() >= 0 and colors.max() <= 1
    # Kept points are coloured by what the views see there, not at random.
    assert abs(colors.mean() - images.mean()) < abs(plain_colors.mean() - images.mean()) + 0.05


def test_background_carving_keeps_points_out_of_free_space():
    scene = scenes.get_scene("tabletop")
    cams = scenes.rig_cameras(scene.rig, 16, width=48)
    images = scenes.render_scene(scene, cams, supersample=1)
    key = jax.random.key(0)
    plain, _ = random_points(images, cams, 2000, key)
    carved, colors = random_points(images, cams, 2000, key, background=(1.0, 1.0, 1.0))
    lo, hi = scene.bounds()
    assert carved.shape == colors.shape == (2000, 3)
    assert _inside(carved, lo, hi).mean() > 0.6 > _inside(plain, lo, hi).mean()
    # Free-space points seen against the white background took its colour; carved ones do not.
    white = lambda c: np.mean(np.abs(c - 1.0).max(-1) <= 0.02)  # noqa: E731
    assert white(colors) < 0.01
    assert background_fraction(images, (1.0, 1.0, 1.0)) > 0.9  # the table leaves some views
    assert background_fraction(images, (0.0, 0.0, 0.0)) < 0.1


# slow tier: two reconstructions to a quality bar
@pytest.mark.slow
def test_a_dataset_without_points_reconstructs_within_2_db_of_one_with_points(tmp_path):
    """Issue 11 item 4: the starting points of a dataset without a cloud cost < 2 dB."""
    import dataclasses

    from jaxedit.io import load_nerfstudio
    from jaxedit.pipelines.reconstruct import reconstruct
    from jaxedit.train import TrainConfig

    scenes.make_scene("tabletop", tmp_path / "data", size=32, views=16, test_views=4,
                      num_points=2000)
    data = load_nerfstudio(tmp_path / "data")
    bare = dataclasses.replace(data, points=None, point_colors=None)
    config = TrainConfig(iterations=200)
    psnr = {}
    for name, d in (("points", data), ("random", bare)):
        m = reconstruct(d, tmp_path / name, config, checkpoint_every=0, log_every=100,
                        random_points=2000, init="auto" if name == "points" else "random")
        psnr[name] = m["test_psnr"]
    assert psnr["random"] > psnr["points"] - 2.0, psnr
