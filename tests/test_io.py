"""jaxedit.io: 3DGS / point-cloud PLY, images, nerfstudio datasets, undistortion."""

from __future__ import annotations

import dataclasses
import json
import struct

import jax
import jax.numpy as jnp
import numpy as np
import OpenImageIO as oiio
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from jaxedit import DataError
from jaxedit import camera as camlib
from jaxedit import gaussians as G
from jaxedit.camera import Camera
from jaxedit import sh as shlib
from jaxedit.io import (Distortion, distort_points, load_nerfstudio, load_ply, load_points_ply,
                        nerfstudio_view_size, read_image, rotate_sh, save_nerfstudio, save_ply,
                        save_points_ply, transform_cameras, transform_gaussians, transform_points,
                        undistort_points, write_image)

FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh")


# ---------------------------------------------------------------------------
# 3DGS PLY

def _random_gaussians(rng, n, degree, capacity):
    g = G.empty(capacity, degree)
    k = (degree + 1) ** 2
    return dataclasses.replace(
        g,
        means=jnp.asarray(rng.normal(size=(capacity, 3)).astype(np.float32)),
        log_scales=jnp.asarray(rng.normal(-3, 1, size=(capacity, 3)).astype(np.float32)),
        quats=jnp.asarray(rng.normal(size=(capacity, 4)).astype(np.float32)),
        opacity_logits=jnp.asarray(rng.normal(size=(capacity,)).astype(np.float32)),
        sh=jnp.asarray(rng.normal(size=(capacity, k, 3)).astype(np.float32)),
        alive=jnp.asarray(rng.permutation(capacity) < n),
    )


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_ply_round_trip_bit_exact_alive_only(tmp_path, degree):
    rng = np.random.default_rng(degree)
    g = _random_gaussians(rng, 7, degree, capacity=11)
    path = save_ply(tmp_path / "s.ply", g)
    back = load_ply(path)
    alive = np.asarray(g.alive)
    assert back.capacity == 7 and back.sh_degree == degree and bool(np.all(back.alive))
    for f in FIELDS:
        want = np.asarray(getattr(g, f))[alive]
        got = np.asarray(getattr(back, f))
        assert got.dtype == np.float32
        assert want.tobytes() == got.tobytes(), f  # bit-exact, slot order kept
    # The header is the INRIA one: normals present, fields in INRIA order.
    header = path.read_bytes().split(b"end_header\n")[0].decode()
    props = [ln.split()[-1] for ln in header.splitlines() if ln.startswith("property")]
    k = (degree + 1) ** 2
    assert props == (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                     + [f"f_rest_{i}" for i in range(3 * (k - 1))] + ["opacity"]
                     + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)])
    assert "format binary_little_endian 1.0" in header


finite32 = hnp.arrays(np.float32, (5, 3 + 3 + 4 + 1 + 16 * 3),
                      elements=st.floats(width=32, allow_nan=False, allow_infinity=False))


@settings(max_examples=25, deadline=None)
@given(values=finite32)
def test_ply_round_trip_any_float32_values(tmp_path_factory, values):
    """Extreme magnitudes, signed zeros and subnormals survive the round trip."""
    path = tmp_path_factory.mktemp("ply") / "h.ply"
    g = G.Gaussians(means=values[:, :3], log_scales=values[:, 3:6], quats=values[:, 6:10],
                    opacity_logits=values[:, 10], sh=values[:, 11:].reshape(5, 16, 3),
                    alive=np.ones(5, bool))
    save_ply(path, g)
    back = load_ply(path)
    for f in FIELDS:
        assert np.asarray(getattr(back, f)).tobytes() == np.ascontiguousarray(getattr(g, f)).tobytes()


def test_ply_empty_and_all_dead(tmp_path):
    g = G.empty(4, 2)
    back = load_ply(save_ply(tmp_path / "e.ply", g))
    assert back.capacity == 0 and back.sh_degree == 2


def _write_raw_ply(path, names, rows, extra_header=""):
    """A binary little-endian PLY written with struct only (independent of save_ply)."""
    header = "ply\nformat binary_little_endian 1.0\n" + extra_header
    header += f"element vertex {len(rows)}\n"
    header += "".join(f"property float {n}\n" for n in names) + "end_header\n"
    body = b"".join(struct.pack("<" + "f" * len(names), *row) for row in rows)
    path.write_bytes(header.encode() + body)


