"""Built-in scenes: ray-caster geometry, camera convention, datasets, determinism."""

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxedit import scenes
from jaxedit.camera import look_at, make_camera
from jaxedit.errors import DataError
from jaxedit.io.nerfstudio import load_nerfstudio
from jaxedit.scenes import raycast as rc

SMALL = dict(size=32, views=6, test_views=2, num_points=300)


@pytest.fixture(scope="module")
def face_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("face")
    scenes.make_scene("face", out / "a", seed=0, **SMALL)
    return out / "a"


# ---------------------------------------------------------------- geometry


def test_list_and_unknown_scene():
    names = scenes.list_scenes()
    assert {"face", "tabletop", "fence"} <= set(names)
    with pytest.raises(DataError, match="face, tabletop, fence"):
        scenes.get_scene("bear")


@settings(max_examples=30, deadline=None)
@given(ox=st.floats(-3, 3), oy=st.floats(-3, 3), tx=st.floats(-0.45, 0.45), ty=st.floats(-0.45, 0.45))
def test_sphere_hit_distance_is_analytic(ox, oy, tx, ty):
    sc = rc.Scene("s", (rc.sphere("ball", (0.0, 0.0, 0.0), 0.7),), (), rc.Rig(radius=3.0))
    origin = np.array([ox, oy, 4.0])
    d = np.array([tx, ty, 0.0]) - origin
    d /= np.linalg.norm(d)
    t, ids = rc.intersect(sc, origin, d[None])
    b = origin @ d
    disc = b * b - (origin @ origin - 0.49)
    assert ids[0] == 0 and disc >= 0
    assert t[0] == pytest.approx(-b - np.sqrt(disc), abs=1e-9)
    assert np.linalg.norm(origin + t[0] * d) == pytest.approx(0.7, abs=1e-9)


def test_box_and_plane_hits_and_rotation():
    box = rc.box("b", (0.0, 0.0, 0.0), (0.2, 0.5, 0.3))
    turned = rc.box("b", (0.0, 0.0, 0.0), (0.5, 0.2, 0.3), euler=(0, 0, 90))
    origin = np.array([3.0, 0.1, 0.05])
    d = np.array([[-1.0, 0.0, 0.0]])
    assert rc.intersect(rc.Scene("x", (box,), (), rc.Rig(3)), origin, d)[0][0] == pytest.approx(2.8)
    assert rc.intersect(rc.Scene("x", (turned,), (), rc.Rig(3)), origin, d)[0][0] == pytest.approx(2.8)
    # A miss beside the box, then a finite plane hit from above and a miss past its edge.
    assert rc.intersect(rc.Scene("x", (box,), (), rc.Rig(3)), np.array([3.0, 0.6, 0.0]), d)[1][0] == -1
    lawn = rc.plane("p", (0.0, 0.0, -1.0), (1.0, 2.0))
    down = np.array([[0.0, 0.0, -1.0]])
    t, ids = rc.intersect(rc.Scene("x", (lawn,), (), rc.Rig(3)), np.array([0.9, -1.9, 1.0]), down)
    assert ids[0] == 0 and t[0] == pytest.approx(2.0)
    assert rc.intersect(rc.Scene("x", (lawn,), (), rc.Rig(3)), np.array([1.1, 0.0, 1.0]), down)[1][0] == -1
    with pytest.raises(DataError, match="size"):
        rc.box("bad", (0, 0, 0), (0.1, -1.0, 0.1))
    with pytest.raises(DataError, match="kind"):
        rc.Shape("bad", "cone", (0, 0, 0), (1, 1, 1))
    with pytest.raises(DataError, match="scikit-image"):
        scenes.textures.pyramid(scenes.Texture("no_such_picture"))


