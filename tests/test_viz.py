"""jaxedit.viz: depth colouring, grids, snapshots, orbit framing, turntables."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from hypothesis.extra import numpy as hnp

from jaxedit import DataError, camera as camlib, gaussians as G, viz
from jaxedit.io import load_ply, read_image
from jaxedit.pipelines.snapshots import write_snapshot

H = W = 8


@settings(max_examples=40, deadline=None)
@given(depth=hnp.arrays(np.float64, (H, W), elements=st.floats(0.1, 50.0)),
       alpha=hnp.arrays(np.float64, (H, W), elements=st.floats(0.0, 1.0)))
def test_colorize_depth_is_monotone_and_blends_over_background(depth, alpha):
    # With the grey colormap the brightness of a fully covered pixel *is* the
    # normalised closeness, so order and range can be checked exactly.
    near, far = viz.depth_range(depth, alpha)
    assert far > near
    solid = viz.colorize_depth(depth, np.ones_like(alpha), near=near, far=far, cmap="gray",
                               background=(0.0, 0.0, 0.0))
    assert solid.dtype == np.float32 and solid.shape == (H, W, 3)
    assert np.all((solid >= 0) & (solid <= 1))
    lum = solid[..., 0].ravel().astype(np.float64)
    order = np.argsort(depth.ravel(), kind="stable")
    assert np.all(np.diff(lum[order]) <= 1e-6), "nearer must never be darker"
    expected = np.clip((far - depth) / (far - near), 0, 1)
    np.testing.assert_allclose(solid[..., 0], expected, atol=2 / 255)  # colormap LUT quantisation
    # Partial coverage: linear blend with the background; uncovered pixels are blank.
    bg = np.array([0.2, 0.5, 0.9])
    out = viz.colorize_depth(depth, alpha, near=near, far=far, cmap="gray", background=bg)
    a = np.where(alpha > viz.MIN_ALPHA, alpha, 0.0)[..., None]
    np.testing.assert_allclose(out, a * solid + (1 - a) * bg, atol=1e-5)


def test_depth_range_ignores_background_and_outliers():
    rng = np.random.default_rng(0)
    depth = rng.uniform(2.0, 3.0, size=(40, 40))
    alpha = np.ones_like(depth)
    alpha[:, :10] = 0.0
    depth[:, :10] = 1e6  # background: meaningless depth
    depth[0, 20] = 1e4  # a single floater
    near, far = viz.depth_range(depth, alpha)
    assert 2.0 <= near < 2.1 and 2.9 < far <= 3.0
    assert viz.depth_range(depth, np.zeros_like(alpha)) == (0.0, 1.0)
    flat = viz.depth_range(np.full((4, 4), 5.0), np.ones((4, 4)))
    assert flat[0] < 5.0 < flat[1]
    # Turbo: near is warm (red), far is cool (blue).
    img = viz.colorize_depth(np.array([[2.0, 3.0]]), np.ones((1, 2)), near=2.0, far=3.0)
    assert img[0, 0, 0] > img[0, 0, 2] and img[0, 1, 2] > img[0, 1, 0]
    with pytest.raises(DataError, match="cmap"):
        viz.colorize_depth(depth, alpha, cmap="no-such-map")
    with pytest.raises(DataError, match="shape"):
        viz.colorize_depth(depth, alpha[:3])
    with pytest.raises(DataError, match="far"):
        viz.colorize_depth(depth, alpha, near=2.0, far=1.0)


def test_image_grid_places_images_row_major():
    imgs = [np.full((4, 5, 3), v, np.float32) for v in (0.1, 0.2, 0.3)]
    imgs.append(np.zeros((2, 3), np.uint8))  # grey uint8, smaller: top-left aligned
    grid = viz.image_grid(imgs, ncols=2, pad=1, pad_value=1.0)
    assert grid.shape == (2 * (4 + 1) + 1, 2 * (5 + 1) + 1, 3)
    assert np.all(grid[1:5, 1:6] == np.float32(0.1)) and np.all(grid[1:5, 7:12] == np.float32(0.2))
    assert np.all(grid[6:10, 1:6] == np.float32(0.3))
    assert np.all(grid[6:8, 7:10] == 0.0) and np.all(grid[8:10, 7:12] == 1.0)
    assert np.all(grid[0] == 1.0) and np.all(grid[:, 6] == 1.0)
    with pytest.raises(DataError):
        viz.image_grid([])
    with pytest.raises(DataError, match=r"images\[0\]"):
        viz.image_grid([np.zeros((2, 2, 4))])


def test_frame_cameras_recovers_the_orbit():
    target = np.array([0.3, -0.2, 0.5])
    cams = camlib.orbit(7, radius=2.5, elevation_deg=30.0, target=target, width=40, height=40,
                        fov_deg=50.0)
    t, radius, elevation, fov = viz.frame_cameras(cams)
    np.testing.assert_allclose(t, target, atol=1e-5)
    assert abs(radius - 2.5) < 1e-5 and abs(elevation - 30.0) < 1e-4 and abs(fov - 50.0) < 1e-4


def sphere_scene(n=48, seed=0):
    """``n`` opaque Gaussians on a sphere of radius 0.5, coloured by position.

    test_cli renders the same scene at the same size, so the renderer compiles once.
    """
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    pts = 0.5 * v / np.linalg.norm(v, axis=1, keepdims=True)
    return G.from_points(pts, np.clip(0.5 + pts, 0, 1), sh_degree=1, init_opacity=0.9)


def test_write_snapshot_and_turntable_with_the_renderer(tmp_path):
    g = sphere_scene()
    cams = camlib.hemisphere(2, radius=2.2, width=24, height=24, fov_deg=50.0)
    rec = write_snapshot(tmp_path / "snap", g, cams, turntable_frames=4, turntable_size=24,
                             background=(1.0, 1.0, 1.0))
    assert rec["ply"] == "scene.ply" and rec["renders"] == ["renders/view_000.png",
                                                              "renders/view_001.png"]
    assert rec["depth"] == ["depth/view_000.png", "depth/view_001.png"]
    assert rec["turntable"][0] == "turntable.webp"
    back = load_ply(tmp_path / "snap" / "scene.ply")
    np.testing.assert_array_equal(np.asarray(back.means), np.asarray(g.means))
    img = read_image(tmp_path / "snap" / "renders" / "view_000.png")
    assert img.shape == (24, 24, 3)
    # The object is in view and the corners show the white background.
    assert img[10:14, 10:14].mean() < 0.9 and np.allclose(img[0, 0], 1.0, atol=0.03)
    dep = read_image(tmp_path / "snap" / "depth" / "view_001.png")
    assert np.allclose(dep[0, 0], 1.0, atol=0.03) and dep[12, 12].std() > 0.05  # coloured centre
    frames = viz.read_webp_frames(tmp_path / "snap" / "turntable.webp")
    assert frames.shape == (4, 24, 24, 3)
    # Framed from the cameras: every frame sees the object in its centre.
    assert np.all(frames[:, 10:14, 10:14].mean(axis=(1, 2, 3)) < 230)
    # Without cameras, the orbit is framed from the Gaussians themselves.
    # (One image size throughout the test: each new size compiles the renderer again.)
    auto = viz.turntable(g, n_frames=3, size=24)
    assert auto.shape == (3, 24, 24, 3) and auto.dtype == np.uint8
    assert np.all(auto[:, 10:14, 10:14].mean(axis=(1, 2, 3)) < 230)
    assert np.all(auto[:, 0, 0] > 240)


def test_turntable_files(tmp_path):
    # Smooth frames like renders (lossy WebP subsamples chroma: random blocks would bleed).
    yy, xx = np.mgrid[0:24, 0:28] / 28.0
    frames = np.stack([np.stack([xx, yy, 0.5 + 0.4 * np.sin(xx * 3 + f)], -1) for f in range(5)])
    paths = viz.write_turntable(tmp_path / "t.webp", frames, fps=10, mp4=False)
    assert paths == [tmp_path / "t.webp"]
    back = viz.read_webp_frames(tmp_path / "t.webp")
    assert back.shape == (5, 24, 28, 3)
    assert np.abs(back.astype(float) - viz.to_uint8(frames)).mean() < 4  # lossy but faithful
    from PIL import Image

    with Image.open(tmp_path / "t.webp") as im:
        assert im.is_animated and im.info.get("loop") == 0  # loops forever
    assert viz.read_webp(tmp_path / "t.webp")[1].tolist() == [100] * 5  # 10 fps
    with pytest.raises(DataError, match="webp"):
        viz.write_turntable(tmp_path / "t.gif", frames)
    with pytest.raises(DataError, match="frames"):
        viz.write_turntable(tmp_path / "u.webp", frames[0])
    if viz.mp4_available():
        paths = viz.write_turntable(tmp_path / "m.webp", frames, fps=10, mp4=True)
        mp4 = (tmp_path / "m.mp4").read_bytes()
        assert paths[-1].suffix == ".mp4" and mp4[4:8] == b"ftyp" and len(mp4) > 500


def test_camera_path_round_trip_and_errors(tmp_path):
    import json

    cams = camlib.orbit(4, radius=3.0, elevation_deg=25.0, width=40, height=30, fov_deg=55.0)
    viz.save_camera_path(tmp_path / "path.json", cams, fps=8)
    back, fps = viz.load_camera_path(tmp_path / "path.json")
    assert fps == 8 and (back.width, back.height) == (40, 30)
    np.testing.assert_allclose(back.world_to_camera, cams.world_to_camera, atol=1e-5)
    np.testing.assert_allclose(back.fy, cams.fy, rtol=1e-5)
    data = json.loads((tmp_path / "path.json").read_text())
    # nerfstudio's convention: fov is the vertical one, pose the OpenGL camera-to-world.
    assert abs(data["camera_path"][0]["fov"] - np.degrees(2 * np.arctan(15 / float(cams.fy[0])))) < 1e-6
    c2w = np.asarray(data["camera_path"][0]["camera_to_world"]).reshape(4, 4)
    np.testing.assert_allclose(c2w[:3, 3], np.asarray(cams.center()[0]), atol=1e-5)
    for patch, needle in [({"camera_type": "fisheye"}, "perspective only"),
                          ({"camera_path": []}, "non-empty"),
                          ({"render_width": "wide"}, "integers")]:
        (tmp_path / "bad.json").write_text(json.dumps({**data, **patch}))
        with pytest.raises(DataError, match=needle):
            viz.load_camera_path(tmp_path / "bad.json")
    skewed = json.loads(json.dumps(data))
    skewed["camera_path"][1]["camera_to_world"][0] = 2.0
    (tmp_path / "bad.json").write_text(json.dumps(skewed))
    with pytest.raises(DataError, match=r"camera_path\[1\].*rigid"):
        viz.load_camera_path(tmp_path / "bad.json")
    with pytest.raises(DataError, match="cannot read"):
        viz.load_camera_path(tmp_path / "missing.json")