def _expected(rng, n, degree):
    k = (degree + 1) ** 2
    return dict(means=rng.normal(size=(n, 3)), log_scales=rng.normal(size=(n, 3)),
                quats=rng.normal(size=(n, 4)), opacity=rng.normal(size=n),
                sh=rng.normal(size=(n, k, 3)))


def _row_values(e, i, names):
    k = e["sh"].shape[1]
    v = {"x": e["means"][i, 0], "y": e["means"][i, 1], "z": e["means"][i, 2],
         "nx": 0.0, "ny": 0.0, "nz": 0.0, "opacity": e["opacity"][i]}
    for c in range(3):
        v[f"f_dc_{c}"] = e["sh"][i, 0, c]
        v[f"scale_{c}"] = e["log_scales"][i, c]
        for j in range(k - 1):  # channel-major: all of R's rest, then G's, then B's
            v[f"f_rest_{c * (k - 1) + j}"] = e["sh"][i, 1 + j, c]
    for c in range(4):
        v[f"rot_{c}"] = e["quats"][i, c]
    return [v[n] for n in names]


def _check_loaded(g, e):
    np.testing.assert_array_equal(np.asarray(g.means), e["means"].astype(np.float32))
    np.testing.assert_array_equal(np.asarray(g.log_scales), e["log_scales"].astype(np.float32))
    np.testing.assert_array_equal(np.asarray(g.quats), e["quats"].astype(np.float32))
    np.testing.assert_array_equal(np.asarray(g.opacity_logits), e["opacity"].astype(np.float32))
    np.testing.assert_array_equal(np.asarray(g.sh), e["sh"].astype(np.float32))


def test_reads_inria_layout_with_zero_normals(tmp_path):
    rng = np.random.default_rng(1)
    e = _expected(rng, 6, 3)
    names = (["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{i}" for i in range(3)]
             + [f"f_rest_{i}" for i in range(45)] + ["opacity"]
             + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)])
    path = tmp_path / "inria.ply"
    _write_raw_ply(path, names, [_row_values(e, i, names) for i in range(6)])
    g = load_ply(path)
    assert g.sh_degree == 3
    _check_loaded(g, e)


def test_reads_gsplat_layout_without_normals_other_order(tmp_path):
    rng = np.random.default_rng(2)
    e = _expected(rng, 5, 1)
    names = (["x", "y", "z"] + [f"rot_{i}" for i in range(4)] + [f"scale_{i}" for i in range(3)]
             + ["opacity"] + [f"f_rest_{i}" for i in range(9)][::-1] + [f"f_dc_{i}" for i in range(3)])
    path = tmp_path / "gsplat.ply"
    _write_raw_ply(path, names, [_row_values(e, i, names) for i in range(5)],
                   extra_header="comment made by a test\n")
    g = load_ply(path)
    assert g.sh_degree == 1 and g.capacity == 5
    _check_loaded(g, e)


def test_reads_ply_with_other_elements_before_and_after_vertex(tmp_path):
    rng = np.random.default_rng(3)
    e = _expected(rng, 2, 0)
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
             "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    header = ("ply\nformat binary_little_endian 1.0\nelement meta 1\nproperty list uchar int ids\n"
              "property double v\nelement vertex 2\n"
              + "".join(f"property float {n}\n" for n in names)
              + "element face 1\nproperty list uchar int vertex_indices\nend_header\n")
    body = struct.pack("<B3id", 3, 1, 2, 3, 0.5)
    body += b"".join(struct.pack("<" + "f" * len(names), *_row_values(e, i, names)) for i in range(2))
    body += struct.pack("<B3i", 3, 0, 1, 0)
    (tmp_path / "x.ply").write_bytes(header.encode() + body)
    _check_loaded(load_ply(tmp_path / "x.ply"), e)


# ---------------------------------------------------------------------------
# point-cloud PLY

def test_points_ply_round_trip(tmp_path):
    rng = np.random.default_rng(4)
    pts = rng.normal(size=(30, 3)).astype(np.float32)
    cols = rng.uniform(size=(30, 3))
    p, c = load_points_ply(save_points_ply(tmp_path / "p.ply", pts, cols))
    np.testing.assert_array_equal(p, pts)
    np.testing.assert_allclose(c, np.round(cols * 255) / 255, atol=1e-7)