def test_surface_points_project_to_their_pixels():
    # The shared camera convention: what the ray caster sees at pixel (i, j) projects back
    # to that pixel centre with jaxedit.camera.Camera.project, from every view.
    sc = scenes.get_scene("tabletop")
    cams, _, _ = scenes.scene_cameras(sc, views=3, test_views=0, size=24)
    pts, ids, uv = scenes.surface_points_and_ids(sc, cams)
    assert pts.shape == (3, 24, 24, 3) and ids.shape == (3, 24, 24) and uv.shape == (3, 24, 24, 2)
    assert np.isnan(pts[ids < 0]).all() and np.isfinite(pts[ids >= 0]).all()
    jj, ii = np.meshgrid(np.arange(24) + 0.5, np.arange(24) + 0.5)
    for v in range(3):
        hit = ids[v] >= 0
        pix, depth = cams[v].project(pts[v][hit])
        np.testing.assert_allclose(np.asarray(pix), np.stack([jj[hit], ii[hit]], -1), atol=2e-3)
        assert (np.asarray(depth) > 0).all()
    # A known point: the top of the red ball, seen from straight above, lands mid-image.
    ball = sc.shapes[sc.object_names.index("red_ball")]
    top = ball.c + np.array([0.0, 0.0, ball.s[2]])
    # Odd size: the centre of pixel (8, 8) is the principal point (8.5, 8.5).
    cam = make_camera(look_at(top + [0.0, 0.0, 2.0], top, up=(0.0, 1.0, 0.0)), width=17, height=17)
    p, i, _ = scenes.surface_points_and_ids(sc, cam)
    assert sc.object_names[i[8, 8]] == "red_ball"
    np.testing.assert_allclose(p[8, 8], top, atol=1e-6)


# ---------------------------------------------------------------- images


@pytest.mark.parametrize("name", ["face", "tabletop", "fence"])
def test_images_are_non_trivial(name):
    sc = scenes.get_scene(name)
    cams, _, _ = scenes.scene_cameras(sc, views=6, test_views=0, size=32)
    img = scenes.render_scene(sc, cams)
    _, ids, _ = scenes.surface_points_and_ids(sc, cams)
    assert img.shape == (6, 32, 32, 3) and img.dtype == np.float32
    assert img.min() >= 0.0 and img.max() <= 1.0
    for v in range(6):
        covered = ids[v] >= 0
        assert 0.1 < covered.mean() < 1.0  # object in view, background around it
        assert img[v].std() > 0.05
        # Textured, shaded surfaces: many distinct colours on the objects, not flat fills
        # (at 32 px the mip-mapped grass and bricks are nearly averaged out, hence only 10).
        assert np.unique((img[v][covered] * 32).astype(int), axis=0).shape[0] > 10
        # Background pixels are the background colour.
        far = ~covered
        assert np.allclose(img[v][far].mean(0), sc.background, atol=0.15)


def test_face_front_view_shows_the_face():
    sc = scenes.get_scene("face")
    cam = make_camera(look_at((3.6, 0.0, 0.3), (0.0, 0.0, 0.3)), width=32, height=32, fov_deg=40)
    _, ids, uv = scenes.surface_points_and_ids(sc, cam)
    assert sc.object_names[ids[16, 16]] == "head"
    # The decal coordinates put the face centre at (0.5, 0.5), u to the right, v down.
    assert abs(uv[16, 16, 0] - 0.5) < 0.05 and abs(uv[16, 16, 1] - 0.5) < 0.1
    assert uv[16, 20, 0] > uv[16, 12, 0] and uv[20, 16, 1] > uv[12, 16, 1]


def test_supersampling_converges():
    # Mip-mapped textures + 2x2 supersampling are already close to a 4x4 reference:
    # the targets are not aliased.
    sc = scenes.get_scene("fence")
    cams, _, _ = scenes.scene_cameras(sc, views=2, test_views=0, size=32)
    two = scenes.render_scene(sc, cams, supersample=2)
    four = scenes.render_scene(sc, cams, supersample=4)
    one = scenes.render_scene(sc, cams, supersample=1)
    err2 = np.abs(two - four).mean()
    assert err2 < 0.03 and err2 < np.abs(one - four).mean()
    rgba = scenes.render_scene(sc, cams[0], alpha=True)
    assert rgba.shape == (32, 32, 4) and 0.0 < rgba[..., 3].mean() < 1.0


# ---------------------------------------------------------------- datasets


def test_dataset_loads_and_matches_the_renders(face_dir):
    data = load_nerfstudio(face_dir)
    assert data.images.shape == (8, 32, 32, 3)
    assert len(data.train_indices) == 6 and len(data.test_indices) == 2
    sc = scenes.get_scene("face")
    cams, train, test = scenes.scene_cameras(sc, views=6, test_views=2, size=32)
    np.testing.assert_array_equal(data.train_indices, train)
    np.testing.assert_array_equal(data.test_indices, test)
    np.testing.assert_allclose(np.asarray(data.cameras.world_to_camera),
                               np.asarray(cams.world_to_camera), atol=1e-5)
    np.testing.assert_allclose(np.asarray(data.cameras.fx), np.asarray(cams.fx), rtol=1e-6)
    # PNG quantisation only.
    assert np.abs(data.images - scenes.render_scene(sc, cams)).max() <= 0.5 / 255 + 1e-6
    assert data.points.shape == (300, 3) and data.point_colors.shape == (300, 3)
    info = json.loads((face_dir / scenes.SCENE_INFO).read_text())
    assert info["scene"] == "face" and info["objects"][0] == "head"


