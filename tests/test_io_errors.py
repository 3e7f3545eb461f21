"""Bad input to jaxedit.io raises DataError naming the file/field and the problem, and
nothing is left half-written."""

from __future__ import annotations

import dataclasses
import json
import shutil
import struct
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jaxedit import camera as camlib
from jaxedit import gaussians as G
from jaxedit.errors import DataError
from jaxedit.io import (load_nerfstudio, load_ply, load_points_ply, read_image, save_nerfstudio,
                        save_ply, save_points_ply, write_image)

W, H = 6, 4


def _meta(n=2):
    frames = []
    for i in range(n):
        c2w = np.eye(4)
        c2w[:3, 3] = [i, 0.0, 3.0]
        frames.append({"file_path": f"images/f{i}.png", "transform_matrix": c2w.tolist()})
    return {"camera_model": "PINHOLE", "fl_x": 5.0, "fl_y": 5.0, "cx": 3.0, "cy": 2.0, "w": W, "h": H,
            "frames": frames}


@pytest.fixture(scope="module")
def template(tmp_path_factory):
    """A valid two-frame dataset; tests copy it and break one thing."""
    root = tmp_path_factory.mktemp("tmpl")
    for i in range(2):
        write_image(root / f"images/f{i}.png", np.full((H, W, 3), 0.25 * (i + 1)))
    (root / "transforms.json").write_text(json.dumps(_meta()))
    load_nerfstudio(root)  # it is valid
    return root


def _copy(template, dst, meta=None, text=None):
    shutil.copytree(template, dst)
    if meta is not None:
        text = json.dumps(meta)
    if text is not None:
        (dst / "transforms.json").write_text(text)
    return dst


def _raises(path, *fragments, **kw):
    with pytest.raises(DataError) as info:
        load_nerfstudio(path, **kw)
    msg = str(info.value)
    assert "\n" not in msg
    for frag in fragments:
        assert frag in msg, msg
    return msg


# ---------------------------------------------------------------------------
# transforms.json

def test_missing_and_unreadable_json(tmp_path, template):
    _raises(tmp_path, "transforms.json not found")
    _raises(tmp_path / "nope.json", "not found")
    d = _copy(template, tmp_path / "bin")
    (d / "transforms.json").write_bytes(b"\xff\xfe\x00garbage")
    _raises(d, "transforms.json", "UTF-8")
    d2 = tmp_path / "dir"
    (d2 / "transforms.json").mkdir(parents=True)
    _raises(d2, "not a file")


def test_malformed_json(tmp_path, template):
    _raises(_copy(template, tmp_path / "a", text='{"frames": [1, 2'), "malformed JSON", "line 1")
    _raises(_copy(template, tmp_path / "b", text="[1, 2]"), "top level must be a JSON object")


