"""Splat file formats: round trips within each format's quantisation, conventions, bad input,
and the proof by the tool people use (@playcanvas/splat-transform 3.7.0, skipped where absent)."""

from __future__ import annotations

import io
import json
import os
import shutil
import struct
import subprocess
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from jaxedit import sh as shlib
from jaxedit.errors import DataError
from jaxedit.gaussians import quat_to_rotmat
from jaxedit.io import load_ply, load_scene, save_ply, save_scene, upright
from jaxedit.io.formats import compressed_ply, sog, splat, spz
from jaxedit.io.formats.common import Splats, from_gaussians, morton_order, to_gaussians
from jaxedit.io.formats.scene import scene_format
from jaxedit.io.similarity import AXES

def ply_bytes(s: Splats) -> bytes:
    """The INRIA .ply of ``s`` (save_ply's bytes)."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        return save_ply(Path(tmp) / "s.ply", to_gaussians(s)).read_bytes()


ENCODERS = {"compressed-ply": compressed_ply.encode, "spz": spz.encode, "sog": sog.encode_sog,
            "splat": splat.encode, "ply": ply_bytes}
SUFFIX = {"ply": ".ply", "compressed-ply": ".compressed.ply", "spz": ".spz", "sog": ".sog",
          "splat": ".splat"}


def make_splats(n=700, degree=3, seed=0) -> Splats:
    """A scene whose values lie inside every format's range (SH within SPZ's [-1, 1))."""
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    sh = np.concatenate([rng.uniform(-1.5, 1.5, (n, 1, 3)), rng.uniform(-0.9, 0.9, (n, k - 1, 3))], 1)
    return Splats(rng.uniform(-2, 2, (n, 3)).astype(np.float32),
                  rng.uniform(-6, -1, (n, 3)).astype(np.float32),
                  rng.normal(size=(n, 4)).astype(np.float32),
                  rng.uniform(-5, 5, n).astype(np.float32), sh.astype(np.float32))


def sorted_like(s: Splats) -> Splats:
    return s.take(morton_order(s.means))


def rotation_error(a: np.ndarray, b: np.ndarray) -> float:
    """Largest 1 - |<a, b>| over unit quaternions (0 when equal up to sign)."""
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return float(np.max(1 - np.abs((a * b).sum(1))))


def sigmoid(x):
    return 1 / (1 + np.exp(-np.asarray(x, np.float64)))


# --- round trips ---------------------------------------------------------------------


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_compressed_ply_round_trip_within_its_quantisation(degree):
    s = make_splats(degree=degree)
    d, t = compressed_ply.decode(compressed_ply.encode(s)), sorted_like(s)
    assert d.sh.shape == t.sh.shape
    # chunk extents of at most 4 (positions) and 5 (log-scales): 11/10-bit steps
    assert np.abs(d.means - t.means).max() <= 4 / 1022
    assert np.abs(d.log_scales - t.log_scales).max() <= 5 / 1022
    assert np.abs(d.sh[:, 0] - t.sh[:, 0]).max() * shlib.C0 <= 1 / 255
    assert np.abs(sigmoid(d.opacity_logits) - sigmoid(t.opacity_logits)).max() <= 1 / 255
    assert rotation_error(d.quats, t.quats) < 2e-5
    if degree:
        assert np.abs(d.sh[:, 1:] - t.sh[:, 1:]).max() <= 8 / 256 + 1e-6


@pytest.mark.parametrize("version", [2, 3, 4])
@pytest.mark.parametrize("degree", [0, 3])
def test_spz_round_trip_within_its_quantisation(version, degree):
    s = make_splats(degree=degree)
    d = spz.decode(spz.encode(s, version=version))
    assert np.abs(d.means - s.means).max() <= 0.5 / 4096 + 1e-6
    assert np.abs(d.log_scales - s.log_scales).max() <= 1 / 32 + 1e-6
    assert np.abs(d.sh[:, 0] - s.sh[:, 0]).max() <= 0.5 / (0.15 * 255) + 1e-6
    assert np.abs(sigmoid(d.opacity_logits) - sigmoid(s.opacity_logits)).max() <= 0.5 / 255 + 1e-6
    assert rotation_error(d.quats, s.quats) < (2e-2 if version == 2 else 2e-5)
    if degree:  # round to 1/128, then 5 bits (degree 1) or 4 bits (above)
        assert np.abs(d.sh[:, 1:4] - s.sh[:, 1:4]).max() <= 4.5 / 128 + 1e-6
        assert np.abs(d.sh[:, 4:] - s.sh[:, 4:]).max() <= 8.5 / 128 + 1e-6


def test_splat_round_trip_keeps_the_dc_colour_only():
    s = make_splats(degree=2)
    d = splat.decode(splat.encode(s))
    assert d.sh.shape == (s.count, 1, 3)
    np.testing.assert_array_equal(d.means, s.means)
    assert np.abs(d.log_scales - s.log_scales).max() < 1e-6
    rgb = np.clip(0.5 + shlib.C0 * s.sh[:, 0], 0, 1)
    assert np.abs(0.5 + shlib.C0 * d.sh[:, 0] - rgb).max() <= 0.5 / 255 + 1e-6
    assert np.abs(sigmoid(d.opacity_logits) - sigmoid(s.opacity_logits)).max() <= 0.5 / 255 + 1e-6
    assert rotation_error(d.quats, s.quats) < 1e-3


@pytest.mark.parametrize("degree", [0, 2])
def test_sog_round_trip_within_its_codebooks(degree):
    s = make_splats(n=1500, degree=degree)
    # 40 distinct SH vectors: a palette of 1024 entries must hold each of them
    rest = s.sh[np.random.default_rng(2).integers(0, 40, s.count), 1:]
    s = Splats(s.means, s.log_scales, s.quats, s.opacity_logits,
               np.concatenate([s.sh[:, :1], rest], 1))
    files = sog.encode_files(s, iterations=4)
    d, t = sog.decode_files(files.__getitem__), sorted_like(s)
    log_span = np.log(3.0) * 2  # sign(x) log(|x| + 1) over [-2, 2], 16 bits
    assert np.abs(d.means - t.means).max() <= 3 * log_span / 65535
    assert np.abs(d.log_scales - t.log_scales).max() <= 5 / 128  # 256 centres over a span of 5
    assert np.abs(d.sh[:, 0] - t.sh[:, 0]).max() <= 3 / 128
    assert np.abs(sigmoid(d.opacity_logits) - sigmoid(t.opacity_logits)).max() <= 0.5 / 255 + 1e-6
    assert rotation_error(d.quats, t.quats) < 1e-4
    assert d.sh.shape == t.sh.shape
    if degree:  # up to the 256-entry codebook of the palette's values over [-0.9, 0.9]
        assert np.abs(d.sh[:, 1:] - t.sh[:, 1:]).max() <= 1.8 / 128


def test_sog_quantisers_are_the_plain_algorithms_made_fast(monkeypatch):
    """codebook_1d is the weighted 1-D Lloyd it replaces (sorted once, prefix sums); the two-level
    kmeans is seeded by its seed alone and clusters about as tightly as a flat k-means."""
    rng = np.random.default_rng(5)
    values = np.concatenate([rng.normal(0, 1, 3000), rng.exponential(4, 500)])
    centres, labels = sog.codebook_1d(values, size=64, iterations=6)
    # the reference: weighted quantiles, then Lloyd steps by bincount over all values
    flat = values.astype(np.float64)
    order = np.argsort(flat, kind="stable")
    weight = np.empty_like(flat)
    weight[order] = sog._density_weights(flat[order], 0.0)
    cum = np.cumsum(weight[order])
    ref = flat[order][np.minimum(np.searchsorted(cum, (np.arange(64) + 0.5) / 64 * cum[-1]),
                                 len(flat) - 1)]
    for _ in range(6):
        ref = np.unique(ref)
        cell = np.searchsorted((ref[1:] + ref[:-1]) / 2, flat)
        w = np.bincount(cell, weight, len(ref))
        ref = np.where(w > 0, np.bincount(cell, flat * weight, len(ref)) / np.maximum(w, 1e-300), ref)
    np.testing.assert_allclose(np.unique(centres), np.unique(ref.astype(np.float32)), rtol=1e-5,
                               atol=1e-6)
    np.testing.assert_array_equal(labels, np.searchsorted((centres[1:] + centres[:-1]) / 2, values))

    blobs = rng.normal(size=(200, 6)).astype(np.float32) * 20  # 200 blobs
    x = np.repeat(blobs, 12, axis=0) + rng.normal(0, 0.01, (2400, 6)).astype(np.float32)
    monkeypatch.setattr(sog, "FLAT_KMEANS", 0)  # two levels at this small size too
    c1, l1 = sog.kmeans(x, 200, iterations=8, seed=3)
    c2, l2 = sog.kmeans(x, 200, iterations=8, seed=3)
    np.testing.assert_array_equal(c1, c2)
    np.testing.assert_array_equal(l1, l2)
    assert len(c1) <= 200 and l1.max() < len(c1)
    # a row's label is the nearest centre of its first-level cluster: nearly always the nearest
    # of all; and the clustering is about as tight as a flat k-means'
    assert np.mean(l1 == sog._nearest(x, c1)) > 0.9
    c0, l0 = sog._lloyd(x, 200, 8, np.random.default_rng(3))
    assert ((c1[l1] - x) ** 2).sum() <= 1.5 * ((c0[l0] - x) ** 2).sum()


def test_load_scene_and_save_scene_by_name_and_header(tmp_path):
    g = to_gaussians(make_splats(n=300, degree=1))
    for fmt, suffix in SUFFIX.items():
        path = save_scene(tmp_path / f"scene{suffix}", g)
        assert scene_format(path) == fmt
        back = load_scene(path)
        assert int(back.alive.sum()) == 300
        assert back.sh.shape[1] == (1 if fmt == "splat" else 4)
    np.testing.assert_array_equal(np.asarray(load_scene(tmp_path / "scene.ply").means),
                                  np.asarray(g.means))
    # a compressed PLY under a plain .ply name is told by its header
    path = save_scene(tmp_path / "plain.ply", g, format="compressed-ply")
    assert scene_format(path) == "compressed-ply"
    assert load_scene(path).sh.shape == (300, 4, 3)
    with pytest.raises(DataError, match="compressed PLY.*load_scene"):
        load_ply(path)
    # SOG as meta.json and its textures in a folder
    meta = save_scene(tmp_path / "sog" / "meta.json", g)
    assert sorted(p.name for p in meta.parent.iterdir())[:2] == ["means_l.webp", "means_u.webp"]
    assert load_scene(meta).capacity == 300


def test_dead_slots_are_dropped_and_bad_gaussians_refused(tmp_path):
    g = to_gaussians(make_splats(n=50, degree=0))
    g = type(g)(**{**g.__dict__, "alive": g.alive.at[:10].set(False)})
    assert load_scene(save_scene(tmp_path / "a.spz", g)).capacity == 40
    quats = np.asarray(g.quats).copy()
    quats[20] = 0
    bad = type(g)(**{**g.__dict__, "quats": quats})
    with pytest.raises(DataError, match="zero rotation quaternion at alive Gaussian 10"):
        save_scene(tmp_path / "b.spz", bad)
    assert not (tmp_path / "b.spz").exists()
    means = np.asarray(g.means).copy()
    means[30, 1] = np.nan
    with pytest.raises(DataError, match="non-finite position"):
        save_scene(tmp_path / "c.compressed.ply", type(g)(**{**g.__dict__, "means": means}))


# --- conventions ---------------------------------------------------------------------


def test_rub_flip_is_the_change_of_axes_for_positions_rotations_and_sh():
    rng = np.random.default_rng(1)
    s = make_splats(n=64, degree=3)
    f = spz.flip_axes(s)
    flip = np.diag([1.0, -1.0, -1.0])
    np.testing.assert_allclose(f.means, s.means @ flip)
    rot, rot_f = np.asarray(quat_to_rotmat(s.quats)), np.asarray(quat_to_rotmat(f.quats))
    np.testing.assert_allclose(rot_f, flip @ rot @ flip, atol=1e-5)
    dirs = rng.normal(size=(64, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    colour = np.asarray(shlib.evaluate(s.sh, dirs.astype(np.float32)))
    colour_f = np.asarray(shlib.evaluate(f.sh, (dirs @ flip).astype(np.float32)))
    np.testing.assert_allclose(colour_f, colour, atol=1e-5)
    # encode with axes="rub", decode raw: the file holds flipped positions; decoding rub undoes it
    raw = spz.decode(spz.encode(s, axes="rub"))
    assert np.abs(raw.means - s.means @ flip).max() < 1e-3
    assert np.abs(spz.decode(spz.encode(s, axes="rub"), axes="rub").means - s.means).max() < 1e-3


def test_spz_sh_is_colour_interleaved_and_ply_channel_major():
    s = make_splats(n=1, degree=1)
    sh = np.zeros((1, 4, 3), np.float32)
    sh[0, 1] = [0.5, -0.5, 0.25]  # the first higher coefficient of r, g, b
    s = Splats(s.means, s.log_scales, s.quats, s.opacity_logits, sh)
    data = spz.encode(s, version=3)
    payload = __import__("gzip").decompress(data)
    sh_bytes = np.frombuffer(payload[-9:], np.uint8)
    np.testing.assert_array_equal(sh_bytes[:3], [192, 64, 160])  # r g b of coefficient 1
    cp = compressed_ply.decode(compressed_ply.encode(s))
    assert cp.sh[0, 1].tolist() == pytest.approx([0.5, -0.5, 0.25], abs=1 / 32)


def test_spz_degree_four_keeps_bands_zero_to_three():
    s = make_splats(n=20, degree=3)
    arrays = spz._arrays(s, 3)
    extra = np.full((20, 9, 3), 128, np.uint8).tobytes()  # band 4: 9 coefficients of zero
    sh4 = np.concatenate([np.frombuffer(arrays[5], np.uint8).reshape(20, 15, 3),
                          np.frombuffer(extra, np.uint8).reshape(20, 9, 3)], 1)
    header = struct.pack("<IIIBBBB", spz.MAGIC, 3, 20, 4, 12, 0, 0)
    data = __import__("gzip").compress(header + b"".join(arrays[:5]) + sh4.tobytes())
    with pytest.warns(UserWarning, match="band 4 dropped"):
        d = spz.decode(data)
    ref = spz.decode(spz.encode(s, version=3))
    np.testing.assert_array_equal(d.sh, ref.sh)


def test_morton_order_keeps_neighbours_together():
    grid = np.stack(np.meshgrid(*[np.arange(8.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    order = morton_order(np.random.default_rng(0).permutation(grid))
    assert sorted(order.tolist()) == list(range(512))
    cells = np.random.default_rng(0).permutation(grid)[order]
    # every run of 8 in Morton order is one 2x2x2 block
    assert (np.ptp(cells.reshape(64, 8, 3), axis=1) == 1).all()


# --- bad input -----------------------------------------------------------------------


def _write(tmp_path, name, data):
    path = tmp_path / name
    path.write_bytes(data)
    return path


@pytest.mark.parametrize("fmt", ["compressed-ply", "spz", "sog", "splat"])
def test_truncated_files_are_refused(tmp_path, fmt):
    data = ENCODERS[fmt](make_splats(n=300, degree=1))
    path = _write(tmp_path, "cut" + SUFFIX[fmt], data[:len(data) - 37])
    with pytest.raises(DataError, match=str(path.name)):
        load_scene(path)


def test_wrong_magic_unknown_versions_and_absurd_counts(tmp_path):
    s = make_splats(n=40, degree=0)
    v4 = bytearray(spz.encode(s))
    bad = _write(tmp_path, "magic.spz", b"NOPE" + bytes(v4[4:]))
    with pytest.raises(DataError, match="not an SPZ file"):
        load_scene(bad)
    v4[4] = 9
    with pytest.raises(DataError, match="unsupported SPZ version 9"):
        load_scene(_write(tmp_path, "version.spz", bytes(v4)))
    # v3 declaring 2^31 splats in a small file: refused before anything is allocated
    header = struct.pack("<IIIBBBB", spz.MAGIC, 3, 1 << 31, 0, 12, 0, 0)
    with pytest.raises(DataError, match="a wrong count"):
        load_scene(_write(tmp_path, "count.spz", __import__("gzip").compress(header + b"\0" * 64)))
    v4 = bytearray(spz.encode(s))
    struct.pack_into("<I", v4, 8, 41)  # the count disagrees with the streams' sizes
    with pytest.raises(DataError, match="declares .* bytes, 41 splats need"):
        load_scene(_write(tmp_path, "disagree.spz", bytes(v4)))
    cp = compressed_ply.encode(s).replace(b"element vertex 40", b"element vertex 99999999", 1)
    with pytest.raises(DataError, match="cannot hold|truncated"):
        load_scene(_write(tmp_path, "count.compressed.ply", cp))
    with pytest.raises(DataError, match="not a whole number of 32-byte"):
        load_scene(_write(tmp_path, "odd.splat", b"\0" * 33))
    files = sog.encode_files(s)
    meta = json.loads(files["meta.json"])
    for change, message in (({"version": 3}, "unsupported SOG version 3"),
                            ({"count": 10 ** 12}, "count must be an integer"),
                            ({"count": 5000}, "texture for 5000 entries")):
        files["meta.json"] = json.dumps({**meta, **change}).encode()
        with pytest.raises(DataError, match=message):
            sog.decode_files(files.__getitem__, "x.sog")


def _spz_v4(n: int, degree: int, streams: list[tuple[bytes, int]], tail: bytes = b"") -> bytes:
    """A v4 file of ``n`` splats from (compressed chunk, declared size) pairs, then ``tail``."""
    header = struct.pack("<IIIBBBBI", spz.MAGIC, 4, n, degree, 12, 0, len(streams), 32)
    toc = b"".join(struct.pack("<QQ", len(c), size) for c, size in streams)
    return header.ljust(32, b"\0") + toc + b"".join(c for c, _ in streams) + tail


def test_spz_data_beyond_the_count_is_refused_without_inflating_it(tmp_path):
    """A gzip SPZ declaring 1 splat followed by 64 MiB of zeros: refused after inflating the
    header and the one splat (not the zeros); the count/data checks of v4's streams too."""
    import gzip
    import tracemalloc

    import zstandard

    one = bytes(spz.encode(make_splats(n=1, degree=0), version=3))
    payload = gzip.decompress(one)
    bomb = _write(tmp_path, "bomb.spz", gzip.compress(payload + bytes(64 << 20), 9, mtime=0))
    assert bomb.stat().st_size < 1 << 20
    tracemalloc.start()
    try:
        with pytest.raises(DataError, match="more than the 20 bytes 1 splats need"):
            load_scene(bomb)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8 << 20, peak  # the 64 MiB were never inflated
    short = _write(tmp_path, "short.spz", gzip.compress(payload[:-3], mtime=0))
    with pytest.raises(DataError, match="truncated file or a wrong count"):
        load_scene(short)
    with pytest.raises(DataError, match="bytes after the gzip stream"):
        load_scene(_write(tmp_path, "tail.spz", one + b"\0" * 10))

    n = 40
    s = make_splats(n=n, degree=0)
    arrays = spz._arrays(s, 4)
    z = zstandard.ZstdCompressor(level=3)
    good = [(z.compress(a), len(a)) for a in arrays]
    assert spz.decode(_spz_v4(n, 0, good)).count == n  # the helper builds a valid file
    cases = [
        (_spz_v4(n, 0, good, tail=b"\0" * 9), "9 bytes after the last SPZ v4 stream"),
        # two frames where the table says one: the second's bytes are more than the count
        (_spz_v4(n, 0, [good[0], (good[1][0] * 2, n), *good[2:]]), "stream 1 holds more than"),
        # a frame whose header declares another size than the count implies
        (_spz_v4(n, 0, [good[0], (z.compress(bytes(n + 1)), n), *good[2:]]),
         "frame declares 41 bytes"),
        (_spz_v4(n, 0, [good[0], (b"junkjunk", n), *good[2:]]), "not a ZSTD frame"),
        # 2^31 splats whose streams are a few bytes: refused before any inflating
        (_spz_v4(1 << 31, 0, [(c, size // n << 31) for c, size in good]), "cannot inflate"),
    ]
    for i, (data, message) in enumerate(cases):
        with pytest.raises(DataError, match=message):
            load_scene(_write(tmp_path, f"v4_{i}.spz", data))


def test_zero_quaternion_and_nan_in_a_file_are_refused(tmp_path):
    data = bytearray(splat.encode(make_splats(n=10, degree=0)))
    data[3 * 32 + 28:3 * 32 + 32] = bytes([128] * 4)
    with pytest.raises(DataError, match="zero rotation quaternion at splat 3"):
        load_scene(_write(tmp_path, "zero.splat", bytes(data)))
    data = bytearray(splat.encode(make_splats(n=10, degree=0)))
    data[5 * 32:5 * 32 + 4] = struct.pack("<f", float("nan"))
    with pytest.raises(DataError, match="non-finite position .* at splat 5"):
        load_scene(_write(tmp_path, "nan.splat", bytes(data)))
    cp = bytearray(compressed_ply.encode(make_splats(n=10, degree=0)))
    start = cp.index(b"end_header\n") + len(b"end_header\n")
    cp[start:start + 4] = struct.pack("<f", float("nan"))  # chunk min_x
    with pytest.raises(DataError, match="non-finite position"):
        load_scene(_write(tmp_path, "nan.compressed.ply", bytes(cp)))


def test_a_zip_bomb_sog_is_refused_before_inflating(tmp_path):
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("meta.json", b"{}")
        zf.writestr("means_l.webp", b"\0" * (40 << 20))  # 40 MiB of zeros, ~40 KiB packed
    path = _write(tmp_path, "bomb.sog", buf.getvalue())
    with pytest.raises(DataError, match="zip bomb"):
        load_scene(path)
    with pytest.raises(DataError, match="not a .sog"):
        load_scene(_write(tmp_path, "junk.sog", b"PK\3\4 junk"))


def test_unknown_extension_and_missing_file(tmp_path):
    g = to_gaussians(make_splats(n=5, degree=0))
    with pytest.raises(DataError, match="unknown splat file extension"):
        save_scene(tmp_path / "scene.obj", g)
    with pytest.raises(DataError, match="file not found"):
        load_scene(tmp_path / "none.spz")


# --- proof by splat-transform --------------------------------------------------------


def splat_transform() -> list[str] | None:
    """The splat-transform command: $SPLAT_TRANSFORM_DIR (an npm prefix) or PATH; None if absent."""
    folder = os.environ.get("SPLAT_TRANSFORM_DIR")
    candidates = [Path(folder) / "node_modules" / ".bin" / "splat-transform"] if folder else []
    candidates.append(Path(shutil.which("splat-transform") or "/nonexistent"))
    for c in candidates:
        if c.exists() and shutil.which("node"):
            return [str(c)]
    return None


ST = splat_transform()
needs_st = pytest.mark.skipif(ST is None, reason="@playcanvas/splat-transform is not installed "
                                                 "(.ci/run installs it; set SPLAT_TRANSFORM_DIR)")


def run_st(*args):
    out = subprocess.run([*ST, "-q", "-w", *map(str, args)], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    return out.stdout


FORWARD = {"opacity": sigmoid, **{f"scale_{i}": np.exp for i in range(3)},
           **{f"f_dc_{i}": (lambda v: 0.5 + shlib.C0 * v) for i in range(3)}}


def raw_columns(s: Splats) -> dict[str, np.ndarray]:
    """Our reading as the PLY columns splat-transform's --stats summarises (f_rest channel-major)."""
    n = s.count
    rest = s.sh[:, 1:, :].transpose(0, 2, 1).reshape(n, -1)
    return {"x": s.means[:, 0], "y": s.means[:, 1], "z": s.means[:, 2],
            **{f"rot_{i}": s.quats[:, i] for i in range(4)},
            **{f"scale_{i}": s.log_scales[:, i] for i in range(3)},
            "opacity": s.opacity_logits, **{f"f_dc_{i}": s.sh[:, 0, i] for i in range(3)},
            **{f"f_rest_{i}": rest[:, i] for i in range(rest.shape[1])}}


@pytest.mark.slow  # starts node a few times; CI runs the slow tier every time
@needs_st
@pytest.mark.parametrize("fmt", ["ply", "compressed-ply", "spz", "sog", "splat"])
def test_splat_transform_reads_our_files_as_we_do(tmp_path, fmt):
    s = make_splats(n=600, degree=0 if fmt == "splat" else 2)
    path = _write(tmp_path, "ours" + SUFFIX[fmt], ENCODERS[fmt](s))
    ours = from_gaussians(load_scene(path))
    printed = run_st(path, "--stats", "json", "null")
    stats = json.loads(printed[printed.index("{"):])
    assert stats["numGaussians"] == 600
    assert stats["shBands"] == (0 if fmt == "splat" else 2)
    table = stats["stats"][0]
    # --stats gives raw statistics through the monotonic activations (exp scale, sigmoid, rgb)
    mine = raw_columns(ours)
    if fmt == "ply":  # the INRIA layout's normals, written as zeros
        mine.update({f"n{a}": np.zeros(ours.count, np.float32) for a in "xyz"})
    assert set(mine) == set(table["columns"])
    for i, name in enumerate(table["columns"]):
        forward = FORWARD.get(name, lambda v: v)
        # .splat: splat-transform decodes a rotation byte as b/127.5 - 1, antimatter15 as (b - 128)/128
        tol = 1e-2 if fmt == "splat" and name.startswith("rot") else 1e-4
        for stat, fn in (("mean", np.mean), ("min", np.min), ("max", np.max)):
            value = float(forward(fn(mine[name].astype(np.float64))))
            assert table["data"][stat][i] == pytest.approx(value, abs=tol, rel=1e-4), (name, stat)
    # its conversion back to an INRIA .ply holds the values our reader gives
    run_st(path, tmp_path / "back.ply")
    back = load_ply(tmp_path / "back.ply")
    np.testing.assert_allclose(np.asarray(back.means), ours.means, atol=1e-5)
    np.testing.assert_allclose(np.asarray(back.log_scales), ours.log_scales, atol=1e-5)
    np.testing.assert_allclose(np.asarray(back.sh), ours.sh, atol=1e-5)
    # .splat: the rotation byte's two decodings (above) differ by up to half a step
    assert rotation_error(np.asarray(back.quats), ours.quats) < (1e-3 if fmt == "splat" else 1e-6)


@pytest.mark.slow  # starts node a few times; CI runs the slow tier every time
@needs_st
@pytest.mark.parametrize("fmt", ["ply", "compressed-ply", "spz", "sog"])
def test_we_read_splat_transforms_files_as_it_does(tmp_path, fmt):
    s = make_splats(n=600, degree=3)
    source = save_ply(tmp_path / "scene.ply", to_gaussians(s))
    theirs = tmp_path / ("theirs" + SUFFIX[fmt])
    if fmt == "ply":  # its INRIA .ply of our scene holds our values, bit for bit
        run_st(source, theirs)
        back = from_gaussians(load_scene(theirs))
        for a, b in zip((back.means, back.log_scales, back.quats, back.opacity_logits, back.sh),
                        (s.means, s.log_scales, s.quats, s.opacity_logits, s.sh)):
            np.testing.assert_array_equal(a, b)
    run_st(*(["-g", "cpu"] if fmt == "sog" else []), source, theirs)
    run_st(theirs, tmp_path / "decoded.ply")  # their decoder's reading of their file
    ours, ref = load_scene(theirs), load_ply(tmp_path / "decoded.ply")
    assert ours.capacity == ref.capacity == 600
    np.testing.assert_allclose(np.asarray(ours.means), np.asarray(ref.means), atol=1e-5)
    np.testing.assert_allclose(np.asarray(ours.log_scales), np.asarray(ref.log_scales), atol=1e-5)
    np.testing.assert_allclose(np.asarray(ours.sh), np.asarray(ref.sh), atol=1e-5)
    np.testing.assert_allclose(sigmoid(ours.opacity_logits), sigmoid(ref.opacity_logits), atol=1e-5)
    assert rotation_error(np.asarray(ours.quats), np.asarray(ref.quats)) < 1e-6


# --- the export command --------------------------------------------------------------


def _edit_run(tmp_path):
    """A folder laid out as an edit run: schedule.json listing two subtasks' snapshots."""
    run = tmp_path / "run"
    subtasks = []
    for index, ratio in enumerate((0.5, 1.0)):
        rel = f"subtasks/{index:02d}_r{ratio:.3f}/scene.ply"
        save_ply(run / rel, to_gaussians(make_splats(n=100 + index, degree=1, seed=index)))
        subtasks.append({"index": index, "name": f"s{index}", "ratio": ratio, "snapshot": rel})
    (run / "schedule.json").write_text(json.dumps({"subtasks": subtasks}))
    return run


def test_export_command_converts_files_and_run_snapshots(tmp_path, capsys):
    from experiments.cli import main

    run = _edit_run(tmp_path)
    assert main(["export", str(run), "--select", "1", "--out", str(tmp_path / "a.spz")]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["gaussians"] == 101 and result["format"] == "spz"
    assert not (run / "selected.ply").exists()  # the run is only read
    assert load_scene(tmp_path / "a.spz").capacity == 101
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.spz", "run"]  # no record, no lock
    # --out names a file: an existing one is replaced; --output is the same flag
    assert main(["export", str(run), "--select", "0", "--output", str(tmp_path / "a.spz")]) == 0
    assert load_scene(tmp_path / "a.spz").capacity == 100
    assert main(["export", str(tmp_path / "a.spz"), "--out", str(tmp_path / "b" / "meta.json")]) == 0
    assert load_scene(tmp_path / "b" / "meta.json").capacity == 100
    assert main(["export", str(run), "--select", "0.5", "--out", str(tmp_path / "c.ply"),
                 "--format", "compressed-ply"]) == 0
    assert scene_format(tmp_path / "c.ply") == "compressed-ply"


@pytest.mark.parametrize("up", AXES)
def test_upright_turns_each_axis_to_the_viewers_up(up):
    m = upright(up)
    r = m[:3, :3]
    axis = np.eye(3)["xyz".index(up[1])] * (1.0 if up[0] == "+" else -1.0)
    np.testing.assert_array_equal(r @ axis, [0.0, -1.0, 0.0])
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0) and (m[:3, 3] == 0).all()
    assert set(np.unique(r)) <= {-1.0, 0.0, 1.0}  # a turn of the axes: exact in float32
    with pytest.raises(DataError, match="--up"):
        upright("up")


def test_export_up_turns_the_scene_and_its_view_dependent_colour(tmp_path, capsys):
    """``export --up +z``: the exported scene seen from the turned camera is the input scene
    seen from the camera, view-dependent colour included."""
    import jaxedit
    from experiments.cli import main
    from jaxedit import camera as camlib
    from jaxedit.io import transform_cameras

    s = make_splats(n=64, degree=2, seed=5)
    s = Splats(s.means * 0.3, s.log_scales - 1.2, s.quats, s.opacity_logits, s.sh)
    scene = save_ply(tmp_path / "scene.ply", to_gaussians(s))
    assert main(["export", str(scene), "--out", str(tmp_path / "up.ply"), "--up", "+z"]) == 0
    assert json.loads(capsys.readouterr().out)["up"] == "+z"
    cam = camlib.make_camera(camlib.look_at((2.0, 0.6, 0.4), (0.0, 0.0, 0.0)), width=24,
                             height=24, focal=24.0)
    turned = transform_cameras(cam, upright("+z"))
    before = np.asarray(jaxedit.render(load_scene(scene), cam).rgb)
    after = np.asarray(jaxedit.render(load_scene(tmp_path / "up.ply"), turned).rgb)
    assert before.max() > 0.1
    np.testing.assert_allclose(after, before, atol=2e-4)
    plain = np.asarray(jaxedit.render(load_scene(scene), turned).rgb)
    assert np.abs(plain - before).max() > 0.2  # the camera did turn


@pytest.mark.parametrize("argv, message", [
    (["{run}", "--output", "{tmp}/x.spz"], "without selected.ply: give --select"),
    (["{run}", "--select", "7", "--output", "{tmp}/x.spz"], "no finished subtask 7"),
    (["{tmp}/missing.spz", "--output", "{tmp}/x.spz"], "missing.spz"),
    (["{run}/schedule.json", "--output", "{tmp}/x.spz"], "not a SOG meta.json (keys subtasks;"),
    (["{run}/schedule.json", "--out", "{tmp}/x.spz"], "schedule.json: not a SOG meta.json"),
    (["{run}", "--select", "0"], "--out: give the file to write"),
    (["{run}", "--select", "0", "--out", "{tmp}"], "is a directory, expected a file name"),
    (["{run}", "--select", "0", "--output", "{tmp}/x.obj"], "unknown splat file extension"),
    (["{bad}", "--output", "{tmp}/x.ply"], "not an SPZ file"),
])
def test_export_command_answers_bad_input_in_one_line(tmp_path, capsys, argv, message):
    from experiments.cli import main

    run = _edit_run(tmp_path)
    bad = _write(tmp_path, "bad.spz", b"\0" * 64)
    args = [a.format(run=run, tmp=tmp_path, bad=bad) for a in argv]
    assert main(["export", *args]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and message in err and "\n" not in err
    assert not (tmp_path / "x.spz").exists() and not (tmp_path / "x.ply").exists()


@pytest.mark.parametrize("fmt", ["spz", "sog", "compressed-ply"])
def test_render_scene_takes_every_format(tmp_path, fmt):
    """``render --scene`` of a .spz (SOG, compressed PLY) draws what load_scene reads: the same
    frames as rendering that reading saved as an INRIA .ply."""
    from experiments.cli import main
    from jaxedit.io import read_image

    s = make_splats(n=48, degree=1, seed=3)
    s = Splats(s.means * 0.2, s.log_scales - 1.0, s.quats, s.opacity_logits, s.sh)
    scene = _write(tmp_path, "scene" + SUFFIX[fmt], ENCODERS[fmt](s))
    plain = save_ply(tmp_path / "read.ply", load_scene(scene))
    flags = ["--orbit", "2", "--size", "16", "--no-depth", "--quiet"]
    assert main(["render", "--scene", str(scene), "--out", str(tmp_path / "a"), *flags]) == 0
    assert main(["render", "--scene", str(plain), "--out", str(tmp_path / "b"), *flags]) == 0
    for name in ("frame_000.png", "frame_001.png"):
        a = read_image(tmp_path / "a" / "frames" / name)
        assert a.min() < 0.9  # something was drawn
        np.testing.assert_array_equal(a, read_image(tmp_path / "b" / "frames" / name))


def _edit_inputs(tmp_path):
    """A 16 px, 4-view dataset (one held out) and a 30-Gaussian scene to edit."""
    from jaxedit import camera as camlib
    from jaxedit import gaussians as G
    from jaxedit.io import save_nerfstudio

    rng = np.random.default_rng(0)
    cams = camlib.hemisphere(4, radius=2.2, width=16, height=16, fov_deg=50.0)
    images = rng.uniform(0.2, 0.8, size=(4, 16, 16, 3)).astype(np.float32)
    pts = rng.normal(scale=0.3, size=(30, 3)).astype(np.float32)
    data = save_nerfstudio(tmp_path / "data", images, cams, test_indices=np.array([1]),
                           points=pts, point_colors=rng.uniform(size=(30, 3)).astype(np.float32))
    scene = save_ply(tmp_path / "scene.ply", G.from_points(pts, rng.uniform(size=(30, 3)),
                                                           sh_degree=0))
    return data.parent, scene


def test_edit_export_writes_the_selected_snapshot_and_refuses_a_bad_format_first(tmp_path, capsys):
    """edit --export spz,ply: RUN/selected.spz is the selected snapshot within SPZ's steps;
    an unknown format is refused before anything is trained or written."""
    from experiments.cli import main
    from experiments.export import export_selected

    data, scene = _edit_inputs(tmp_path)
    run = tmp_path / "run"
    base = ["edit", "--data", str(data), "--scene", str(scene), "--prompt", "turn him into a bronze statue",
            "--mode", "nd",
            "--sync", "--subtasks", "2", "--max-steps", "2", "--test-views", "1",
            "--turntable-frames", "0", "--no-report", "--accept-low-identity", "--out", str(run)]
    assert main([*base, "--export", "spz,webp"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: --export: ") and "'webp'" in err and "\n" not in err
    assert not run.exists()

    assert main([*base, "--quiet", "--export", "spz,ply", "--select", "0"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["exported"] == [str(run / "selected.spz"), str(run / "selected.ply")]
    chosen = json.loads((run / "selected.json").read_text())
    assert chosen["index"] == 0
    want = from_gaussians(load_scene(run / chosen["snapshot"]))
    np.testing.assert_array_equal(from_gaussians(load_scene(run / "selected.ply")).means, want.means)
    got = from_gaussians(load_scene(run / "selected.spz"))
    assert got.count == want.count == 30
    assert np.abs(got.means - want.means).max() <= 0.5 / 4096 + 1e-6
    assert np.abs(got.log_scales - want.log_scales).max() <= 1 / 32 + 1e-6
    assert np.abs(sigmoid(got.opacity_logits) - sigmoid(want.opacity_logits)).max() <= 0.5 / 255 + 1e-6
    assert rotation_error(got.quats, want.quats) < 2e-5

    # --select-only re-exports; without --select, the last snapshot is the one
    assert main(["edit", "--out", str(run), "--select-only", "--select", "1", "--export", "splat",
                 "--quiet"]) == 0
    assert json.loads(capsys.readouterr().out)["exported"] == [str(run / "selected.splat")]
    lines = []
    assert export_selected(run, ("compressed-ply",), None, log=lines.append) == [
        str(run / "selected.compressed.ply")]
    assert lines[0].startswith(f"exported the selected snapshot as compressed-ply: {run}")
    last = json.loads((run / "schedule.json").read_text())["subtasks"][-1]
    assert json.loads((run / "selected.json").read_text())["index"] == last["index"]
    assert load_scene(run / "selected.compressed.ply").capacity == 30


# --- a web viewer draws our export ---------------------------------------------------


def viewer_settings(eye, target, fov_deg: float) -> dict:
    """SuperSplat viewer settings (splat-transform --viewer-settings) of one camera, white, no effects.

    The viewer's world is the PLY's turned 180 degrees about z ((x, y, z) -> (-x, -y, z)), its
    camera looks at ``target`` with the world's +y up, i.e. the PLY's -y.
    """
    to_viewer = np.array([-1.0, -1.0, 1.0])
    off = {"enabled": False}
    return {"version": 2, "tonemapping": "none", "highPrecisionRendering": False,
            "background": {"color": [1, 1, 1]},
            "postEffectSettings": {"sharpness": {**off, "amount": 0},
                                   "bloom": {**off, "intensity": 1, "blurLevel": 2},
                                   "grading": {**off, "brightness": 0, "contrast": 1, "saturation": 1,
                                               "tint": [1, 1, 1]},
                                   "vignette": {**off, "intensity": 0.5, "inner": 0.3, "outer": 0.75,
                                                "curvature": 1},
                                   "fringing": {**off, "intensity": 0.5}},
            "animTracks": [], "annotations": [], "startMode": "default",
            "cameras": [{"initial": {"position": (to_viewer * eye).tolist(),
                                     "target": (to_viewer * np.asarray(target)).tolist(), "fov": fov_deg}}]}


@pytest.mark.slow  # headless Chromium with software WebGL
@needs_st
def test_a_web_viewer_draws_our_spz_as_we_render_it(tmp_path):
    import jax.numpy as jnp
    from PIL import Image
    from test_viewer import CHROMIUM, DevTools

    import jaxedit
    from jaxedit import camera as camlib
    from jaxedit import metrics

    if CHROMIUM is None:
        pytest.skip("chromium is not on PATH (CI installs Debian's chromium)")
    rng = np.random.default_rng(3)
    n = 3000
    dirs = rng.normal(size=(n, 3))
    means = dirs / np.linalg.norm(dirs, axis=1, keepdims=True) * rng.uniform(0, 0.5, (n, 1)) ** (1 / 3)
    sh = np.concatenate([rng.normal(0, 0.9, (n, 1, 3)), rng.normal(0, 0.05, (n, 15, 3))], 1)
    scene = Splats(means.astype(np.float32), rng.normal(-3.2, 0.3, (n, 3)).astype(np.float32),
                   rng.normal(size=(n, 4)).astype(np.float32), rng.normal(1, 1, n).astype(np.float32),
                   sh.astype(np.float32))
    ours = save_scene(tmp_path / "scene.spz", to_gaussians(scene))
    eye, target, fov, size = np.array([1.6, 0.0, 0.0]), np.zeros(3), 50.0, 256
    (tmp_path / "settings.json").write_text(json.dumps(viewer_settings(eye, target, fov)))
    run_st("-g", "cpu", "--viewer-settings", tmp_path / "settings.json", ours, tmp_path / "viewer.html")

    cam = camlib.make_camera(camlib.look_at(eye, target, up=(0.0, -1.0, 0.0)), width=size,
                             height=size, focal=size / 2 / np.tan(np.radians(fov / 2)))
    rgb = np.clip(np.asarray(jaxedit.render(load_scene(ours), cam, background=jnp.ones(3)).rgb), 0, 1)
    profile = tmp_path / "chromium"
    profile.mkdir()
    browser = DevTools(profile, (tmp_path / "viewer.html").as_uri() + "?noui&noanim&webgl")
    try:
        browser.call("Emulation.setDeviceMetricsOverride", width=size, height=size,
                     deviceScaleFactor=1, mobile=False)
        deadline, shot = time.monotonic() + 120, None
        while time.monotonic() < deadline:  # until the splats are drawn and the frame settles
            time.sleep(2)
            img = browser.screenshot(tmp_path / "shot.png").astype(np.float32) / 255
            if shot is not None and (img < 0.9).mean() > 0.05 and np.abs(img - shot).max() < 1 / 255:
                break
            shot = img
    finally:
        browser.close()
    Image.fromarray((np.concatenate([img, rgb], 1) * 255).astype(np.uint8)).save(tmp_path / "side.png")
    # a wrong axis, rotation or SH convention draws another picture, far below this
    assert float(metrics.psnr(img, rgb)) > 25, tmp_path / "side.png"
