"""Points for a posed dataset without any: features triangulated at the known poses (issue 74.3).

The oracle is the built-in face scene: its ray caster says where every pixel's surface is,
so triangulated points must lie on that surface, in the loaded cameras' world (normalised
or not), and not on its mirror image.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from experiments import cli
from jaxedit import DataError, scenes
from jaxedit import camera as camlib
from jaxedit.capture.triangulate import (MAX_ENLARGE, POINTS_FILE, TriangulateOptions,
                                         enlargement, feature_views, neighbor_pairs,
                                         triangulate, write_dataset_points)
from jaxedit.io import load_nerfstudio
from jaxedit.io.images import write_image
from jaxedit.pipelines.reconstruct import initial_points

pycolmap = pytest.importorskip("pycolmap")
SIZE, VIEWS = 128, 16
# One COLMAP thread: the same points every run; features at 256 px, quicker than the default.
FAST = TriangulateOptions(feature_side=256)


def _bare(folder: Path) -> Path:
    """``folder``'s dataset without its point cloud (as instant-ngp or Polycam write one)."""
    meta = json.loads((folder / "transforms.json").read_text())
    (folder / meta.pop("ply_file_path")).unlink()
    (folder / "transforms.json").write_text(json.dumps(meta, indent=2))
    return folder


@pytest.fixture(scope="module")
def face(tmp_path_factory):
    """A face-scene dataset of VIEWS + 2 views at SIZE px, without its points."""
    root = tmp_path_factory.mktemp("face")
    scenes.make_scene("face", root, size=SIZE, views=VIEWS, test_views=2, num_points=50)
    return _bare(root)


def _nearest(points: np.ndarray, surface: np.ndarray) -> np.ndarray:
    """Distance of each of ``points`` [P, 3] to its nearest of ``surface`` [S, 3]."""
    out = np.empty(len(points))
    for k in range(0, len(points), 64):
        d = np.linalg.norm(points[k:k + 64, None] - surface[None], axis=-1)
        out[k:k + 64] = d.min(axis=1)
    return out


def _surface(cameras) -> np.ndarray:
    """The face scene's surface seen by ``cameras``: every 3rd pixel's hit [S, 3]."""
    hits = scenes.surface_points_and_ids(scenes.get_scene("face"), cameras)[0]
    hits = hits[:, ::3, ::3].reshape(-1, 3)
    return hits[np.isfinite(hits).all(axis=1)].astype(np.float64)


def test_each_view_is_paired_with_its_nearest_cameras_and_all_when_few():
    cams = camlib.orbit(12, radius=3.0, width=16, height=16)
    pairs = neighbor_pairs(cams, 2)
    # On a circle of 12 evenly spaced cameras the 2 nearest are the two next to it.
    assert pairs == sorted({(min(i, (i + 1) % 12), max(i, (i + 1) % 12)) for i in range(12)})
    assert neighbor_pairs(cams, 11) == [(i, j) for i in range(12) for j in range(i + 1, 12)]


@pytest.mark.parametrize("normalize", ["none", "nerfstudio"])
def test_triangulated_points_lie_on_the_true_surface_in_the_loaded_world(face, normalize):
    data = load_nerfstudio(face, normalize=normalize)
    images, cameras = data.train()
    points, colors = triangulate(images, cameras, options=FAST)
    assert points.dtype == colors.dtype == np.float32
    assert points.shape == colors.shape and len(points) >= FAST.min_points
    assert ((colors >= 0) & (colors <= 1)).all()
    # The truth in the original world, carried into the loaded one by the loader's similarity.
    original = load_nerfstudio(face)
    truth = _surface(original.cameras[original.train_indices])
    truth = truth @ data.world_transform[:3, :3].T + data.world_transform[:3, 3]
    extent = np.linalg.norm(truth.max(0) - truth.min(0))
    dist = _nearest(points.astype(np.float64), truth) / extent
    assert np.median(dist) < 0.01 and np.percentile(dist, 90) < 0.03, np.percentile(dist, [50, 90])
    # The test can tell a mirrored or rescaled frame: those points are off the surface.
    centre = truth.mean(0)
    mirrored = (points - centre) * np.array([-1.0, 1.0, 1.0]) + centre
    scaled = (points - centre) * 1.2 + centre
    assert np.median(_nearest(mirrored, truth) / extent) > 0.03
    assert np.median(_nearest(scaled, truth) / extent) > 0.03


