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


# ---------------------------------------------------------------- the rendered person


@pytest.fixture(scope="module")
def person_full():
    return load_nerfstudio(scenes.dataset_path("person"))


@pytest.fixture(scope="module")
def person_small(tmp_path_factory):
    out = tmp_path_factory.mktemp("person") / "data"
    scenes.make_scene("person", out, downscale=2, views=6, test_views=2)
    return out


def _alpha(path):
    from jaxedit.io.images import read_image_with_alpha

    _, alpha = read_image_with_alpha(path)
    assert alpha is not None, f"{path} has no alpha channel"
    return alpha


def _on_silhouette(points, camera, alpha):
    """(in-frame mask, on-silhouette mask) of points projected through ``camera``: a point is on
    the silhouette when some pixel of the 3 x 3 block around it is mostly covered."""
    pix, depth = camera.project(np.asarray(points, np.float32))
    col, row = np.floor(np.asarray(pix)).astype(int).T
    h, w = alpha.shape
    inside = (np.asarray(depth) > 0) & (col >= 1) & (col < w - 1) & (row >= 1) & (row < h - 1)
    padded = np.pad(alpha, 1)
    covered = np.max([padded[i:i + h, j:j + w] for i in range(3) for j in range(3)], axis=0) > 0.5
    return inside, inside & covered[np.clip(row, 0, h - 1), np.clip(col, 0, w - 1)]


def test_person_is_a_rendered_dataset():
    assert "person" in scenes.list_scenes() and "person" in scenes.DATASETS
    with pytest.raises(DataError, match="rendered dataset"):
        scenes.get_scene("person")
    with pytest.raises(DataError, match="face, tabletop, fence, ball, person"):
        scenes.dataset_path("bear")


def test_person_mesh_vertices_land_on_the_silhouette(person_full):
    # The dataset's conventions (OpenGL camera-to-world, PINHOLE intrinsics, pixel centres at
    # +0.5, the world of the point cloud): vertices of the rendered mesh, projected through the
    # loaded cameras, land on the person's silhouette (the PNG's alpha) in every view.
    data, root = person_full, scenes.dataset_path("person")
    info = json.loads((root / scenes.SCENE_INFO).read_text())
    verts = np.asarray(info["mesh_vertices"])
    assert data.images.shape == (80, 256, 256, 3)
    assert len(data.train_indices) == 72 and len(data.test_indices) == 8
    assert set(data.test_indices) & set(data.train_indices) == set()
    hits, flipped_hits, seen = 0, 0, 0
    for v in range(0, 80, 9):
        alpha = _alpha(root / data.filenames[v])
        inside, on = _on_silhouette(verts, data.cameras[v], alpha)
        assert inside.sum() > 40, v  # head and shoulders fill the frame
        seen, hits = seen + inside.sum(), hits + on.sum()
        # The same test fails for a camera that is wrong by a vertical flip (OpenCV read as
        # OpenGL): the check has teeth.
        _, on_flipped = _on_silhouette(verts, data.cameras[v], alpha[::-1])
        flipped_hits += on_flipped.sum()
    assert hits == seen
    assert flipped_hits < 0.8 * seen
    # Above the head there is only backdrop, in every view.
    top = verts[np.argmax(verts[:, 2])] + np.array([0.0, 0.0, 0.06])
    for v in (0, 40, 79):
        inside, on = _on_silhouette(top[None], data.cameras[v], _alpha(root / data.filenames[v]))
        assert inside[0] and not on[0], v


def test_person_points_lie_on_the_visible_surface(person_full):
    data = person_full
    assert data.points.shape[0] >= 2000 and data.point_colors.shape == data.points.shape
    # Every point projects onto the silhouette of the training views that contain it.
    root = scenes.dataset_path("person")
    for v in data.train_indices[::24]:
        inside, on = _on_silhouette(data.points, data.cameras[v], _alpha(root / data.filenames[v]))
        assert inside.sum() > 500 and on[inside].mean() > 0.99
    # Colours come from the renders: skin, hair and suit, not a flat fill.
    assert data.point_colors.std(0).min() > 0.08


def test_person_copy_downscales_and_subsets(person_full, person_small):
    small = load_nerfstudio(person_small)
    assert small.images.shape == (8, 128, 128, 3)
    assert len(small.train_indices) == 6 and len(small.test_indices) == 2
    full = person_full
    for k, name in enumerate(small.filenames):
        j = full.filenames.index(name)
        np.testing.assert_allclose(np.asarray(small.cameras.world_to_camera[k]),
                                   np.asarray(full.cameras.world_to_camera[j]), atol=1e-6)
        assert float(small.cameras.fx[k]) == pytest.approx(float(full.cameras.fx[j]) / 2)
        assert float(small.cameras.cx[k]) == pytest.approx(float(full.cameras.cx[j]) / 2)
        # RGBA kept: compositing the downscaled copy = downscaling the composited original.
        a = full.images[j].reshape(128, 2, 128, 2, 3).mean(axis=(1, 3))
        assert np.abs(small.images[k] - a).max() < 3 / 255
        assert 0.0 < _alpha(person_small / name).mean() < 1.0
    # Held-out views of the copy are held-out views of the original (evenly spread).
    assert {small.filenames[i] for i in small.test_indices} <= \
        {full.filenames[i] for i in full.test_indices}
    np.testing.assert_array_equal(small.points, full.points)
    info = json.loads((person_small / scenes.SCENE_INFO).read_text())
    assert (info["size"], info["downscale"], info["views"]) == (128, 2, 6)
    credits = (person_small / "CREDITS.txt").read_text()
    assert "Reallusion" in credits and "Attribution 3.0" in credits
    assert "Creative Commons" in (person_small / "LICENSE-Reallusion.txt").read_text()
    # the renders' own licence note sits beside them, in the copy as in the package
    for root in (scenes.dataset_path("person"), person_small):
        note = (root / "images" / "LICENSE.txt").read_text()
        assert "CC BY 3.0 US" in note and "Reallusion" in note and "NOT under" in note


def test_cli_make_scene_person(tmp_path, capsys):
    from experiments.cli import main

    out = tmp_path / "person"
    assert main(["make-scene", "person", "--out", str(out), "--downscale", "4", "--views", "3",
                 "--test-views", "1"]) == 0
    data = load_nerfstudio(out)
    assert data.images.shape == (4, 64, 64, 3) and len(data.test_indices) == 1
    capsys.readouterr()
    for argv, flag in ((["person", "--size", "64"], "--size"),
                       (["person", "--views", "100"], "views"),
                       (["person", "--downscale", "0"], "downscale"),
                       (["face", "--downscale", "2"], "--downscale")):
        assert main(["make-scene", *argv, "--out", str(tmp_path / "bad")]) == 2, argv
        err = capsys.readouterr().err
        assert flag in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "bad" / "transforms.json").exists()


def test_demo_copies_the_person_at_its_size(tmp_path):
    from experiments import cli, demo

    assert cli.parse(["demo", "--out", str(tmp_path)]).scene_name == "person"

    assert demo._scene_size("person", 64) == {"--downscale": 4}
    assert demo._scene_size("face", 48) == {"--size": 48}
    with pytest.raises(DataError) as e:
        demo._scene_size("person", 100)
    assert e.value.where == "size"  # the library names the field; the CLI names the flag:
    assert str(cli.named_by_flag(e.value, cli.parse(["demo", "--out", str(tmp_path)]))
               ).startswith("--size: person is rendered at 256 px")