@pytest.mark.parametrize("edit,fragments", [
    (lambda m: m.pop("frames"), ["missing key 'frames'"]),
    (lambda m: m.update(frames=[]), ["'frames' must be a non-empty list"]),
    (lambda m: m["frames"][1].pop("transform_matrix"), ["frames[1]", "missing key 'transform_matrix'"]),
    (lambda m: m["frames"][0].pop("file_path"), ["frames[0]", "missing key 'file_path'"]),
    (lambda m: m.pop("fl_x"), ["missing intrinsic 'fl_x'"]),
    (lambda m: m.pop("h"), ["missing intrinsic 'h'"]),
    (lambda m: m.update(cx="3"), ["cx must be a number"]),
    (lambda m: m.update(w=6.5), ["w must be a whole number"]),
    (lambda m: m.update(fl_y=-1.0), ["fl_y must be positive"]),
    (lambda m: m.update(camera_model="OPENCV_FISHEYE"), ["unsupported camera model", "OPENCV_FISHEYE"]),
    (lambda m: m.update(camera_model="EQUIRECTANGULAR"), ["unsupported camera model"]),
    (lambda m: m.update(k1=0.1), ["PINHOLE declares non-zero distortion"]),
    (lambda m: m["frames"][0]["transform_matrix"][0].__setitem__(3, float("nan")),
     ["frames[0].transform_matrix", "non-finite"]),
    (lambda m: m["frames"][0]["transform_matrix"][1].__setitem__(2, float("inf")), ["non-finite"]),
    (lambda m: m["frames"][1].update(transform_matrix=np.diag([2.0, 2.0, 2.0, 1.0]).tolist()),
     ["frames[1].transform_matrix", "not a rigid transform", "orthonormal"]),
    (lambda m: m["frames"][1].update(transform_matrix=np.diag([1.0, 1.0, -1.0, 1.0]).tolist()),
     ["not a rigid transform", "determinant < 0"]),
    (lambda m: m["frames"][0].update(transform_matrix=[[1, 0, 0], [0, 1, 0]]), ["4x4"]),
    (lambda m: m["frames"][0]["transform_matrix"].__setitem__(3, [0, 0, 1, 1]), ["last row"]),
    (lambda m: m["frames"][1].update(file_path="images/missing.png"), ["frames[1].file_path",
                                                                       "not found"]),
    (lambda m: m["frames"][1].update(file_path="images/f0.png"), ["appears in more than one frame"]),
    (lambda m: m["frames"][1].update(w=8, h=4), ["different image sizes"]),
    (lambda m: m.update(ply_file_path="points.ply"), ["ply_file_path", "not found"]),
    (lambda m: m.update(ply_file_path=3), ["ply_file_path must be a non-empty string"]),
    (lambda m: m.update(train_filenames=["images/zzz.png"]), ["train_filenames", "not the file_path"]),
    (lambda m: m.update(test_filenames="images/f0.png"), ["test_filenames must be a list"]),
])
def test_bad_transforms_fields(tmp_path, template, edit, fragments):
    meta = _meta()
    edit(meta)
    _raises(_copy(template, tmp_path / "d", meta=meta), *fragments)


def test_image_size_differs_from_declared(tmp_path, template):
    meta = _meta()
    meta["w"], meta["cx"] = 7, 3.5
    _raises(_copy(template, tmp_path / "d", meta=meta), "f0.png", "image is 6x4", "w=7, h=4")


def test_undecodable_image(tmp_path, template):
    d = _copy(template, tmp_path / "d")
    (d / "images/f1.png").write_bytes(b"\x89PNG\r\n\x1a\n this is not a png")
    _raises(d, "f1.png", "cannot")


def test_bad_point_cloud(tmp_path, template):
    meta = dict(_meta(), ply_file_path="pc.ply")
    d = _copy(template, tmp_path / "d", meta=meta)
    (d / "pc.ply").write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n"
                              "property float y\nend_header\n1 2\n3 4\n")
    _raises(d, "pc.ply", "lacks field(s) z")
    (d / "pc.ply").write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n"
                              "property float y\nproperty float z\nend_header\n1 2 3\n")
    _raises(d, "pc.ply", "truncated")


def test_bad_arguments(template):
    _raises(template, "downscale", downscale=0)
    _raises(template, "normalize", normalize="pca")
    _raises(template, "background", background=(1, 1))


# Fuzzing: whatever the corruption, DataError or a successful load, nothing else.