def test_points_ply_ascii_colmap_style_with_normals(tmp_path):
    text = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            "property float z\nproperty float nx\nproperty float ny\nproperty float nz\n"
            "property uint8 red\nproperty uint8 green\nproperty uint8 blue\nend_header\n"
            "1 2 3 0 0 1 255 0 0\n-1.5 0.25 4e-1 0 1 0 0 128 255\n0 0 0 1 0 0 10 20 30\n")
    (tmp_path / "a.ply").write_text(text)
    p, c = load_points_ply(tmp_path / "a.ply")
    np.testing.assert_allclose(p, [[1, 2, 3], [-1.5, 0.25, 0.4], [0, 0, 0]], rtol=1e-6)
    np.testing.assert_allclose(c, np.array([[255, 0, 0], [0, 128, 255], [10, 20, 30]]) / 255, atol=1e-7)


def test_points_from_a_3dgs_file_use_dc_colour(tmp_path):
    rng = np.random.default_rng(6)
    g = _random_gaussians(rng, 4, 2, capacity=4)
    g = dataclasses.replace(g, sh=g.sh.at[:, 0].set(shlib.rgb_to_dc(jnp.asarray(rng.uniform(size=(4, 3)),
                                                                              jnp.float32))))
    p, c = load_points_ply(save_ply(tmp_path / "g.ply", g))
    np.testing.assert_array_equal(p, np.asarray(g.means))
    np.testing.assert_allclose(c, np.asarray(shlib.dc_to_rgb(g.sh[:, 0])), atol=1e-6)