def test_small_views_are_enlarged_for_features_up_to_a_limit():
    assert enlargement(128, 96, 256) == 2 and enlargement(100, 60, 256) == 3
    assert enlargement(512, 300, 256) == 1 and enlargement(8, 8, 256) == MAX_ENLARGE


@pytest.mark.parametrize("normalize", ["none", "nerfstudio"])
def test_views_loaded_smaller_than_their_photos_are_read_again_for_features(face, normalize):
    full = load_nerfstudio(face, normalize=normalize)
    half = load_nerfstudio(face, downscale=2, normalize=normalize)
    images, cameras = feature_views(half, SIZE)
    # The photos' own pixels and the same frames, poses and world, intrinsics at their size.
    np.testing.assert_allclose(images, full.train()[0], atol=1e-6)
    np.testing.assert_allclose(np.asarray(cameras.world_to_camera),
                               np.asarray(half.train()[1].world_to_camera), atol=1e-6)
    np.testing.assert_allclose(np.asarray(cameras.fx), 2 * np.asarray(half.train()[1].fx))
    # Loaded at feature size already, or photos no larger than loaded: the views as loaded.
    for data, side in ((half, SIZE // 2), (full, 4 * SIZE)):
        images, cameras = feature_views(data, side)
        np.testing.assert_array_equal(images, data.train()[0])
        assert cameras.width == data.image_size[1]


def test_enlarged_views_give_more_points_on_the_same_surface(face):
    data = load_nerfstudio(face)
    images, cameras = data.train()
    plain = dataclasses.replace(FAST, feature_side=1, peak_threshold=1 / 150, min_points=1)
    few = triangulate(images, cameras, options=plain)[0]
    many = triangulate(images, cameras, options=FAST)[0]
    assert len(many) > 1.5 * len(few), (len(many), len(few))
    truth = _surface(cameras)
    extent = np.linalg.norm(truth.max(0) - truth.min(0))
    # Intrinsics scaled with the views: the points are as close to the surface as before.
    assert (np.median(_nearest(many.astype(np.float64), truth))
            <= 1.2 * np.median(_nearest(few.astype(np.float64), truth)) + 1e-4 * extent)


def test_reconstruct_init_auto_triangulates_a_bare_dataset_and_random_keeps_the_old_start(face):
    data = load_nerfstudio(face)
    tri = initial_points(data, 300, 0, init="triangulate", triangulation=FAST)
    assert tri[2] == "triangulated" and len(tri[0]) >= FAST.min_points
    # The training views' points, the same ones on every run (a multi-process run relies on it).
    again = triangulate(*data.train(), options=FAST)
    np.testing.assert_array_equal(tri[0], again[0])
    np.testing.assert_array_equal(tri[1], again[1])
    random = initial_points(data, 300, 0, init="random")
    assert random[2] == "random" and len(random[0]) == 300
    # auto: every triangulated point, then points on the surfaces they mark up to the random
    # start's count, nearer the surface than the random ones (both carved by the white
    # background, as reconstruct does)...
    n = len(tri[0]) + 300
    white = (1.0, 1.0, 1.0)
    auto = initial_points(data, n, 0, white, triangulation=FAST)
    assert auto[2] == "triangulated+dense" and len(auto[0]) == len(auto[1]) == n
    np.testing.assert_array_equal(auto[0][:len(tri[0])], tri[0])
    np.testing.assert_array_equal(auto[1][:len(tri[0])], tri[1])
    truth = _surface(data.train()[1])
    dense = _nearest(auto[0][len(tri[0]):].astype(np.float64), truth)
    far = _nearest(initial_points(data, 300, 0, white, init="random")[0].astype(np.float64),
                   truth)
    assert np.median(dense) < 0.25 * np.median(far), (np.median(dense), np.median(far))
    # ...and the triangulated points alone when they are as many.
    alone = initial_points(data, len(tri[0]), 0, triangulation=FAST)
    assert alone[2] == "triangulated"
    np.testing.assert_array_equal(alone[0], tri[0])
    with_points = data.__class__(**{**data.__dict__, "points": tri[0], "point_colors": tri[1]})
    kept = initial_points(with_points, 300, 0)
    assert kept[2] == "dataset"
    np.testing.assert_array_equal(kept[0], tri[0])
    assert initial_points(with_points, 300, 0, init="random")[2] == "random"


def _noise_dataset(folder: Path) -> Path:
    """A posed dataset of noise images: nothing matches between them."""
    rng = np.random.default_rng(0)
    cams = camlib.orbit(6, radius=3.0, width=48, height=48, fov_deg=50.0)
    frames = []
    for k in range(6):
        write_image(folder / "images" / f"f{k}.png", rng.uniform(size=(48, 48, 3)))
        c2w = camlib.opencv_w2c_to_opengl_c2w(np.asarray(cams.world_to_camera[k]))
        frames.append({"file_path": f"images/f{k}.png", "transform_matrix": c2w.tolist()})
    f = float(cams.fx[0])
    (folder / "transforms.json").write_text(json.dumps(
        {"camera_model": "PINHOLE", "fl_x": f, "fl_y": f, "cx": 24.0, "cy": 24.0, "w": 48,
         "h": 48, "frames": frames}))
    return folder


def test_too_few_points_is_a_data_error_and_auto_falls_back_to_random(tmp_path):
    data = load_nerfstudio(_noise_dataset(tmp_path))
    with pytest.raises(DataError, match="--init random"):
        triangulate(*data.train(), options=FAST, where=data.path)
    with pytest.raises(DataError, match="--init random"):
        initial_points(data, 50, 0, init="triangulate", triangulation=FAST)
    assert initial_points(data, 50, 0, triangulation=FAST)[2] == "random"


def _main(capsys, *argv) -> subprocess.CompletedProcess:
    capsys.readouterr()
    code = cli.main([str(a) for a in argv])
    captured = capsys.readouterr()
    return subprocess.CompletedProcess(argv, code, captured.out, captured.err)


def _one_line(proc, *needles) -> None:
    assert proc.returncode == 2, proc.stderr[-800:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), proc.stderr[-800:]
    for needle in needles:
        assert needle in lines[0], lines[0]


def test_process_data_triangulate_writes_the_points_the_loader_reads(face, tmp_path, capsys):
    import shutil

    folder = tmp_path / "data"
    shutil.copytree(face, folder)
    proc = _main(capsys, "process-data", "--triangulate", folder, "--triangulation.num-threads",
                 2, "--quiet")
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads(proc.stdout)
    data = load_nerfstudio(folder)
    assert json.loads((folder / "transforms.json").read_text())["ply_file_path"] == POINTS_FILE
    assert len(data.points) == summary["num_points"] >= FAST.min_points
    assert summary["num_views"] == VIEWS + 2
    # Triangulated from all views, they lie on the surface as the in-memory ones do.
    truth = _surface(data.cameras)
    extent = np.linalg.norm(truth.max(0) - truth.min(0))
    assert np.median(_nearest(data.points.astype(np.float64), truth)) < 0.01 * extent
    # Again: the dataset has points now, and nothing changes.
    before = (folder / "transforms.json").read_bytes()
    _one_line(_main(capsys, "process-data", "--triangulate", folder, "--quiet"),
              "already has points")
    assert (folder / "transforms.json").read_bytes() == before


def test_process_data_triangulate_bad_inputs_are_one_line_and_write_nothing(tmp_path, capsys):
    noise = _noise_dataset(tmp_path / "noise")
    before = (noise / "transforms.json").read_bytes()
    _one_line(_main(capsys, "process-data", "--triangulate", noise, "--quiet"),
              "transforms.json", "--init random")
    assert (noise / "transforms.json").read_bytes() == before
    assert not (noise / POINTS_FILE).exists()
    broken = _noise_dataset(tmp_path / "broken")
    (broken / "images" / "f2.png").write_bytes(b"not a png")
    _one_line(_main(capsys, "process-data", "--triangulate", broken, "--quiet"), "f2.png")
    (broken / "images" / "f3.png").unlink()
    _one_line(_main(capsys, "process-data", "--triangulate", broken, "--quiet"), "missing",
              "--skip-missing-images")
    (broken / "images" / "f2.png").unlink()
    _one_line(_main(capsys, "process-data", "--triangulate", broken, "--skip-missing-images",
                    "--quiet"), "--init random")  # past the missing photos, to the points
    assert not (broken / POINTS_FILE).exists()
    _one_line(_main(capsys, "process-data", "--images", broken / "images", "--out",
                    tmp_path / "o2", "--skip-missing-images", "--quiet"),
              "--skip-missing-images", "--triangulate")
    _one_line(_main(capsys, "process-data", "--triangulate", noise, "--out", tmp_path / "o",
                    "--quiet"), "--out")
    (noise / POINTS_FILE).write_bytes(b"mine")
    with pytest.raises(DataError, match="does not list it"):
        write_dataset_points(noise, np.zeros((4, 3)), np.zeros((4, 3)))
    assert (noise / POINTS_FILE).read_bytes() == b"mine"
    assert (noise / "transforms.json").read_bytes() == before