@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_corrupted_json_text_raises_only_data_error(tmp_path_factory, template, data):
    text = json.dumps(_meta(), indent=1)
    n_edits = data.draw(st.integers(1, 4))
    for _ in range(n_edits):
        pos = data.draw(st.integers(0, len(text)))
        kind = data.draw(st.sampled_from(["delete", "insert", "truncate"]))
        if kind == "delete":
            text = text[:pos] + text[pos + data.draw(st.integers(1, 8)):]
        elif kind == "insert":
            text = text[:pos] + data.draw(st.text(alphabet='{}[]",:0123456789.-eE nultrfaNI\\x', max_size=6)) + text[pos:]
        else:
            text = text[:pos]
    d = _copy(template, tmp_path_factory.mktemp("fz") / "d", text=text)
    try:
        load_nerfstudio(d)
    except DataError:
        pass


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda children: st.lists(children, max_size=5) | st.dictionaries(st.text(max_size=6), children,
                                                                      max_size=4),
    max_leaves=20)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(key=st.sampled_from(["frames", "fl_x", "fl_y", "cx", "w", "h", "camera_model", "k1", "p2",
                            "ply_file_path", "train_filenames", "val_filenames", "file_path",
                            "transform_matrix", "frame.fl_x", "frame.h"]),
       value=json_values)
def test_wrong_json_types_raise_only_data_error(tmp_path_factory, template, key, value):
    meta = _meta()
    if key in ("k1", "p2"):
        meta["camera_model"] = "OPENCV"
    if key in ("file_path", "transform_matrix") or key.startswith("frame."):
        meta["frames"][0][key.removeprefix("frame.")] = value
    else:
        meta[key] = value
    d = _copy(template, tmp_path_factory.mktemp("fz") / "d", text=json.dumps(meta))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no silent overflow to inf either
        try:
            load_nerfstudio(d)
        except DataError:
            pass


# ---------------------------------------------------------------------------
# save_nerfstudio: nothing half-written

def test_failed_save_leaves_nothing(tmp_path):
    cams = camlib.orbit(3, radius=2.0, width=W, height=H)
    imgs = np.full((3, H, W, 3), 0.5)
    imgs[2, 0, 0, 0] = np.nan  # the last image fails, after the others were written
    with pytest.raises(DataError, match="non-finite"):
        save_nerfstudio(tmp_path / "new", imgs, cams)
    assert list(tmp_path.iterdir()) == []
    good = np.full((3, H, W, 3), 0.5)
    save_nerfstudio(tmp_path / "old", good, cams)
    before = {p: p.read_bytes() for p in (tmp_path / "old").rglob("*") if p.is_file()}
    with pytest.raises(DataError):
        save_nerfstudio(tmp_path / "old", imgs * 0.2, cams)
    after = {p: p.read_bytes() for p in (tmp_path / "old").rglob("*") if p.is_file()}
    assert before == after
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old"]


def test_save_nerfstudio_argument_errors(tmp_path):
    cams = camlib.orbit(3, radius=2.0, width=W, height=H)
    imgs = np.full((3, H, W, 3), 0.5)
    with pytest.raises(DataError, match="images"):
        save_nerfstudio(tmp_path / "a", imgs[..., :2], cams)
    with pytest.raises(DataError, match="batch of 2 cameras"):
        save_nerfstudio(tmp_path / "a", imgs[:2], cams)
    with pytest.raises(DataError, match="camera size"):
        save_nerfstudio(tmp_path / "a", np.full((3, H + 1, W, 3), 0.5), cams)
    with pytest.raises(DataError, match="unique"):
        save_nerfstudio(tmp_path / "a", imgs, cams, filenames=["a.png", "b.png", "./a.png"])
    with pytest.raises(DataError, match="relative path"):
        save_nerfstudio(tmp_path / "a", imgs, cams, filenames=["a.png", "b.png", "../c.png"])
    with pytest.raises(DataError, match="indices"):
        save_nerfstudio(tmp_path / "a", imgs, cams, test_indices=[3])
    assert not (tmp_path / "a").exists()


# ---------------------------------------------------------------------------
# 3DGS PLY

