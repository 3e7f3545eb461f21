"""process-data: structure from motion on rendered views recovers their poses.

The pose test renders the textured ``face`` scene with the ray caster at 256 x 256
(a size where SIFT finds ~1000 features per view), runs ``process-data`` on the
images alone and compares the recovered cameras with the true ones after a
Umeyama similarity. The video test encodes rendered orbit frames (some of them
blurred) as an H.264 file, checks that the blurred frames are the ones dropped,
and runs the video path end to end. Bad inputs go through the CLI: one line,
exit status 2, nothing written.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from experiments import cli
from jaxedit import DataError, camera as camlib, scenes
from jaxedit.capture import (APPLIED_TRANSFORM, blur_score, colmap_intrinsics, image_pairs,
                             pose_errors, transforms_meta, umeyama, windows)
from jaxedit.io import load_nerfstudio, transform_cameras, write_image

ROOT = Path(__file__).resolve().parents[1]
pycolmap = pytest.importorskip("pycolmap")
SIZE, VIEWS = 256, 32
FAST = ["--max-features", "1024", "--threads", "2"]


def _cli(*argv) -> subprocess.CompletedProcess:
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    return subprocess.run([sys.executable, "-m", "experiments", *map(str, argv)], cwd=ROOT,
                          capture_output=True, text=True, timeout=600, env=env)


def _main(capsys, *argv) -> subprocess.CompletedProcess:
    """:func:`experiments.cli.main` in-process (the same code path as ``_cli``, no start-up)."""
    capsys.readouterr()
    code = cli.main([str(a) for a in argv])
    captured = capsys.readouterr()
    return subprocess.CompletedProcess(argv, code, captured.out, captured.err)


def _one_line_error(proc, *needles) -> str:
    """Exit 2 and one error line, the last one (progress lines of finished stages may precede it)."""
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-800:])
    lines = proc.stderr.strip().splitlines()
    errors = [line for line in lines if line.startswith("error:")]
    assert errors == lines[-1:] and "Traceback" not in proc.stderr, proc.stderr[-800:]
    for needle in needles:
        assert needle in lines[-1], lines[-1]
    return lines[-1]


def _nothing_written(parent: Path, out: Path) -> None:
    assert not out.exists()
    assert not [p for p in parent.iterdir() if p.name.startswith(f".{out.name}.")]  # no staging


# ----------------------------------------------------------------- pure parts


def test_umeyama_recovers_a_similarity_and_pose_errors_are_zero_for_it():
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    sim = np.eye(4)
    sim[:3, :3], sim[:3, 3] = 2.5 * q, [1.0, -2.0, 0.5]
    src = rng.normal(size=(10, 3))
    np.testing.assert_allclose(umeyama(src, src @ sim[:3, :3].T + sim[:3, 3]), sim, atol=1e-9)
    cams = camlib.orbit(6, radius=3.0, elevation_deg=30.0, width=16, height=16)
    moved = transform_cameras(cams, np.linalg.inv(sim))  # "estimated" = a similar copy
    e = pose_errors(moved, cams)
    assert e["median_rotation_deg"] < 1e-2 and e["median_centre_error_rel"] < 1e-5
    with pytest.raises(DataError, match="N >= 3"):
        umeyama(src[:2], src[:2])


def test_relative_rotation_errors_are_the_differences_of_known_turns():
    """Each view turned by theta_k about the world z axis: the pair (i, j) is off by
    |theta_i - theta_j|, whatever frame the estimate is in (no alignment)."""
    from scipy.spatial.transform import Rotation

    from jaxedit.capture.align import relative_rotation_errors

    cams = camlib.orbit(6, radius=3.0, elevation_deg=30.0, width=16, height=16)
    theta = np.array([0.0, 1.0, 2.5, 3.0, 4.0, 7.0])
    w2c = np.array(cams.world_to_camera, np.float64)
    w2c[:, :3, :3] = w2c[:, :3, :3] @ Rotation.from_euler("z", theta[:, None], degrees=True).as_matrix()
    turned = dataclasses.replace(cams, world_to_camera=w2c.astype(np.float32))
    q, _ = np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))
    sim = np.eye(4)
    sim[:3, :3] = 2.0 * q * np.sign(np.linalg.det(q))
    moved = transform_cameras(turned, sim)  # another frame: the pairs' errors stay
    i, j = np.triu_indices(6, 1)
    np.testing.assert_allclose(relative_rotation_errors(moved, cams), np.abs(theta[i] - theta[j]),
                               atol=2e-3)
    assert pose_errors(moved, cams)["median_relative_rotation_deg"] == pytest.approx(
        np.median(np.abs(theta[i] - theta[j])), abs=2e-3)


def test_image_pairs_exhaustive_and_sequential_with_quadratic_overlap():
    assert len(image_pairs(6, "exhaustive")) == 15
    seq = image_pairs(40, "sequential", overlap=3)
    assert (0, 1) in seq and (0, 3) in seq and (0, 5) not in seq and (0, 6) not in seq
    assert (0, 4) in seq and (0, 8) in seq and (0, 32) in seq  # quadratic: 2^k frames ahead
    assert all(i < j < 40 for i, j in seq) and len(set(seq)) == len(seq)


def test_windows_split_frames_evenly_and_blur_lowers_the_score():
    np.testing.assert_array_equal(windows(10, 5), [0, 0, 1, 1, 2, 2, 3, 3, 4, 4])
    assert windows(3, 10).tolist() == [0, 1, 2]
    from skimage.filters import gaussian

    image = scenes.render_scene(scenes.get_scene("ball"), camlib.orbit(1, radius=3.5, width=48,
                                                                       height=48))[0]
    assert blur_score(gaussian(image, sigma=1.5, channel_axis=-1)) < 0.5 * blur_score(image)


def test_transforms_meta_follows_nerfstudio_and_the_loader_reads_it_back(tmp_path):
    cams = camlib.orbit(4, radius=3.0, elevation_deg=20.0, width=16, height=12)
    w2c = np.asarray(cams.world_to_camera, np.float64)
    intr = colmap_intrinsics("SIMPLE_RADIAL", [20.0, 8.0, 6.0, 0.01], 16, 12)
    assert intr["camera_model"] == "OPENCV" and intr["k1"] == 0.01 and intr["fl_y"] == 20.0
    assert colmap_intrinsics("SIMPLE_PINHOLE", [20.0, 8.0, 6.0], 16, 12)["camera_model"] == "PINHOLE"
    with pytest.raises(DataError, match="FISHEYE"):
        colmap_intrinsics("OPENCV_FISHEYE", [1, 1, 1, 1, 0, 0, 0, 0], 16, 12)
    names = [f"frame_{k:05d}.png" for k in range(1, 5)]
    meta = transforms_meta(names, w2c, [intr] * 4)
    assert meta["applied_transform"] == APPLIED_TRANSFORM.tolist() and meta["fl_x"] == 20.0
    for name in names:
        write_image(tmp_path / "images" / name, np.full((12, 16, 3), 0.5))
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    data = load_nerfstudio(tmp_path, split_every=0)
    applied = np.vstack([APPLIED_TRANSFORM, [0, 0, 0, 1]])
    expected = transform_cameras(cams, applied)  # COLMAP world rotated, same physical cameras
    np.testing.assert_allclose(data.cameras.world_to_camera, expected.world_to_camera, atol=1e-6)


# ----------------------------------------------------------------- structure from motion


@pytest.fixture(scope="module")
def face_views(tmp_path_factory):
    """(image folder, true cameras [VIEWS]) of the face scene at SIZE x SIZE."""
    scene = scenes.get_scene("face")
    cams = scenes.rig_cameras(scene.rig, VIEWS, width=SIZE)
    images = scenes.render_scene(scene, cams, supersample=1)
    folder = tmp_path_factory.mktemp("photos")
    for k, image in enumerate(images):
        write_image(folder / f"view_{k:03d}.png", image)
    return folder, cams


@pytest.mark.slow
def test_process_data_recovers_the_poses_of_rendered_views(face_views, tmp_path, capsys):
    folder, truth = face_views
    out = tmp_path / "data"
    proc = _main(capsys, "process-data", "--images", folder, "--out", out, *FAST, "--quiet")
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads(proc.stdout)
    data = load_nerfstudio(out, split_every=0)
    # frame_00001 is the first input in sorted order: view_000.
    index = np.array([int(Path(f).stem.split("_")[1]) - 1 for f in data.filenames])
    errors = pose_errors(data.cameras, truth[index])
    print(f"registered {len(index)}/{VIEWS}, median rotation {errors['median_rotation_deg']:.3f} "
          f"deg, median centre error {100 * errors['median_centre_error_rel']:.3f}% of the extent, "
          f"stages {summary['seconds']}")
    assert summary["num_registered"] == len(index) >= 0.9 * VIEWS
    assert errors["median_rotation_deg"] < 1.0
    assert errors["median_centre_error_rel"] < 0.01
    meta = json.loads((out / "transforms.json").read_text())
    assert meta["camera_model"] == "OPENCV" and meta["ply_file_path"] == "sparse_pc.ply"
    assert len(data.points) > 100 and (out / "colmap" / "database.db").is_file()
    for factor in (2, 4):
        half = load_nerfstudio(out, split_every=0, downscale=factor)
        assert (out / f"images_{factor}" / "frame_00001.png").is_file()
        assert half.images.shape[1:3] == (SIZE // factor, SIZE // factor)
    assert json.loads((out / "config.json").read_text())["command"] == "process-data"


def _write_video(path: Path, frames) -> None:
    import imageio_ffmpeg

    h, w = frames.shape[1:3]
    writer = imageio_ffmpeg.write_frames(str(path), (w, h), fps=10, quality=10,
                                         macro_block_size=16, output_params=["-g", "1"])
    writer.send(None)
    for frame in frames:
        writer.send(np.ascontiguousarray(np.round(255 * frame).astype(np.uint8)))
    writer.close()


@pytest.mark.slow
def test_video_frames_drop_the_blurriest_and_reconstruct(tmp_path, capsys):
    from skimage.filters import gaussian

    from jaxedit.capture import sample_video

    scene = scenes.get_scene("face")
    cams = camlib.orbit(48, radius=scene.rig.radius, elevation_deg=15.0, width=SIZE, height=SIZE,
                        fov_deg=scene.rig.fov_deg, start_deg=-60.0)[:24]  # a 180-degree arc
    frames = scenes.render_scene(scene, cams, supersample=1)
    blurred = np.arange(24) % 2 == 0  # every window of two holds one blurred frame
    frames[blurred] = gaussian(frames[blurred], sigma=(0, 2.0, 2.0, 0))
    video = tmp_path / "orbit.mp4"
    _write_video(video, frames)
    picked, index, scores = sample_video(video, 12)
    assert picked.shape == (12, SIZE, SIZE, 3) and not blurred[index].any()
    assert np.all(index // 2 == np.arange(12))
    out = tmp_path / "data"
    # One COLMAP thread: seeded RANSAC and mapping are then deterministic (several threads
    # registered these 12 frames differently from run to run).
    proc = _main(capsys, "process-data", "--video", video, "--num-frames", "12", "--out", out,
                 *FAST, "--threads", "1", "--quiet")
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads(proc.stdout)
    assert summary["matching"] == "sequential" and summary["video_frames"] == index.tolist()
    data = load_nerfstudio(out, split_every=0)
    sharp = cams[np.asarray(summary["video_frames"])]
    keep = np.array([int(Path(f).stem.split("_")[1]) - 1 for f in data.filenames])
    errors = pose_errors(data.cameras, sharp[keep])
    assert len(keep) >= 10 and errors["median_rotation_deg"] < 2.0


# ----------------------------------------------------------------- bad input, through the CLI


def test_bad_inputs_fail_with_one_line_and_write_nothing(tmp_path, capsys):
    photos = tmp_path / "photos"
    rng = np.random.default_rng(0)
    for k in range(2):
        write_image(photos / f"p{k}.png", rng.uniform(size=(32, 32, 3)))
    out = tmp_path / "data"
    _one_line_error(_cli("process-data", "--images", photos, "--out", out), "found 2 image(s)",
                    "at least 3")
    _nothing_written(tmp_path, out)
    write_image(photos / "p2.png", rng.uniform(size=(40, 32, 3)))
    _one_line_error(_main(capsys, "process-data", "--images", photos, "--out", out), "different sizes")
    (photos / "p2.png").write_bytes(b"not an image at all")
    _one_line_error(_main(capsys, "process-data", "--images", photos, "--out", out), "p2.png")
    _nothing_written(tmp_path, out)
    # Featureless views: SIFT finds nothing, so the mapper registers none.
    for k in range(4):
        write_image(photos / f"p{k}.png", np.full((48, 48, 3), 0.5))
    _one_line_error(_main(capsys, "process-data", "--images", photos, "--out", out, "--threads", "2"),
                    "registered 0 of 4 images")
    _nothing_written(tmp_path, out)
    (tmp_path / "clip.mp4").write_bytes(b"\x00" * 64)
    _one_line_error(_main(capsys, "process-data", "--video", tmp_path / "clip.mp4", "--out", out),
                    "clip.mp4", "cannot read video")
    _nothing_written(tmp_path, out)
    _one_line_error(_main(capsys, "process-data", "--images", tmp_path / "none", "--out", out),
                    "none", "does not exist")


# ----------------------------------------------------------------- known intrinsics


@pytest.fixture(scope="module")
def person_photos(tmp_path_factory):
    """12 plain photos of the person scene over its 160-degree arc: (folder, true cameras),
    and the same photos as JPEGs whose EXIF carries the 35 mm equivalent focal length."""
    root = tmp_path_factory.mktemp("person")
    paths, truth = scenes.photo_capture("person", root / "png", views=12)
    diagonal = float(np.hypot(truth.width, truth.height))
    f35 = int(round(float(np.asarray(truth.fx)[0]) * np.hypot(36.0, 24.0) / diagonal))
    scenes.photo_capture("person", root / "jpg", views=12, suffix=".jpg",
                         exif={"Exif:FocalLengthIn35mmFilm": f35})
    return root, truth


@pytest.mark.parametrize("how", ["focal-px", "camera-params", "exif"])
def test_known_intrinsics_are_held_and_photo_names_kept(person_photos, tmp_path, capsys, how):
    root, truth = person_photos
    f = float(np.asarray(truth.fx)[0])
    out = tmp_path / "data"
    flags = {"focal-px": ["--focal-px", f],
             "camera-params": ["--camera-params", f"{f},{f},128,128", "--camera-model", "PINHOLE"],
             "exif": []}[how]
    photos = root / ("jpg" if how == "exif" else "png")
    proc = _main(capsys, "process-data", "--images", photos, "--out", out, *FAST, *flags, "--quiet")
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads(proc.stdout)
    meta = json.loads((out / "transforms.json").read_text())
    if how == "exif":
        # COLMAP reads the 35 mm equivalent against the diagonal: the start is the truth up
        # to the tag's whole millimetres. Bundle adjustment then trades focal length against
        # k1 on 12 views of a small scene, and where it lands moves with COLMAP's thread
        # timing (0.4 % to 7 % low over repeated runs), so the refined value gets 10 %.
        assert summary["focal_source"] == "exif"
        assert abs(summary["focal_start_px"] / f - 1.0) < 0.01, summary["focal_start_px"]
        assert abs(meta["fl_x"] / f - 1.0) < 0.10, meta["fl_x"]
    else:
        assert summary["focal_source"] == "given" and summary["focal_start_px"] == f
        assert meta["fl_x"] == meta["fl_y"] == f and (meta["cx"], meta["cy"]) == (128.0, 128.0)
        assert meta.get("k1", 0.0) == 0.0
    # Every frame names its photo: frame_00001 is the first photo in sorted order.
    data = load_nerfstudio(out, split_every=0)
    assert summary["num_registered"] == len(data.filenames) >= 10
    for frame in meta["frames"]:
        k = int(Path(frame["file_path"]).stem.split("_")[1]) - 1
        assert frame["original_file_path"] == f"IMG_{k:04d}.{photos.name}"
    index = np.array([int(Path(f).stem.split("_")[1]) - 1 for f in data.filenames])
    assert pose_errors(data.cameras, truth[index])["median_relative_rotation_deg"] < 2.0


@pytest.mark.parametrize("flags, needle", [
    (["--focal-px", "0"], "--focal-px"), (["--focal-px", "-300"], "--focal-px"),
    (["--focal-px", "nan"], "--focal-px"), (["--focal-px", "inf"], "--focal-px"),
    (["--camera-params", "300,300,64"], "--camera-params"),
    (["--camera-params", "300,300,64,64,0,0,0"], "--camera-params"),
    (["--camera-params", "300,300,64,64,0,0,0,0,0"], "--camera-params"),
    (["--camera-params", "300,x,64,64"], "--camera-params"),
    (["--camera-params", "0,300,64,64"], "--camera-params"),
    (["--camera-params", "300,300,inf,64"], "--camera-params"),
    (["--camera-params", "300,310,64,64"], "--camera-params"),  # SIMPLE_RADIAL: one focal
    (["--camera-params", "300,300,64,64,0.1,0.2"], "--camera-params"),  # SIMPLE_RADIAL: no k2
    (["--refine-intrinsics"], "--refine-intrinsics"),
    (["--focal-px", "300", "--camera-params", "300,300,64,64"], "--camera-params"),
])
def test_bad_intrinsics_exit_2_naming_the_flag(tmp_path, capsys, flags, needle):
    photos = tmp_path / "photos"
    for k in range(3):
        write_image(photos / f"p{k}.png", np.full((32, 32, 3), 0.5))
    out = tmp_path / "data"
    capsys.readouterr()
    try:
        code = cli.main(["process-data", "--images", str(photos), "--out", str(out), *flags])
    except SystemExit as e:  # argparse's own errors (two exclusive flags)
        code = e.code
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and needle in err[0], err
    _nothing_written(tmp_path, out)