def test_points_ply_double_coords_no_colour_big_endian(tmp_path):
    header = ("ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty double x\n"
              "property double y\nproperty double z\nend_header\n")
    body = struct.pack(">6d", 1, 2, 3, 4, 5, 6)
    (tmp_path / "b.ply").write_bytes(header.encode() + body)
    p, c = load_points_ply(tmp_path / "b.ply")
    np.testing.assert_array_equal(p, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(c, np.full((2, 3), 0.5, np.float32))


# ---------------------------------------------------------------------------
# images

def _smooth_image(h=24, w=32):
    y, x = np.mgrid[0:h, 0:w] / max(h, w)
    return np.stack([x, y, 0.5 + 0.4 * np.sin(6 * x) * np.cos(4 * y)], -1).astype(np.float32)


@pytest.mark.parametrize("suffix,tol", [(".png", 0.5 / 255 + 1e-6), (".tif", 0.5 / 65535 + 1e-6),
                                        (".exr", 0.0), (".jpg", 0.08)])
def test_image_round_trip(tmp_path, suffix, tol):
    img = _smooth_image()
    back = read_image(write_image(tmp_path / f"i{suffix}", img))
    assert back.shape == img.shape and back.dtype == np.float32
    assert np.abs(back - img).max() <= tol
    if suffix == ".jpg":  # lossy (chroma subsampling at edges) but close on average
        assert np.abs(back - img).mean() < 0.01


@pytest.mark.parametrize("suffix", [".png", ".exr"])
def test_write_strided_and_fortran_ordered_images(tmp_path, suffix):
    img = _smooth_image(16, 16)
    views = [img.transpose(1, 0, 2), np.asfortranarray(img), img[:, ::2], img[..., ::-1]]
    for i, view in enumerate(views):
        back = read_image(write_image(tmp_path / f"v{i}{suffix}", view))
        np.testing.assert_allclose(back, view, atol=0.5 / 255 + 1e-6)


def test_rgba_composited_over_background(tmp_path):
    rng = np.random.default_rng(5)
    rgb = (rng.integers(0, 256, (6, 5, 3)) / 255).astype(np.float32)
    alpha = (rng.integers(0, 256, (6, 5, 1)) / 255).astype(np.float32)
    for suffix in (".png", ".exr"):
        path = write_image(tmp_path / f"a{suffix}", np.concatenate([rgb, alpha], -1))
        for bg in [(1.0, 1.0, 1.0), (0.0, 0.25, 1.0)]:
            want = rgb * alpha + (1 - alpha) * np.asarray(bg, np.float32)
            np.testing.assert_allclose(read_image(path, background=bg), want, atol=1e-6)


def test_read_image_with_alpha_returns_straight_colour(tmp_path):
    from jaxedit.io.images import read_image_with_alpha

    rng = np.random.default_rng(11)
    rgb = (rng.integers(0, 256, (5, 4, 3)) / 255).astype(np.float32)
    alpha = (rng.integers(1, 256, (5, 4, 1)) / 255).astype(np.float32)
    for suffix, tol in ((".png", 1e-6), (".exr", 1e-5)):
        path = write_image(tmp_path / f"a{suffix}", np.concatenate([rgb, alpha], -1))
        colour, a = read_image_with_alpha(path)
        np.testing.assert_allclose(a, alpha[..., 0], atol=1e-6)
        np.testing.assert_allclose(colour, rgb, atol=tol)
    colour, a = read_image_with_alpha(write_image(tmp_path / "o.png", rgb))
    assert a is None
    np.testing.assert_allclose(colour, rgb, atol=1e-6)


def test_grey_and_16_bit_png_read_with_oiio_writer(tmp_path):
    grey = (np.arange(12, dtype=np.uint16).reshape(3, 4) * 5000)
    out = oiio.ImageOutput.create(str(tmp_path / "g.png"))
    out.open(str(tmp_path / "g.png"), oiio.ImageSpec(4, 3, 1, oiio.UINT16))
    assert out.write_image(grey[:, :, None])
    out.close()
    img = read_image(tmp_path / "g.png")
    assert img.shape == (3, 4, 3)
    np.testing.assert_allclose(img, np.repeat(grey[..., None] / 65535.0, 3, -1), atol=1e-6)


# ---------------------------------------------------------------------------
# nerfstudio

def _write_dataset(root, frames, images, **top):
    """A transforms.json written by hand (independent of save_nerfstudio)."""
    root.mkdir(parents=True, exist_ok=True)
    for fp, img in images.items():
        write_image(root / fp, img)
    meta = dict(top, frames=frames)
    (root / "transforms.json").write_text(json.dumps(meta))
    return root / "transforms.json"


def test_opengl_pose_converted_to_opencv_projection(tmp_path):
    """Camera at (0, 0, 5), OpenGL identity rotation: looks down -z at the origin, y up."""
    c2w = np.eye(4)
    c2w[:3, 3] = [0.0, 0.0, 5.0]
    w, h, f = 40, 30, 50.0
    path = _write_dataset(tmp_path / "d", [{"file_path": "im.png", "transform_matrix": c2w.tolist()}],
                          {"im.png": np.zeros((h, w, 3))}, fl_x=f, fl_y=f, cx=20.0, cy=15.0, w=w, h=h,
                          camera_model="PINHOLE")
    ds = load_nerfstudio(path, split_every=0)
    cam = ds.cameras[0]
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    uv, z = cam.project(jnp.asarray(pts))
    np.testing.assert_allclose(np.asarray(z), [5, 5, 5], atol=1e-5)
    # +x world is image right, +y world (up) is image up, i.e. smaller v.
    np.testing.assert_allclose(np.asarray(uv), [[20, 15], [20 + f / 5, 15], [20, 15 - f / 5]], atol=1e-4)


def test_rotated_pose_point_lands_on_expected_pixel(tmp_path):
    """A camera built by look_at (OpenCV), written as OpenGL c2w, projects a known point."""
    eye, target = np.array([3.0, -2.0, 1.5]), np.array([0.2, 0.1, -0.3])
    w2c = camlib.look_at(eye, target)
    c2w_gl = camlib.opencv_w2c_to_opengl_c2w(w2c)
    # An independent check of the OpenGL convention: column 2 points backwards.
    fwd = (target - eye) / np.linalg.norm(target - eye)
    np.testing.assert_allclose(c2w_gl[:3, 2], -fwd, atol=1e-12)
    path = _write_dataset(tmp_path / "d", [{"file_path": "im.png", "transform_matrix": c2w_gl.tolist(),
                                            "fl_x": 30.0, "fl_y": 32.0, "cx": 17.0, "cy": 11.0}],
                          {"im.png": np.zeros((20, 36, 3))}, w=36, h=20)
    cam = load_nerfstudio(path, split_every=0).cameras[0]
    uv, z = cam.project(jnp.asarray(target[None].astype(np.float32)))
    np.testing.assert_allclose(np.asarray(uv)[0], [17.0, 11.0], atol=1e-4)  # target -> principal point
    assert float(z[0]) == pytest.approx(np.linalg.norm(target - eye), rel=1e-5)


def _scene(n=10, w=16, h=12, seed=0):
    rng = np.random.default_rng(seed)
    cams = camlib.hemisphere(n, radius=4.0, target=(1.0, -2.0, 0.5), width=w, height=h, fov_deg=50)
    imgs = (rng.integers(0, 256, (n, h, w, 3)) / 255).astype(np.float32)
    return cams, imgs, rng


def test_save_load_round_trip(tmp_path):
    cams, imgs, rng = _scene()
    pts, cols = rng.normal(size=(25, 3)), rng.uniform(size=(25, 3))
    path = save_nerfstudio(tmp_path / "ds", imgs, cams, points=pts, point_colors=cols,
                           test_indices=[2, 5])
    meta = json.loads(path.read_text())
    assert meta["camera_model"] == "PINHOLE" and "fl_x" in meta and "fl_x" not in meta["frames"][0]
    assert meta["ply_file_path"] == "sparse_pc.ply" and meta["val_filenames"] == meta["test_filenames"]
    ds = load_nerfstudio(tmp_path / "ds")  # folder or json both work
    np.testing.assert_allclose(ds.images, imgs, atol=1e-6)
    np.testing.assert_allclose(np.asarray(ds.cameras.world_to_camera),
                               np.asarray(cams.world_to_camera), atol=1e-6)
    for k in ("fx", "fy", "cx", "cy"):
        np.testing.assert_allclose(np.asarray(getattr(ds.cameras, k)), np.asarray(getattr(cams, k)))
    assert ds.test_indices.tolist() == [2, 5] and len(ds.train_indices) == 8
    np.testing.assert_allclose(ds.points, pts, atol=1e-6)
    np.testing.assert_allclose(ds.point_colors, np.round(cols * 255) / 255, atol=1e-7)
    tr_imgs, tr_cams = ds.train()
    assert tr_imgs.shape == (8, 12, 16, 3) and len(tr_cams) == 8
    # Exact float images through EXR, per-frame intrinsics when cameras differ.
    cams2 = dataclasses.replace(cams, fx=np.asarray(cams.fx) * np.linspace(1, 1.2, 10).astype(np.float32))
    fimgs = rng.uniform(size=imgs.shape).astype(np.float32)
    path = save_nerfstudio(tmp_path / "ds2", fimgs, cams2, image_format="exr")
    assert "fl_x" in json.loads(path.read_text())["frames"][3]
    ds2 = load_nerfstudio(path)
    assert ds2.images.tobytes() == fimgs.tobytes()
    np.testing.assert_allclose(np.asarray(ds2.cameras.fx), np.asarray(cams2.fx))


def test_save_into_existing_folder_replaces_files(tmp_path):
    cams, imgs, _ = _scene(n=3)
    save_nerfstudio(tmp_path / "ds", imgs, cams)
    save_nerfstudio(tmp_path / "ds", 1 - imgs, cams)
    np.testing.assert_allclose(load_nerfstudio(tmp_path / "ds").images, 1 - imgs, atol=1e-6)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no staging left


def test_split_rules(tmp_path):
    cams, imgs, _ = _scene(n=17)
    save_nerfstudio(tmp_path / "ds", imgs, cams)
    ds = load_nerfstudio(tmp_path / "ds")
    assert ds.test_indices.tolist() == [0, 8, 16]
    assert ds.train_indices.tolist() == [i for i in range(17) if i % 8]
    assert load_nerfstudio(tmp_path / "ds", split_every=5).test_indices.tolist() == [0, 5, 10, 15]
    assert len(load_nerfstudio(tmp_path / "ds", split_every=0).test_indices) == 0
    # Explicit lists: val_filenames used when test_filenames is absent; frames sorted by name.
    meta = json.loads((tmp_path / "ds/transforms.json").read_text())
    meta["frames"] = meta["frames"][::-1]
    meta["train_filenames"] = [f"images/frame_{i:05d}.png" for i in (1, 3, 4)]
    meta["val_filenames"] = ["./images/frame_00002.png", "images/frame_00009.png"]
    (tmp_path / "ds/transforms.json").write_text(json.dumps(meta))
    ds = load_nerfstudio(tmp_path / "ds")
    assert ds.filenames == sorted(ds.filenames)
    assert ds.train_indices.tolist() == [1, 3, 4] and ds.test_indices.tolist() == [2, 9]
    np.testing.assert_allclose(ds.images[9], imgs[9], atol=1e-6)


def test_downscale_area_average_and_intrinsics(tmp_path):
    cams, imgs, _ = _scene(n=2, w=17, h=12)
    save_nerfstudio(tmp_path / "ds", imgs, cams)
    ds = load_nerfstudio(tmp_path / "ds", downscale=2)
    assert ds.images.shape == (2, 6, 8, 3) and (ds.cameras.width, ds.cameras.height) == (8, 6)
    # the size from transforms.json alone is the loaded one, image files not needed
    for f in (tmp_path / "ds" / "images").iterdir():
        f.unlink()
    assert nerfstudio_view_size(tmp_path / "ds", downscale=2) == (6, 8)
    assert nerfstudio_view_size(tmp_path / "ds") == (12, 17)
    for bad, message in ((0, "integer >= 1"), (13, "no pixels would be left")):
        with pytest.raises(DataError, match=message):
            nerfstudio_view_size(tmp_path / "ds", downscale=bad)
    want = imgs[:, :12, :16].reshape(2, 6, 2, 8, 2, 3).mean(axis=(2, 4))
    # 8-bit photos are held as uint8: the average is rounded to the nearest code value.
    assert ds.pixels.dtype == np.uint8
    np.testing.assert_allclose(ds.images, want, atol=0.5 / 255 + 1e-6)
    # A world point lands at half the pixel coordinates.
    p = jnp.asarray([[1.1, -1.8, 0.6]], jnp.float32)
    full, _ = cams[1].project(p)
    half, _ = ds.cameras[1].project(p)
    np.testing.assert_allclose(np.asarray(half), np.asarray(full) / 2, atol=1e-4)


def test_nerfstudio_normalisation_round_trip(tmp_path):
    cams, imgs, rng = _scene(n=9)
    pts = rng.normal(size=(12, 3)) + [1.0, -2.0, 0.5]
    # Tilt the whole scene so "up" is not +z in the file.
    tilt = np.eye(4)
    tilt[:3, :3] = camlib.look_at([0, 0, 0], [0.3, 1.0, 0.2])[:3, :3]
    tilted = transform_cameras(cams, tilt)
    save_nerfstudio(tmp_path / "ds", imgs, tilted, points=transform_points(pts, tilt),
                    point_colors=np.full((12, 3), 0.5))
    raw = load_nerfstudio(tmp_path / "ds")
    ds = load_nerfstudio(tmp_path / "ds", normalize="nerfstudio")
    centres = np.asarray(ds.cameras.center())
    assert np.abs(centres).max() == pytest.approx(1.0, abs=1e-5)
    np.testing.assert_allclose(centres.mean(axis=0), 0.0, atol=1e-5)
    up = -np.asarray(ds.cameras.rotation)[:, 1, :].mean(axis=0)  # OpenCV y is down
    np.testing.assert_allclose(up / np.linalg.norm(up), [0, 0, 1], atol=1e-5)
    assert ds.scene_scale == pytest.approx(np.cbrt(np.linalg.det(ds.world_transform[:3, :3])))
    assert ds.scene_scale == pytest.approx(1.0 / 4.0, rel=0.2)  # cameras ~4 units from their centre
    # Mapping back gives the original poses and points.
    back = ds.to_original_cameras(ds.cameras)
    np.testing.assert_allclose(np.asarray(back.world_to_camera), np.asarray(raw.cameras.world_to_camera),
                               atol=1e-5)
    np.testing.assert_allclose(ds.to_original_points(ds.points), raw.points, atol=1e-5)
    # Points project to the same pixels in both worlds.
    uv_n, _ = ds.cameras[3].project(jnp.asarray(ds.points))
    uv_r, _ = raw.cameras[3].project(jnp.asarray(raw.points))
    np.testing.assert_allclose(np.asarray(uv_n), np.asarray(uv_r), atol=1e-3)


# ---------------------------------------------------------------------------
# lens distortion

DIST = Distortion(k1=-0.12, k2=0.03, k3=0.0, k4=0.0, p1=0.002, p2=-0.001)


@settings(max_examples=30, deadline=None)
@given(hnp.arrays(np.float64, (16, 2), elements=st.floats(-0.8, 0.8)))
def test_undistort_points_inverts_distortion(xy):
    back = undistort_points(distort_points(xy, DIST), DIST)
    np.testing.assert_allclose(back, xy, atol=1e-9)


def _pattern(x, y):
    """A smooth function of normalised undistorted coordinates, three channels."""
    return np.stack([0.5 + 0.4 * np.sin(3 * x) * np.cos(2 * y), 0.5 + 0.3 * x * y,
                     0.5 + 0.4 * np.cos(4 * x + y)], -1)


def test_opencv_images_undistorted_exactly(tmp_path):
    """A lens-distorted capture of a known pattern comes back as the pinhole view."""
    w, h, fx, fy, cx, cy = 64, 48, 50.0, 52.0, 31.0, 25.0
    v, u = np.mgrid[0:h, 0:w] + 0.5
    # What the distorting lens records at pixel (u, v): the pattern at the
    # undistorted direction, found by inverting the model (independent of the
    # forward remap the loader uses).
    und = undistort_points(np.stack([(u - cx) / fx, (v - cy) / fy], -1), DIST)
    captured = _pattern(und[..., 0], und[..., 1]).astype(np.float32)
    c2w = np.eye(4)
    intr = dict(camera_model="OPENCV", fl_x=fx, fl_y=fy, cx=cx, cy=cy, w=w, h=h, **DIST._asdict())
    path = _write_dataset(tmp_path / "d", [{"file_path": "c.exr", "transform_matrix": c2w.tolist()}],
                          {"c.exr": captured}, **intr)
    img = load_nerfstudio(path, split_every=0).images[0]
    pinhole = _pattern((u - cx) / fx, (v - cy) / fy)
    interior = np.s_[4:-4, 4:-4]
    err = np.abs(img[interior] - pinhole[interior]).max()
    assert err < 4e-3  # bilinear resampling error only
    assert np.abs(captured[interior] - pinhole[interior]).max() > 10 * err  # distortion was real


# ---------------------------------------------------------------------------
# similarity transforms of Gaussians (mapping results back to the original world)

# Jitted once per module: eager jnp calls compile every primitive separately.
_covariance = jax.jit(G.covariance)
_sh_eval = jax.jit(shlib.evaluate)


def _similarity(seed):
    rng = np.random.default_rng(seed)
    rot, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    rot *= np.sign(np.linalg.det(rot))  # a proper rotation
    m = np.eye(4)
    m[:3, :3] = 2.5 * rot
    m[:3, 3] = rng.normal(size=3)
    return m, rot, 2.5


def test_transform_gaussians_geometry_and_view_dependent_colour():
    m, rot, s = _similarity(7)
    rng = np.random.default_rng(8)
    g = _random_gaussians(rng, 6, 3, capacity=6)
    g = dataclasses.replace(g, sh=g.sh * 0.3)
    t = transform_gaussians(g, m)
    np.testing.assert_allclose(np.asarray(t.means), transform_points(np.asarray(g.means), m), atol=1e-5)
    cov = np.asarray(_covariance(g.quats, g.log_scales), np.float64)
    cov_t = np.asarray(_covariance(t.quats, t.log_scales), np.float64)
    np.testing.assert_allclose(cov_t, s * s * rot @ cov @ rot.T, rtol=1e-4, atol=1e-9)
    # The colour seen along d before is the colour seen along R d after.
    d = rng.normal(size=(6, 3))
    before = np.asarray(_sh_eval(g.sh, jnp.asarray(d, jnp.float32)))
    after = np.asarray(_sh_eval(t.sh, jnp.asarray(d @ rot.T, jnp.float32)))
    np.testing.assert_allclose(after, before, atol=2e-5)
    assert np.abs(after - np.asarray(_sh_eval(g.sh, jnp.asarray(d @ rot.T, jnp.float32)))).max() > 1e-3
    # And back again.
    back = transform_gaussians(t, np.linalg.inv(m))
    for f in ("means", "log_scales", "sh"):
        np.testing.assert_allclose(np.asarray(getattr(back, f)), np.asarray(getattr(g, f)), atol=2e-5)
    np.testing.assert_allclose(np.asarray(_covariance(back.quats, back.log_scales)), cov,
                               rtol=1e-4, atol=1e-9)


def test_rotate_sh_identity_and_dc_invariant():
    rng = np.random.default_rng(9)
    sh = rng.normal(size=(4, 16, 3))
    np.testing.assert_allclose(rotate_sh(sh, np.eye(3)), sh, atol=1e-6)
    _, rot, _ = _similarity(3)
    out = rotate_sh(sh, rot)
    np.testing.assert_allclose(out[:, 0], sh[:, 0], atol=1e-6)  # DC has no direction
    # Rotations preserve the energy of each band.
    for band in range(4):
        sl = slice(band * band, (band + 1) ** 2)
        np.testing.assert_allclose(np.linalg.norm(out[:, sl], axis=1),
                                   np.linalg.norm(sh[:, sl], axis=1), rtol=1e-5)


def test_dataset_maps_gaussians_back_to_original_world(tmp_path):
    cams, imgs, rng = _scene(n=6)
    save_nerfstudio(tmp_path / "ds", imgs, cams)
    ds = load_nerfstudio(tmp_path / "ds", normalize="nerfstudio")
    g = _random_gaussians(rng, 5, 1, capacity=5)
    g = dataclasses.replace(g, means=jnp.asarray(transform_points(np.asarray(g.means), ds.world_transform),
                                                 jnp.float32))
    orig = ds.to_original_gaussians(g)
    # A Gaussian projects to the same pixel in both worlds.
    uv_n, _ = ds.cameras[2].project(g.means)
    uv_o, _ = cams[2].project(orig.means)
    np.testing.assert_allclose(np.asarray(uv_n), np.asarray(uv_o), atol=1e-3)


def test_bilinear_sample_pixel_centre_convention():
    from jaxedit.io.distortion import bilinear_sample

    img = np.arange(2 * 3 * 1, dtype=np.float32).reshape(2, 3, 1)
    u = np.array([0.5, 1.5, 1.0, 2.9, 0.2, 3.2, 1.0])
    v = np.array([0.5, 1.5, 0.5, 1.0, 0.2, 1.0, -0.1])
    out = bilinear_sample(img, u, v, fill=[-1.0])[:, 0]
    # centres, a midpoint between columns 0 and 1, edge clamping, outside -> fill
    np.testing.assert_allclose(out, [0.0, 4.0, 0.5, 3.5, 0.0, -1.0, -1.0])


@pytest.mark.parametrize("up", [[0.3, -0.2, 0.9], [0.0, 0.0, -1.0], [1e-9, 0.0, -1.0], [0, 1.0, 0]])
def test_nerfstudio_orientation_takes_mean_up_to_z(up):
    from jaxedit.io.nerfstudio import nerfstudio_world_transform

    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    # Two cameras whose OpenGL up (column 1) is `up`, at different places.
    basis = camlib.look_at([0, 0, 0], np.cross(up, [0.1, 0.7, 0.2]), up=up)[:3, :3]  # rows: cam axes
    c2w = np.tile(np.eye(4), (2, 1, 1))
    c2w[:, :3, :3] = (np.diag([1.0, -1.0, -1.0]) @ basis).T  # OpenGL columns; column 1 = up
    c2w[:, :3, 3] = [[1.0, 2.0, 3.0], [3.0, 2.0, 0.0]]
    np.testing.assert_allclose(c2w[0, :3, 1], up, atol=1e-9)
    m, s = nerfstudio_world_transform(c2w)
    r = m[:3, :3] / s
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(r) == pytest.approx(1.0)
    np.testing.assert_allclose(r @ up, [0, 0, 1], atol=1e-9)
    centres = transform_points(c2w[:, :3, 3], m)
    np.testing.assert_allclose(centres.mean(0), 0, atol=1e-12)
    assert np.abs(centres).max() == pytest.approx(1.0)