NAMES = (["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(9)]
         + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def _ply_bytes(names=NAMES, n=3, fmt="binary_little_endian", kind="float", values=None):
    header = f"ply\nformat {fmt} 1.0\nelement vertex {n}\n"
    header += "".join(f"property {kind} {name}\n" for name in names) + "end_header\n"
    values = np.arange(n * len(names), dtype=np.float32) / 7 if values is None else values
    if fmt == "ascii":
        body = "\n".join(" ".join(str(v) for v in row) for row in values.reshape(n, -1)).encode() + b"\n"
    else:
        code = {"float": "f", "double": "d", "int": "i"}[kind]
        body = struct.pack("<" + code * values.size, *values.ravel().tolist())
    return header.encode() + body


def _ply_raises(tmp_path, data, *fragments, loader=load_ply):
    path = tmp_path / "bad.ply"
    if data is not None:
        path.write_bytes(data)
    with pytest.raises(DataError) as info:
        loader(path)
    for frag in fragments:
        assert frag in str(info.value), str(info.value)
    assert "bad.ply" in str(info.value)


def test_ply_valid_baseline(tmp_path):
    (tmp_path / "ok.ply").write_bytes(_ply_bytes())
    assert load_ply(tmp_path / "ok.ply").sh_degree == 1


def test_ply_errors(tmp_path):
    _ply_raises(tmp_path, None, "file not found")
    _ply_raises(tmp_path, b"PK\x03\x04 zip file", "not a PLY file")
    _ply_raises(tmp_path, b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n", "end_header")
    _ply_raises(tmp_path, _ply_bytes(fmt="ascii"), "binary_little_endian", "ascii")
    _ply_raises(tmp_path, _ply_bytes(fmt="binary_big_endian"), "binary_little_endian")
    _ply_raises(tmp_path, _ply_bytes([n for n in NAMES if n != "opacity"]), "lacks field(s) opacity")
    _ply_raises(tmp_path, _ply_bytes([n for n in NAMES if not n.startswith("rot")]),
                "rot_0, rot_1, rot_2, rot_3")
    _ply_raises(tmp_path, _ply_bytes(NAMES + ["f_rest_9"]), "10 f_rest fields", "3((d+1)^2-1)")
    _ply_raises(tmp_path, _ply_bytes([n for n in NAMES if n != "f_rest_4"] + ["f_rest_9"]),
                "not numbered", "f_rest_4")
    _ply_raises(tmp_path, _ply_bytes()[:-5], "truncated")
    nan = np.arange(3 * len(NAMES), dtype=np.float32)
    nan[len(NAMES) + NAMES.index("scale_1")] = np.nan
    _ply_raises(tmp_path, _ply_bytes(values=nan), "non-finite scale", "vertex 1")
    inf = np.zeros(3 * len(NAMES), np.float32)
    inf[NAMES.index("f_rest_3")] = np.inf
    _ply_raises(tmp_path, _ply_bytes(values=inf), "non-finite f_dc/f_rest")
    _ply_raises(tmp_path, _ply_bytes(kind="int", values=np.zeros(3 * len(NAMES), np.int32)),
                "must be float")
    _ply_raises(tmp_path, _ply_bytes().replace(b"vertex", b"point"), "exactly one 'vertex'")
    _ply_raises(tmp_path, _ply_bytes().replace(b"property float x", b"property float y"),
                "declares property 'y' twice")
    _ply_raises(tmp_path, _ply_bytes().replace(b"float x", b"half x"), "malformed property")
    _ply_raises(tmp_path, _ply_bytes().replace(b" 1.0", b" 2.0"), "version")


def test_ply_huge_counts_fail_fast(tmp_path):
    head = b"ply\nformat binary_little_endian 1.0\nelement junk 99999999999\nproperty list uchar int v\n"
    data = head + b"element vertex 1\nproperty float x\nend_header\n" + b"\x00" * 8
    _ply_raises(tmp_path, data, "truncated", loader=load_points_ply)
    data = (b"ply\nformat ascii 1.0\nelement junk 99999999999\nproperty float a\n"
            b"element vertex 1\nproperty float x\nend_header\n1\n")
    _ply_raises(tmp_path, data, "truncated", loader=load_points_ply)


def test_points_ply_errors(tmp_path):
    _ply_raises(tmp_path, b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                b"property float z\nend_header\n1 2 nope\n", "not a number", loader=load_points_ply)
    _ply_raises(tmp_path, b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                b"property float z\nend_header\n1 nan 3\n", "non-finite", loader=load_points_ply)
    with pytest.raises(DataError, match="colors"):
        save_points_ply(tmp_path / "p.ply", np.zeros((3, 3)), np.zeros((2, 3)))
    with pytest.raises(DataError, match="points"):
        save_points_ply(tmp_path / "p.ply", np.full((3, 3), np.nan), np.zeros((3, 3)))
    assert not (tmp_path / "p.ply").exists()


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_corrupted_ply_header_raises_only_data_error(tmp_path, data):
    blob = _ply_bytes()
    end = blob.index(b"end_header\n") + len(b"end_header\n")
    header = blob[:end]
    for _ in range(data.draw(st.integers(1, 3))):
        pos = data.draw(st.integers(0, len(header)))
        kind = data.draw(st.sampled_from(["delete", "insert", "line"]))
        if kind == "delete":
            header = header[:pos] + header[pos + data.draw(st.integers(1, 10)):]
        elif kind == "insert":
            header = header[:pos] + data.draw(st.binary(max_size=6)) + header[pos:]
        else:
            words = data.draw(st.lists(st.sampled_from(
                ["element", "property", "list", "uchar", "float", "int", "vertex", "face", "x",
                 "f_rest_9", "0", "1", "99999999999", "-1", "format", "ascii", "comment"]),
                min_size=1, max_size=5))
            header = header[:pos] + (" ".join(words) + "\n").encode() + header[pos:]
    path = tmp_path / f"fz{data.draw(st.integers(0, 10**9))}.ply"
    path.write_bytes(header + blob[end:])
    for loader in (load_ply, load_points_ply):
        try:
            loader(path)
        except DataError:
            pass


def test_save_ply_refuses_non_finite_alive_values(tmp_path):
    g = G.empty(3, 0)
    g = dataclasses.replace(g, alive=np.array([True, True, False]),
                            means=np.array([[0, 0, 0], [0, np.inf, 0], [0, 0, 0]], np.float32))
    with pytest.raises(DataError, match="1 alive Gaussians have non-finite values"):
        save_ply(tmp_path / "x.ply", g)
    assert list(tmp_path.iterdir()) == []
    dead_nan = dataclasses.replace(g, means=np.array([[0, 0, 0], [0, 1, 0], [np.nan] * 3], np.float32))
    assert load_ply(save_ply(tmp_path / "y.ply", dead_nan)).capacity == 2  # dead slots not written


def test_save_ply_rejects_bad_sh(tmp_path):
    g = G.empty(2, 1)
    bad = dataclasses.replace(g, sh=np.zeros((2, 5, 3), np.float32))
    with pytest.raises(DataError, match="SH coefficients"):
        save_ply(tmp_path / "x.ply", bad)
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------
# images

def test_image_errors(tmp_path):
    with pytest.raises(DataError, match="image file not found"):
        read_image(tmp_path / "none.png")
    (tmp_path / "junk.jpg").write_bytes(b"\xff\xd8\xff\xe0 truncated jpeg")
    with pytest.raises(DataError, match="junk.jpg: cannot"):
        read_image(tmp_path / "junk.jpg")
    (tmp_path / "empty.exr").write_bytes(b"")
    with pytest.raises(DataError, match="empty.exr"):
        read_image(tmp_path / "empty.exr")
    with pytest.raises(DataError, match="unsupported image suffix"):
        write_image(tmp_path / "x.bmpx", np.zeros((2, 2, 3)))
    with pytest.raises(DataError, match="non-finite"):
        write_image(tmp_path / "x.png", np.full((2, 2, 3), np.nan))
    with pytest.raises(DataError, match=r"\[H, W, 3\]"):
        write_image(tmp_path / "x.png", np.zeros((2, 2, 5)))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty.exr", "junk.jpg"]
