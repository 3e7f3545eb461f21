"""PlayCanvas compressed .ply (SuperSplat, splat-transform): chunks of 256 quantised splats.

Layout (``binary_little_endian``), as splat-transform's ``write-compressed-ply.ts`` writes it::

    element chunk ceil(N/256)   18 float: min_x min_y min_z max_x max_y max_z,
                                min/max_scale_x..z (log-scales, clamped to +-20),
                                min/max_r g b (0.5 + C0 * f_dc); readers accept 12 (no colour)
    element vertex N            uint packed_position  11/10/11 bits of x/y/z in the chunk's box
                                uint packed_rotation  2 bits: index of the largest of rot_0..3,
                                                      then the other three, v*sqrt(2)/2 + 0.5 in
                                                      10 bits each (sign flipped: largest >= 0)
                                uint packed_scale     11/10/11 bits of the log-scales
                                uint packed_color     8888: r g b in the chunk's range, sigmoid(opacity)
    element sh N (if degree>0)  uchar f_rest_0..M-1   trunc((v/8 + 0.5) * 256), channel-major

The writer orders the splats along a Morton curve (chunks then hold neighbours) and pads the last
chunk's bounds by repeating its last splat, as splat-transform does. Quantisation: a position
within 1/2046 (x, z) or 1/1022 (y) of its chunk's extent, a log-scale likewise, colour 1/510 of
the chunk's range, opacity 1/510, higher SH within 1/32 + 1/64 in [-4, 4] (clamped outside),
rotation components within about 1e-3.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from ...errors import DataError
from ...gaussians import Gaussians
from ..files import atomic_write_bytes
from ..ply import _binary_dtype, _parse_header, host_array
from .common import (C0, Splats, check_splats, from_gaussians, largest_component, logit,
                     morton_order, need, others, read_file, sigmoid, to_gaussians, unit_quats, with_largest)

CHUNK = 256
_CHUNK_FIELDS = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z",
                 "min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z",
                 "min_r", "min_g", "min_b", "max_r", "max_g", "max_b"]
_VERTEX_FIELDS = ["packed_position", "packed_rotation", "packed_scale", "packed_color"]
_REST_DEGREE = {0: 0, 9: 1, 24: 2, 45: 3}
_SQRT1_2 = math.sqrt(0.5)
#: The value of each SH byte: 0 and 255 are the ends of [-4, 4], the others bucket centres.
_SH_TABLE = ((np.concatenate([[0.0], (np.arange(1, 255) + 0.5) / 256, [1.0]]) - 0.5) * 8).astype(np.float32)


def is_compressed_ply(data: bytes) -> bool:
    """Whether ``data`` (a file's first bytes suffice) is a PLY whose vertices are packed."""
    head = data[:1 << 16]
    end = head.find(b"end_header")
    return head.startswith(b"ply") and end > 0 and b"packed_position" in head[:end]


# --- encoding ------------------------------------------------------------------------


def _unorm(v: np.ndarray, bits: int) -> np.ndarray:
    top = (1 << bits) - 1
    return np.clip(v * np.float32(top) + np.float32(0.5), 0, top).astype(np.uint32)  # floor: >= 0


def _normalise(x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(x - lo) / (hi - lo) in [0, 1] per chunk; a chunk narrower than 1e-5 maps to 0."""
    span = hi - lo
    narrow = span < 1e-5
    t = (x - lo) / np.where(narrow, np.float32(1), span)
    return np.clip(np.where(narrow, np.float32(0), t), 0, 1)


def _extremes(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[C, 1, F] minimum and maximum over each chunk of ``a`` [C, 256, F]."""
    t = np.ascontiguousarray(a.transpose(0, 2, 1))  # a reduction along the last axis is faster
    return t.min(2)[:, None, :], t.max(2)[:, None, :]


def _pack_111011(t: np.ndarray) -> np.ndarray:
    return (_unorm(t[..., 0], 11) << 21) | (_unorm(t[..., 1], 10) << 11) | _unorm(t[..., 2], 11)


def encode(s: Splats) -> bytes:
    """The compressed .ply bytes of ``s`` (Morton-ordered; finite values, non-zero quats)."""
    n, k = s.count, s.sh.shape[1]
    order = morton_order(s.means)
    # SH bytes first, then ordered: a byte a value moves less memory than a float
    # trunc((v/8 + 0.5) * 256) = floor(32 v + 128) once clipped to [0, 255]
    rest = s.sh[:, 1:, :] * np.float32(32)
    rest += np.float32(128)
    sh_bytes = np.clip(rest, 0, 255, out=rest).astype(np.uint8)
    # channel-major f_rest; np.take, not [order]: several times faster on short rows
    sh_bytes = np.take(sh_bytes.transpose(0, 2, 1).reshape(n, 3 * (k - 1)), order, axis=0)
    chunks = math.ceil(n / CHUNK)
    pad = order[np.minimum(np.arange(chunks * CHUNK), max(n - 1, 0))]  # repeat the last splat

    def chunked(a):  # [N, ...] -> [C, 256, ...], Morton-ordered
        return np.take(a, pad, axis=0).reshape((chunks, CHUNK) + a.shape[1:])

    pos, scl = chunked(s.means), chunked(s.log_scales)
    rgb = chunked(s.sh[:, 0, :]) * np.float32(C0) + np.float32(0.5)
    p_lo, p_hi = _extremes(pos)
    s_lo, s_hi = (np.clip(b, -20, 20) for b in _extremes(scl))
    c_lo, c_hi = _extremes(rgb)

    q_index, q = largest_component(unit_quats(np.take(s.quats, order, axis=0)))
    three = _unorm(others(q_index, q) * _SQRT1_2 + 0.5, 10)
    rotation = (q_index.astype(np.uint32) << 30) | (three[:, 0] << 20) | (three[:, 1] << 10) | three[:, 2]
    alpha = _unorm(sigmoid(np.take(s.opacity_logits, order)), 8)
    colour = _normalise(rgb, c_lo, c_hi).reshape(-1, 3)[:n]
    packed = np.stack([
        _pack_111011(_normalise(pos, p_lo, p_hi)).reshape(-1)[:n],
        rotation,
        _pack_111011(_normalise(scl, s_lo, s_hi)).reshape(-1)[:n],
        (_unorm(colour[:, 0], 8) << 24) | (_unorm(colour[:, 1], 8) << 16)
        | (_unorm(colour[:, 2], 8) << 8) | alpha,
    ], axis=1).astype("<u4")
    bounds = np.concatenate([p_lo, p_hi, s_lo, s_hi, c_lo, c_hi], axis=2).reshape(chunks, 18)

    header = ["ply", "format binary_little_endian 1.0", "comment written by jaxedit",
              f"element chunk {chunks}", *[f"property float {f}" for f in _CHUNK_FIELDS],
              f"element vertex {n}", *[f"property uint {f}" for f in _VERTEX_FIELDS]]
    if k > 1:
        header += [f"element sh {n}", *[f"property uchar f_rest_{i}" for i in range(3 * (k - 1))]]
    header.append("end_header\n")
    return b"".join([("\n".join(header)).encode("ascii"), bounds.astype("<f4").tobytes(),
                     packed.tobytes(), sh_bytes.tobytes()])


# --- decoding ------------------------------------------------------------------------


def _unpack_unorm(v: np.ndarray, shift: int, bits: int) -> np.ndarray:
    return ((v >> shift) & ((1 << bits) - 1)).astype(np.float32) / float((1 << bits) - 1)


def _lerp(lo, hi, t):
    return lo * (1.0 - t) + hi * t


def decode(data: bytes, where: str | os.PathLike = "compressed ply") -> Splats:
    """The splats of compressed .ply bytes, in file order. DataError for a malformed file."""
    header = _parse_header(Path(where), data)
    if header.format != "binary_little_endian":
        raise DataError(where, f"compressed PLY must be binary_little_endian, this one is {header.format}")
    elements = {e.name: e for e in header.elements}
    for name in ("chunk", "vertex"):
        if name not in elements:
            raise DataError(where, f"compressed PLY has no {name!r} element "
                                   f"(elements: {[e.name for e in header.elements]})")
    if any(e.has_lists for e in header.elements):
        raise DataError(where, "compressed PLY element with list properties")
    chunk_el, vertex_el, sh_el = elements["chunk"], elements["vertex"], elements.get("sh")
    kinds = {p.name: p.kind for p in vertex_el.properties}
    missing = [f for f in _VERTEX_FIELDS if kinds.get(f) not in ("u4", "i4")]
    if missing:
        raise DataError(where, f"compressed PLY vertex element lacks uint field(s) {', '.join(missing)}")
    chunk_kinds = {p.name: p.kind for p in chunk_el.properties}
    has_colour = all(f in chunk_kinds for f in _CHUNK_FIELDS[12:])
    for f in _CHUNK_FIELDS[:12] + (_CHUNK_FIELDS[12:] if has_colour else []):
        if chunk_kinds.get(f) not in ("f4", "f8"):
            raise DataError(where, f"compressed PLY chunk element lacks float field {f!r}")
    n = vertex_el.count
    if chunk_el.count < math.ceil(n / CHUNK):
        raise DataError(where, f"{chunk_el.count} chunks cannot hold {n} splats "
                               f"(need ceil({n}/{CHUNK}) = {math.ceil(n / CHUNK)})")
    n_rest = 0
    if sh_el is not None:
        rest = [p for p in sh_el.properties if p.name.startswith("f_rest_")]
        n_rest = len(rest)
        if n_rest not in _REST_DEGREE or [p.name for p in rest] != [f"f_rest_{i}" for i in range(n_rest)]:
            raise DataError(where, f"sh element: {n_rest} f_rest fields is not 0, 9, 24 or 45 "
                                   f"numbered from 0")
        if any(p.kind != "u1" for p in rest):
            raise DataError(where, "sh element: f_rest fields must be uchar")
        if sh_el.count != n:
            raise DataError(where, f"sh element has {sh_el.count} rows, the vertex element {n}")

    offset, tables = header.data_offset, {}
    for element in header.elements:  # sizes checked against the file before any view is made
        dtype = _binary_dtype(element, "<")
        need(where, len(data) - offset, element.count, dtype.itemsize, f"element {element.name!r}")
        tables[element.name] = np.frombuffer(data, dtype, element.count, offset)
        offset += element.count * dtype.itemsize

    bounds = tables["chunk"]

    def bound(prefix, axes):  # [N, 3]: each splat's chunk's values
        per_chunk = np.stack([np.asarray(bounds[f"{prefix}{a}"], np.float32) for a in axes], axis=1)
        return np.repeat(per_chunk[:math.ceil(n / CHUNK)], CHUNK, axis=0)[:n]

    v = tables["vertex"]
    pp, pr, ps, pc = (np.asarray(v[f], np.uint32) for f in _VERTEX_FIELDS)

    def unpack_111011(word):
        return np.stack([_unpack_unorm(word, 21, 11), _unpack_unorm(word, 11, 10),
                         _unpack_unorm(word, 0, 11)], axis=1)

    means = _lerp(bound("min_", "xyz"), bound("max_", "xyz"), unpack_111011(pp))
    log_scales = _lerp(bound("min_scale_", "xyz"), bound("max_scale_", "xyz"), unpack_111011(ps))
    three = np.stack([_unpack_unorm(pr, 20, 10), _unpack_unorm(pr, 10, 10), _unpack_unorm(pr, 0, 10)],
                     axis=1)
    quats = with_largest((pr >> 30).astype(np.int64), (three - 0.5) / _SQRT1_2)
    rgb = np.stack([_unpack_unorm(pc, 24, 8), _unpack_unorm(pc, 16, 8), _unpack_unorm(pc, 8, 8)], axis=1)
    if has_colour:
        rgb = _lerp(bound("min_", "rgb"), bound("max_", "rgb"), rgb)
    opacity = logit(_unpack_unorm(pc, 0, 8))
    k = 1 + n_rest // 3
    sh = host_array((n, k, 3))  # filled once, in memory device_put adopts
    sh[:, 0, :] = (rgb - 0.5) / C0
    if n_rest:
        columns = [sh_el.properties.index(p) for p in sh_el.properties if p.name.startswith("f_rest_")]
        b = tables["sh"].view(np.uint8).reshape(n, -1)
        b = b[:, columns[0]:columns[0] + n_rest] if columns == list(
            range(columns[0], columns[0] + n_rest)) else b[:, columns]
        sh[:, 1:, :] = _SH_TABLE[b.reshape(n, 3, k - 1).transpose(0, 2, 1)]
    s = Splats(means.astype(np.float32, copy=False), log_scales.astype(np.float32, copy=False),
               quats, opacity, sh)
    check_splats(where, s)
    return s


def load_compressed_ply(path: str | os.PathLike) -> Gaussians:
    """Read a PlayCanvas compressed .ply into Gaussians (all alive, file order)."""
    path, data = read_file(path, "a compressed .ply file")
    return to_gaussians(decode(data, path), owned=True)


def save_compressed_ply(path: str | os.PathLike, gaussians: Gaussians) -> Path:
    """Write the alive Gaussians as a PlayCanvas compressed .ply, atomically; returns the path."""
    path = Path(path)
    atomic_write_bytes(path, encode(from_gaussians(gaussians, path)))
    return path