def test_same_seed_gives_identical_files(face_dir, tmp_path):
    scenes.make_scene("face", tmp_path / "b", seed=0, **SMALL)
    files = sorted(p.relative_to(face_dir) for p in face_dir.rglob("*") if p.is_file())
    assert len(files) == 8 + 3
    for rel in files:
        assert (face_dir / rel).read_bytes() == (tmp_path / "b" / rel).read_bytes(), rel
    scenes.make_scene("face", tmp_path / "c", seed=1, **SMALL)
    # The face never changes with the seed, its point cloud does.
    assert (tmp_path / "c" / "images" / "frame_00000.png").read_bytes() == \
        (face_dir / "images" / "frame_00000.png").read_bytes()
    assert (tmp_path / "c" / "sparse_pc.ply").read_bytes() != (face_dir / "sparse_pc.ply").read_bytes()


def test_point_cloud_is_like_colmap():
    sc = scenes.get_scene("ball")
    cams, train, _ = scenes.scene_cameras(sc, views=12, test_views=0, size=32)
    pts, cols = scenes.sample_points(sc, cams, 1000, np.random.default_rng(0))
    assert pts.shape == (1000, 3) and pts.dtype == np.float32
    assert 0.0 <= cols.min() and cols.max() <= 1.0
    on_surface = np.abs(np.linalg.norm(pts, axis=-1) - 0.8) < 0.03
    # 5% outliers, uniform in the (margin-grown) bounding box: a few land near the sphere too.
    assert 0.93 < on_surface.mean() < 0.985
    # Surface colours agree with what the cameras see at their projections.
    img = scenes.render_scene(sc, cams, supersample=1)
    p, i, _ = scenes.surface_points_and_ids(sc, cams)
    errs = []
    for q, c in zip(pts[on_surface][:200], cols[on_surface][:200]):
        for v in range(12):
            pix, depth = cams[v].project(q[None])
            x, y = np.floor(np.asarray(pix[0])).astype(int)
            if 0 <= x < 32 and 0 <= y < 32 and np.linalg.norm(p[v, y, x] - q) < 0.05:
                errs.append(np.abs(img[v, y, x] - c).mean())
                break
    assert len(errs) > 150 and np.median(errs) < 0.12


def test_point_cloud_skips_hidden_surfaces():
    # Cameras look down on the table: its underside (a sixth of the area) gets no points;
    # only a few outliers fall in that thin layer.
    sc = scenes.get_scene("tabletop")
    cams, _, _ = scenes.scene_cameras(sc, views=8, test_views=0, size=32)
    pts, _ = scenes.sample_points(sc, cams, 600, np.random.default_rng(1))
    under = (np.abs(pts[:, 2] + 0.1) < 0.02) & (np.abs(pts[:, 0]) < 1.4) & (np.abs(pts[:, 1]) < 1.0)
    top = (np.abs(pts[:, 2]) < 0.02) & (np.abs(pts[:, 0]) < 1.4) & (np.abs(pts[:, 1]) < 1.0)
    assert under.mean() < 0.02 and top.mean() > 0.2


def test_tabletop_seed_moves_objects():
    a, b = scenes.get_scene("tabletop", 0), scenes.get_scene("tabletop", 3)
    assert a.shapes[0] == b.shapes[0]  # the table stays
    assert a.shapes[1].center != b.shapes[1].center
    assert scenes.get_scene("tabletop", 3) == b


def test_cli_make_scene(tmp_path, capsys):
    from experiments.cli import main

    assert main(["make-scene", "bogus", "--out", str(tmp_path / "x")]) == 2
    assert "face, tabletop, fence" in capsys.readouterr().err
    out = tmp_path / "ball"
    assert main(["make-scene", "ball", "--out", str(out), "--size", "16", "--views", "3",
                 "--test-views", "1", "--points", "50", "--preview"]) == 0
    data = load_nerfstudio(out)
    assert data.images.shape == (4, 16, 16, 3) and len(data.test_indices) == 1
    assert data.points.shape == (50, 3) and (out / "preview.png").is_file()
