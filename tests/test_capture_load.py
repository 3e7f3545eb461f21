"""Loading real captures: reduced-size JPEG decoding, the view cache, the default downscale,
the memory check, missing images, the crop of undistortion's blank pixels, EXIF orientation.

The oracle of the loader's pixels is the full-size path it replaced: decode at full size
(OpenImageIO), undistort at full size, area-average (``_reference_view``)."""

from __future__ import annotations

import dataclasses
import json
import logging
import os

import numpy as np
import pytest
from PIL import Image, ImageOps

from jaxedit import DataError
from jaxedit.io import load_nerfstudio, nerfstudio_view_size, undistort_points
from jaxedit.io import view_cache
from jaxedit.io.distortion import Distortion, source_inside, undistort_image, valid_rectangle
from jaxedit.io.images import area_average, orient, photo_header, read_image, read_photo
from jaxedit.io.nerfstudio import auto_downscale


def _psnr(a, b) -> float:
    return float(-10.0 * np.log10(np.mean((np.asarray(a, np.float64) - b) ** 2)))


def _photo(rng, h, w) -> np.ndarray:
    """float [h, w, 3]: smooth colour blobs, stripes and a few hard edges (JPEG-like content)."""
    from scipy import ndimage

    coarse = rng.random((h // 16 + 2, w // 16 + 2, 3))
    img = ndimage.zoom(coarse, (16, 16, 1), order=1)[:h, :w]
    yy, xx = np.mgrid[0:h, 0:w]
    img = img + 0.15 * (np.sin(xx / 5.0) * np.cos(yy / 9.0))[..., None]
    img[(xx // 37 + yy // 29) % 5 == 0] *= 0.5
    return np.clip(img, 0.0, 1.0)


def _save_jpeg(path, image, orientation=1):
    im = Image.fromarray(np.round(image * 255).astype(np.uint8))
    exif = Image.Exif()
    if orientation != 1:
        exif[0x0112] = orientation
    path.parent.mkdir(parents=True, exist_ok=True)
    im.save(path, quality=92, exif=exif)


def _dataset(folder, images, *, intrinsics=None, names=None, orientation=1, **extra):
    """A transforms.json with one shared camera and the given JPEGs (upright [h, w, 3] each)."""
    h, w = images[0].shape[:2]
    names = names or [f"images/frame_{k:05d}.jpg" for k in range(len(images))]
    frames = []
    for k, (name, image) in enumerate(zip(names, images)):
        stored = image if orientation == 1 else _unorient(image, orientation)
        _save_jpeg(folder / name, stored, orientation)
        c2w = np.eye(4)
        c2w[:3, 3] = [0.1 * k, 0.0, 3.0]
        frames.append({"file_path": name, "transform_matrix": c2w.tolist()})
    meta = {"camera_model": "OPENCV", "fl_x": 0.8 * w, "fl_y": 0.8 * w, "cx": w / 2,
            "cy": h / 2, "w": w, "h": h, **(intrinsics or {}), **extra, "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder


def _unorient(image, orientation):
    """The stored pixels whose EXIF ``orientation`` shows ``image`` upright (Pillow's inverse)."""
    for stored_k in range(4):
        for flip in (False, True):
            cand = np.rot90(image[:, ::-1] if flip else image, stored_k)
            if np.array_equal(orient(cand, orientation), image):
                return np.ascontiguousarray(cand)
    raise AssertionError(orientation)


def _reference_view(path, factor, fx, fy, cx, cy, dist, crop=None):
    """The full-size path: OpenImageIO decode, undistortion at full size, area average."""
    full = read_image(path)
    full = undistort_image(full, fx, fy, cx, cy, dist)
    view = area_average(full, factor)
    if crop is not None:
        x0, y0, x1, y1 = crop
        view = view[y0:y1, x0:x1]
    return view


# ---------------------------------------------------------------------------------------------
# decoding at the trained size


def test_jpeg_decoded_at_reduced_size_matches_full_decode_then_average(tmp_path):
    rng = np.random.default_rng(0)
    path = tmp_path / "p.jpg"
    _save_jpeg(path, _photo(rng, 360, 200))
    full = read_image(path)
    for factor in (1, 2, 3, 4, 8, 16):
        got = read_photo(path, factor)
        want = area_average(full, factor)
        assert got.shape == want.shape == (360 // factor, 200 // factor, 3)
        assert got.dtype == np.float32
        # DCT scaling is the block average up to the codec's rounding and chroma filter.
        assert _psnr(got, want) > (60.0 if factor in (1, 3) else 40.0), factor


def test_sizes_not_a_multiple_of_the_block(tmp_path):
    """A side that is not a multiple of 8: the decoder's partial last block is cropped."""
    rng = np.random.default_rng(1)
    path = tmp_path / "odd.jpg"
    _save_jpeg(path, _photo(rng, 101, 83))
    want = area_average(read_image(path), 8)
    got = read_photo(path, 8)
    assert got.shape == want.shape == (12, 10, 3)
    assert _psnr(got, want) > 40.0


def test_distorted_capture_loaded_small_matches_the_full_size_path(tmp_path):
    rng = np.random.default_rng(2)
    h, w = 240, 320
    dist = dict(k1=-0.08, k2=0.01, p1=0.001, p2=-0.0005)
    images = [_photo(rng, h, w) for _ in range(3)]
    d = _dataset(tmp_path / "d", images, intrinsics=dist)
    data = load_nerfstudio(d, downscale=4, split_every=0)
    assert data.pixels.dtype == np.uint8 and data.pixels.shape == (3, 60, 80, 3)
    fx = 0.8 * w
    for k in range(3):
        ref = _reference_view(d / data.filenames[k], 4, fx, fx, w / 2, h / 2, Distortion(**dist))
        # resampling at the small size against averaging the full-size resampling
        assert _psnr(data.images[k], ref) > 33.0


# ---------------------------------------------------------------------------------------------
# the view cache


def test_cache_is_read_back_and_rebuilt_when_a_photo_changes(tmp_path, monkeypatch):
    rng = np.random.default_rng(3)
    d = _dataset(tmp_path / "d", [_photo(rng, 64, 96) for _ in range(4)])
    load_nerfstudio(d)  # full size, no distortion: nothing to cache
    assert not (d / view_cache.FOLDER).exists()
    first = load_nerfstudio(d, downscale=2)
    entries = sorted((d / view_cache.FOLDER).glob("*.npy"))
    assert len(entries) == 4

    import jaxedit.io.nerfstudio as ns

    def no_decode(*a, **k):
        raise AssertionError("decoded a photo the cache holds")

    with monkeypatch.context() as m:
        m.setattr(ns, "read_photo", no_decode)
        second = load_nerfstudio(d, downscale=2)
    np.testing.assert_array_equal(second.pixels, first.pixels)
    # another factor is another entry; the first ones stay
    load_nerfstudio(d, downscale=4)
    assert len(list((d / view_cache.FOLDER).glob("*.npy"))) == 8

    # a changed photo misses, is decoded again, and its stale entry goes
    changed = d / first.filenames[1]
    _save_jpeg(changed, 1.0 - _photo(rng, 64, 96))
    os.utime(changed, ns=(1, 2_000_000_000_000_000_000))
    third = load_nerfstudio(d, downscale=2)
    np.testing.assert_array_equal(third.pixels[[0, 2, 3]], first.pixels[[0, 2, 3]])
    fresh = load_nerfstudio(d, downscale=2, cache=False)
    np.testing.assert_array_equal(third.pixels[1], fresh.pixels[1])
    assert np.abs(third.images[1] - first.images[1]).mean() > 0.1
    assert len(list((d / view_cache.FOLDER).glob("*.npy"))) == 8

    # a damaged entry is rebuilt, never returned
    for entry in (d / view_cache.FOLDER).glob("*.npy"):
        entry.write_bytes(entry.read_bytes()[:40])
    np.testing.assert_array_equal(load_nerfstudio(d, downscale=2).pixels, third.pixels)


def test_read_only_dataset_falls_back_to_the_home_cache_then_to_none(tmp_path, monkeypatch,
                                                                    caplog):
    rng = np.random.default_rng(4)
    d = _dataset(tmp_path / "d", [_photo(rng, 32, 48) for _ in range(3)])
    home = tmp_path / "home"
    monkeypatch.setenv("JAXEDIT_CACHE", str(home))
    writable = view_cache._writable
    # The tests run as root, for whom a read-only mode does not stop writes: refuse by path.
    monkeypatch.setattr(view_cache, "_writable",
                        lambda f: not str(f).startswith(str(d)) and writable(f))
    data = load_nerfstudio(d, downscale=2)
    assert not (d / view_cache.FOLDER).exists()
    assert len(list(home.glob("views/*/*.npy"))) == 3
    monkeypatch.setattr(view_cache, "_writable", lambda f: False)
    with caplog.at_level(logging.WARNING, logger="jaxedit.io"):
        again = load_nerfstudio(d, downscale=2)
    assert "loading without a cache" in caplog.text and len(caplog.records) == 1
    np.testing.assert_array_equal(again.pixels, data.pixels)


# ---------------------------------------------------------------------------------------------
# defaults and memory


def test_auto_downscale_is_nerfstudios_rule():
    assert auto_downscale(1080, 1920) == 2
    assert auto_downscale(3840, 2160) == 4
    assert auto_downscale(1600, 900) == 1 and auto_downscale(1601, 900) == 2
    assert auto_downscale(8000, 6000) == 8


def test_reconstruct_picks_the_default_downscale_and_refuses_what_cannot_fit(tmp_path,
                                                                            monkeypatch, caplog):
    from jaxedit.pipelines import reconstruct as R

    rng = np.random.default_rng(5)
    d = _dataset(tmp_path / "d", [_photo(rng, 40, 1700) for _ in range(3)])
    config = R.ReconstructConfig()
    assert config.downscale is None
    with caplog.at_level(logging.WARNING, logger="jaxedit.reconstruct"):
        data = R.load_dataset(d, config)
    assert data.image_size == (20, 850)
    assert "downscale 2" in caplog.text and "--downscale 1 keeps full size" in caplog.text
    full = R.load_dataset(d, R.ReconstructConfig(downscale=1))
    assert full.image_size == (40, 1700)
    import jaxedit.memory as mem

    monkeypatch.setattr(mem, "available_memory", lambda: 1 << 20)
    with pytest.raises(DataError, match="--downscale.*3 views of 850x20"):
        R.load_dataset(d, config)


def test_edit_refuses_what_cannot_fit_before_loading_the_editor_or_a_photo(tmp_path,
                                                                           monkeypatch):
    import jaxedit.memory as mem
    from jaxedit.io import nerfstudio as ns
    from jaxedit.pipelines.edit_run import EditorConfig, EditRunConfig, require_edit_memory

    rng = np.random.default_rng(5)
    d = _dataset(tmp_path / "d", [_photo(rng, 40, 1700) for _ in range(3)])
    weights = tmp_path / "weights" / "unet"
    weights.mkdir(parents=True)
    (weights / "diffusion_pytorch_model.safetensors").write_bytes(b"0" * 300_000)
    monkeypatch.setattr(ns, "read_photo", lambda *a, **k: pytest.fail("decoded a photo"))
    config = EditRunConfig(editor=EditorConfig(kind="ip2p", weights=tmp_path / "weights"))
    require_edit_memory(config, d, 5, editor_loaded=False)  # fits
    # The cap: --max-gaussians, else the default for the input scene's count.
    views = mem.working_set(3, 20, 850, 1, 10_005)
    monkeypatch.setattr(mem, "available_memory", lambda: views + 200_000)
    simulated = EditRunConfig(editor=EditorConfig(kind="simulated"))  # the lab's: no weights
    require_edit_memory(simulated, d, 5, editor_loaded=False)
    require_edit_memory(config, d, 5)  # the editor is loaded already: free memory says so
    with pytest.raises(DataError, match="--downscale.*3 views of 850x20.*10005 Gaussians "
                                        r"\(--max-gaussians\) and the editor's weights"):
        require_edit_memory(config, d, 5, editor_loaded=False)
    with pytest.raises(DataError, match="--downscale.*3 views of 850x20 and up to 400000"):
        require_edit_memory(dataclasses.replace(config, train=config.train.replace_densify(
            max_gaussians=400_000)), d, 5)


def test_edit_keeps_uint8_views_and_reads_the_same_floats(tmp_path):
    import jax
    from jaxedit import gaussians as G
    from jaxedit.io import save_ply
    from jaxedit.io.views import FloatViews, device_float, stored_views
    from jaxedit.pipelines.edit_run import EditRunConfig, load_inputs

    rng = np.random.default_rng(3)
    d = _dataset(tmp_path / "d", [_photo(rng, 24, 32) for _ in range(9)])
    scene = tmp_path / "scene.ply"
    save_ply(scene, G.from_points(rng.normal(size=(5, 3)), rng.uniform(size=(5, 3)), sh_degree=0))
    data, _ = load_inputs(EditRunConfig(), d, scene)
    full = load_nerfstudio(d)
    floats = full.images  # what edit held before: the float32 views
    train, test = full.train_indices, full.test_indices
    assert isinstance(data.train_images, FloatViews)
    assert stored_views(data.train_images).dtype == np.uint8
    assert data.train_images.shape == (len(train), 24, 32, 3) and len(data.test_images) == 2
    # Every way a consumer reads them gives the float32 views bit for bit.
    np.testing.assert_array_equal(np.asarray(data.train_images), floats[train])
    np.testing.assert_array_equal(data.train_images[3], floats[train[3]])
    np.testing.assert_array_equal(data.train_images[np.array([1, 4])], floats[train[[1, 4]]])
    np.testing.assert_array_equal(np.stack(list(data.test_images)), floats[test])
    np.testing.assert_array_equal(np.asarray(data.train_images, np.float32), floats[train])
    on_device = jax.device_put(stored_views(data.train_images))
    np.testing.assert_array_equal(np.asarray(device_float(on_device[2])), floats[train[2]])
    every = np.arange(256, dtype=np.uint8)
    np.testing.assert_array_equal(np.asarray(jax.jit(device_float)(every)),
                                  np.asarray(FloatViews(every)))


def test_edit_loads_a_large_capture_at_the_size_reconstruct_picks(tmp_path):
    from jaxedit import gaussians as G
    from jaxedit.io import save_ply
    from jaxedit.pipelines.edit_run import EditRunConfig, load_inputs

    rng = np.random.default_rng(7)
    d = _dataset(tmp_path / "d", [_photo(rng, 40, 1700) for _ in range(3)])
    scene = tmp_path / "scene.ply"
    save_ply(scene, G.from_points(rng.normal(size=(5, 3)), rng.uniform(size=(5, 3)), sh_degree=0))
    assert EditRunConfig().downscale is None
    data, _ = load_inputs(EditRunConfig(), d, scene)
    assert data.train_images.shape[1:3] == (20, 850)
    data, _ = load_inputs(EditRunConfig(downscale=1), d, scene)
    assert data.train_images.shape[1:3] == (40, 1700)


# ---------------------------------------------------------------------------------------------
# missing images


def test_missing_images_are_counted_and_can_be_skipped(tmp_path, caplog):
    rng = np.random.default_rng(6)
    names = [f"images/frame_{k:05d}.jpg" for k in range(6)]
    d = _dataset(tmp_path / "d", [_photo(rng, 24, 32) for _ in range(6)], names=names,
                 train_filenames=names[1:], test_filenames=names[:1] + names[3:4])
    (d / names[3]).unlink()
    (d / names[5]).unlink()
    with pytest.raises(DataError, match=r"2 of 6 frames' image files are missing .*frame_00003"
                                        r".*frame_00005.*--skip-missing-images"):
        load_nerfstudio(d)
    with caplog.at_level(logging.WARNING, logger="jaxedit.io"):
        data = load_nerfstudio(d, skip_missing=True)
    assert "dropping 2 of 6" in caplog.text and names[3] in caplog.text and names[5] in caplog.text
    assert data.filenames == [names[k] for k in (0, 1, 2, 4)] and len(data.pixels) == 4
    assert data.train_indices.tolist() == [1, 2, 3] and data.test_indices.tolist() == [0]
    (d / names[0]).unlink()
    (d / names[1]).unlink()
    (d / names[2]).unlink()
    (d / names[4]).unlink()
    with pytest.raises(DataError, match="all 6 frames' image files are missing"):
        load_nerfstudio(d, skip_missing=True)


@pytest.mark.parametrize("command", ["reconstruct", "edit", "process-data"])
def test_every_command_that_reads_photos_takes_skip_missing_images(command):
    from experiments import cli

    args = cli.command_parser(command).parse_args(
        ["--skip-missing-images", "--data" if command != "process-data" else "--triangulate",
         "d"] + (["--prompt", "p", "--scene", "s.ply"] if command == "edit" else []))
    assert args.skip_missing_images is True


def test_edit_and_triangulate_skip_missing_images_too(tmp_path, caplog):
    from jaxedit import gaussians as G
    from jaxedit.capture.triangulate import triangulate_dataset
    from jaxedit.io import save_ply
    from jaxedit.pipelines.edit_run import EditRunConfig, load_inputs

    rng = np.random.default_rng(8)
    d = _dataset(tmp_path / "d", [_photo(rng, 24, 32) for _ in range(5)])
    (d / "images/frame_00002.jpg").unlink()
    scene = tmp_path / "scene.ply"
    save_ply(scene, G.from_points(rng.normal(size=(5, 3)), rng.uniform(size=(5, 3)), sh_degree=0))
    with pytest.raises(DataError, match="1 of 5 .*--skip-missing-images"):
        load_inputs(EditRunConfig(), d, scene)
    with caplog.at_level(logging.WARNING, logger="jaxedit.io"):
        data, _ = load_inputs(EditRunConfig(skip_missing_images=True), d, scene)
    assert "frame_00002" in caplog.text
    assert len(data.train_images) + len(data.test_images) == 4
    pytest.importorskip("pycolmap")
    with pytest.raises(DataError, match="--skip-missing-images"):
        triangulate_dataset(d)
    with pytest.raises(DataError, match="--init random"):  # read 4 views, found no points
        triangulate_dataset(d, skip_missing=True)


def test_render_reads_a_datasets_cameras_without_its_photos(tmp_path, monkeypatch):
    from jaxedit.io import load_nerfstudio_cameras
    from jaxedit.io import nerfstudio as ns

    rng = np.random.default_rng(9)
    dist = {"k1": 0.2, "k2": 0.05}
    d = _dataset(tmp_path / "d", [_photo(rng, 48, 64) for _ in range(9)],
                 intrinsics=dict(fl_x=50.0, fl_y=52.0, cx=31.0, cy=25.0, **dist))
    for normalize in ("none", "nerfstudio"):
        full = load_nerfstudio(d, normalize=normalize, cache=False)
        cams, train, test = load_nerfstudio_cameras(d, normalize=normalize)
        assert (cams.width, cams.height) == (full.cameras.width, full.cameras.height)
        for k in ("world_to_camera", "fx", "fy", "cx", "cy"):
            np.testing.assert_array_equal(np.asarray(getattr(cams, k)),
                                          np.asarray(getattr(full.cameras, k)))
        assert train.tolist() == full.train_indices.tolist()
        assert test.tolist() == full.test_indices.tolist()
    # No photo is decoded, and a missing one does not matter.
    (d / "images/frame_00004.jpg").unlink()
    monkeypatch.setattr(ns, "read_photo", lambda *a, **k: pytest.fail("decoded a photo"))
    monkeypatch.setattr(ns, "photo_header", lambda *a, **k: pytest.fail("read a header"))
    assert len(load_nerfstudio_cameras(d)[0]) == 9


def test_bad_photos_are_one_line_errors(tmp_path):
    rng = np.random.default_rng(7)
    d = _dataset(tmp_path / "d", [_photo(rng, 48, 64) for _ in range(3)])
    photo = d / "images/frame_00001.jpg"
    whole = photo.read_bytes()
    photo.write_bytes(whole[:300])  # truncated inside the header
    with pytest.raises(DataError, match="frame_00001.jpg.*cannot open image"):
        load_nerfstudio(d, downscale=2)
    photo.write_bytes(whole[:len(whole) * 2 // 3])  # truncated inside the pixels
    with pytest.raises(DataError, match="frame_00001.jpg.*cannot decode image.*truncated"):
        load_nerfstudio(d, downscale=2)
    photo.write_bytes(b"\xff\xd8\xff not a jpeg")
    with pytest.raises(DataError, match="frame_00001.jpg.*cannot"):
        load_nerfstudio(d, downscale=2)
    _save_jpeg(photo, _photo(rng, 40, 64))  # another size than declared
    with pytest.raises(DataError, match="frame_00001.jpg.*image is 64x40 but frames"):
        load_nerfstudio(d)
    with pytest.raises(DataError, match="larger than the 64x48 images"):
        load_nerfstudio(d, downscale=65)


# ---------------------------------------------------------------------------------------------
# pixels undistortion leaves without a source


def _pattern(x, y):
    return np.stack([0.5 + 0.4 * np.sin(3 * x) * np.cos(2 * y), 0.5 + 0.3 * x * y,
                     0.5 + 0.4 * np.cos(4 * x + y)], -1)


def test_strong_pincushion_is_cropped_to_pixels_with_a_source(tmp_path):
    w, h, f, cx, cy = 160, 120, 90.0, 81.0, 58.0
    dist = Distortion(k1=0.35, k2=0.08)
    v, u = np.mgrid[0:h, 0:w] + 0.5
    und = undistort_points(np.stack([(u - cx) / f, (v - cy) / f], -1), dist)
    captured = _pattern(und[..., 0], und[..., 1])
    d = _dataset(tmp_path / "d", [captured] * 2, intrinsics=dict(
        fl_x=f, fl_y=f, cx=cx, cy=cy, k1=dist.k1, k2=dist.k2))
    inside = source_inside(h, w, f, f, cx, cy, dist)
    assert inside.mean() < 0.9  # a strong lens: over 10 % of the pinhole view has no source
    data = load_nerfstudio(d, split_every=0, background=(1.0, 0.0, 1.0))
    x0, y0, x1, y1 = valid_rectangle(inside)
    assert inside[y0:y1, x0:x1].all() and data.image_size == (y1 - y0, x1 - x0)
    assert data.image_size == nerfstudio_view_size(d)
    # a crop, not a sliver: 59 % of the image (the largest all-valid rectangle, by brute
    # force, is 0.3 % larger)
    assert (x1 - x0) * (y1 - y0) > 0.58 * w * h
    cam = data.cameras[0]
    assert float(cam.cx) == pytest.approx(cx - x0) and float(cam.cy) == pytest.approx(cy - y0)
    # every pixel shows the scene's pinhole view (no magenta fill), at the shifted centre
    vv, uu = np.mgrid[0:cam.height, 0:cam.width] + 0.5
    pinhole = _pattern((uu - float(cam.cx)) / f, (vv - float(cam.cy)) / f)
    assert np.abs(data.images[0] - pinhole).max() < 0.08
    assert _psnr(data.images[0], pinhole) > 35.0
    # at 1/2 the crop is found at the loaded size again
    half = load_nerfstudio(d, downscale=2, split_every=0)
    hx0, hy0, hx1, hy1 = valid_rectangle(source_inside(h // 2, w // 2, f / 2, f / 2, cx / 2,
                                                       cy / 2, dist))
    assert half.image_size == (hy1 - hy0, hx1 - hx0) == nerfstudio_view_size(d, downscale=2)


def test_valid_rectangle_holds_only_true_pixels():
    rng = np.random.default_rng(8)
    for _ in range(20):
        mask = np.ones((30, 40), bool)
        mask[rng.integers(0, 30, 6), rng.integers(0, 40, 6)] = False
        x0, y0, x1, y1 = valid_rectangle(mask)
        assert mask[y0:y1, x0:x1].all()
    assert valid_rectangle(np.ones((5, 7), bool)) == (0, 0, 7, 5)
    x0, y0, x1, y1 = valid_rectangle(np.zeros((5, 7), bool))
    assert x0 == x1 or y0 == y1


# ---------------------------------------------------------------------------------------------
# EXIF orientation


def test_orient_is_pillows_exif_transpose(tmp_path):
    rng = np.random.default_rng(9)
    stored = np.round(rng.random((5, 7, 3)) * 255).astype(np.uint8)
    for tag in range(1, 9):
        im = Image.fromarray(stored)
        exif = Image.Exif()
        exif[0x0112] = tag
        path = tmp_path / f"o{tag}.png"
        im.save(path, exif=exif)
        with Image.open(path) as saved:
            want = np.asarray(ImageOps.exif_transpose(saved))
        np.testing.assert_array_equal(orient(stored, tag), want)


@pytest.mark.parametrize("tag", [3, 6, 8])
def test_rotated_phone_photos_load_upright(tmp_path, tag):
    rng = np.random.default_rng(10 + tag)
    upright = [_photo(rng, 96, 64) for _ in range(2)]
    d = _dataset(tmp_path / "d", upright, orientation=tag)
    stored_h, stored_w, got_tag, eight = photo_header(d / "images/frame_00000.jpg")
    assert got_tag == tag and eight and (stored_h, stored_w) == ((64, 96) if tag != 3 else (96, 64))
    for factor in (1, 4):
        data = load_nerfstudio(d, downscale=factor, split_every=0)
        assert data.image_size == (96 // factor, 64 // factor)
        for k in range(2):
            assert _psnr(data.images[k], area_average(upright[k], factor)) > 30.0
    # a dataset posed on the stored pixels (COLMAP ignores the tag) is read as stored
    if tag != 3:
        meta = json.loads((d / "transforms.json").read_text())
        meta.update(w=96, h=64, cx=48, cy=32)
        (d / "transforms.json").write_text(json.dumps(meta))
        data = load_nerfstudio(d, split_every=0)
        assert data.image_size == (64, 96)
        assert _psnr(data.images[0], _unorient(upright[0], tag)) > 30.0


# ---------------------------------------------------------------------------------------------
# uint8 views in training


def test_uint8_views_give_the_float_batches():
    import jax

    from jaxedit import camera as camlib
    from jaxedit.train import select_batch

    rng = np.random.default_rng(11)
    pixels = rng.integers(0, 256, (3, 8, 12, 3), dtype=np.uint8)
    cams = camlib.orbit(3, radius=2.0, width=12, height=8)
    base = jax.random.key_data(jax.random.key(0))
    for step in range(4):
        a, _ = select_batch(pixels, cams, base, step)
        b, _ = select_batch(pixels.astype(np.float32) / 255.0, cams, base, step)
        assert a.image.dtype == np.float32
        np.testing.assert_allclose(np.asarray(a.image), np.asarray(b.image), rtol=0, atol=1e-7)


def test_process_data_gives_colmap_the_upright_photos(tmp_path, monkeypatch):
    """COLMAP reads stored pixels and ignores the tag: process-data writes rotated phone
    photos upright (PNG, lossless), so its poses, the loader and the editor see one image."""
    import jaxedit.capture.dataset as cd
    from jaxedit.capture.frames import check_images

    rng = np.random.default_rng(12)
    upright = [_photo(rng, 48, 32) for _ in range(3)]
    photos = []
    for k, image in enumerate(upright):
        photos.append(tmp_path / "photos" / f"IMG_{k}.jpg")
        tag = 6 if k else 1
        _save_jpeg(photos[-1], _unorient(image, tag), tag)
    assert check_images(photos, tmp_path / "photos") == (32, 48)
    seen = {}

    def fake_sfm(image_dir, names, *args, **kwargs):
        seen.update({n: read_image(image_dir / n) for n in names})
        raise DataError("structure from motion", "stopped by the test")

    monkeypatch.setattr(cd, "run_sfm", fake_sfm)
    with pytest.raises(DataError, match="stopped by the test"):
        cd.process_capture(tmp_path / "out", photos)
    assert sorted(seen) == ["frame_00001.jpg", "frame_00002.png", "frame_00003.png"]
    for image, got in zip(upright, (seen[n] for n in sorted(seen))):
        assert got.shape == (48, 32, 3) and _psnr(got, image) > 30.0
    assert not (tmp_path / "out").exists()


def test_the_reused_remap_is_bilinear_sample():
    """undistort_image's sparse remap (one per camera) against scipy's map_coordinates."""
    from jaxedit.io.distortion import _source_coords, bilinear_sample, undistortion_table

    rng = np.random.default_rng(13)
    image = rng.random((37, 53, 3)).astype(np.float32)
    fill = np.array([1.0, 0.0, 1.0])
    for d in (Distortion(k1=-0.2, k2=0.05, p1=0.003, p2=-0.002), Distortion(k1=0.4)):
        args = (37, 53, 30.0, 28.0, 25.0, 19.0, d)
        want = bilinear_sample(image, *_source_coords(*args), fill)
        table = undistortion_table(*args)
        got = undistort_image(image, *args[2:], fill=fill, table=table)
        np.testing.assert_allclose(got, want, atol=1e-6)
        np.testing.assert_array_equal(got, undistort_image(image, *args[2:], fill=fill))


def test_an_edit_of_uint8_views_is_bit_identical_to_one_of_their_floats():
    """A small edit from FloatViews of uint8 photos ends with the Gaussians, bit for bit, of
    the same edit from the float32 arrays edit held before."""
    import dataclasses as dc

    import jax
    from jaxedit import camera as cl
    from jaxedit import gaussians as gl
    from jaxedit.edit import EditData, ProEditConfig, EditTrainConfig
    from jaxedit.edit.outputs import Renderer
    from jaxedit.io.views import FloatViews
    from jaxedit.pipelines import run_edit
    from jaxedit_lab.simulated import SimulatedEditor

    rng = np.random.default_rng(0)
    d = rng.normal(size=(200, 3))  # test_progressive's tiny scene: its programs are cached
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    g = gl.from_points(d * 0.5, np.clip(0.5 + 0.4 * d[:, [2, 0, 1]], 0, 1), sh_degree=1,
                       init_opacity=0.8)
    g = dc.replace(g, log_scales=g.log_scales + 0.3)
    cams = cl.orbit(10, radius=2.5, width=32, height=32, elevation_deg=15)
    photos = np.stack([np.round(np.clip(Renderer().rgb(g, cams[i]), 0, 1) * 255).astype(np.uint8)
                       for i in range(10)])
    train, test = np.arange(8), np.arange(8, 10)
    # What edit held before: Dataset.images, uint8 times 1/255 in float32.
    floats = photos.astype(np.float32) * np.float32(1.0 / 255.0)
    np.testing.assert_array_equal(floats, np.asarray(FloatViews(photos)))
    cfg = ProEditConfig.for_mode("proedit", warmup=6, patience=8, loss_window=4, max_steps=24,
                                 edit_every=3, subtasks=1, consolidate=False, asynchronous=False,
                                 turntable_frames=0)
    runs = []
    for data in (EditData.create(floats[train], cams[train], floats[test], cams[test]),
                 EditData.create(FloatViews(photos[train]), cams[train],
                                 FloatViews(photos[test]), cams[test])):
        runs.append(run_edit(SimulatedEditor(), "turn him into a bronze statue", data, g, config=cfg,
                             settings=EditTrainConfig(lr_sh_dc=0.05), seed=3, run_dir=None))
    for x, y in zip(jax.tree_util.tree_leaves(runs[0]["gaussians"]),
                    jax.tree_util.tree_leaves(runs[1]["gaussians"])):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
